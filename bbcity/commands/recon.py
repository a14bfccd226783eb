"""``bbcity recon``: stereo on a dataset (a rig of 1, 2 or 3 cameras) → a fused coloured point
cloud in a WORK directory."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from ..options import MIN_LENGTH, UsageError, float_range, holdout, length, nonnegative_int, positive_int
from .common import OwnOutput, command_executor, io_parser, logger, workers_parent

#: What a recon's WORK directory holds: a recon writes its cloud there and resumes what it finds.
# (cache: what is made of the cloud and kept beside it, e.g. bbcity mesh's Poisson meshes)
WORK_FILES = OwnOutput(re.compile(r"cloud\.ply|cloud_tiles\.json|poses\.json|recon_report\.json|sfm|spill|cache"),
                       "a recon work directory's", "a recon writes its cloud there and resumes what it finds")


def add(sub) -> None:
    """The ``recon`` command on the subcommands ``sub``."""
    from recon.fusion import FusionConfig
    from recon.pipeline import ReconConfig
    from recon.trinocular import TrinocularConfig

    p = io_parser(
        sub, "recon", "dataset", "dataset directory (rig.json, poses.json, images/)", "work directory",
        help="stereo (rig of 1, 2 or 3 cameras) → fused coloured point cloud (cloud.ply)",
        description="""Rectify each camera pair, match by SGBM with a left-right check (three pairs that must
                       agree: the widest pair's), fuse the pairs per frame
                       (three cameras: three pairs that must agree; two: one pair; one: neighbouring frames), merge
                       all frames by voxel hashing, remove outliers and write WORK/cloud.ply and
                       WORK/recon_report.json (with accuracy and completeness when the dataset has ground truth).""",
        parents=[workers_parent()])
    p.add_argument("--poses", choices=("given", "sfm", "colmap"), default=ReconConfig.poses,
                   help="pose source: given (poses.json, the default), sfm (pycolmap) or colmap (the COLMAP model "
                        "at --colmap-model)")
    p.add_argument("--colmap-model", type=Path, default=None, metavar="DIR",
                   help="with --poses colmap: the COLMAP model directory (cameras, images .txt or .bin)")
    p.add_argument("--preset", default="accurate", help="stereo preset: fast, balanced or accurate (default: accurate)")
    p.add_argument("--voxel-size", type=length, default=FusionConfig.voxel_size,
                   help=f"fused cloud resolution in metres (default {FusionConfig.voxel_size:g})")
    p.add_argument("--min-depth", type=length, default=None, help="nearest depth to match, metres")
    p.add_argument("--max-depth", type=float_range(MIN_LENGTH, lo_open=False, allow_inf=True), default=None,
                   help="farthest depth to match, metres (inf: no limit)")
    p.add_argument("--frame-stride", type=positive_int, default=ReconConfig.frame_stride,
                   help=f"use every n-th frame (default {ReconConfig.frame_stride})")
    p.add_argument("--wls", action="store_true", help="WLS-filter the disparities (smoother, slower)")
    p.add_argument("--min-agree", type=int, choices=(2, 3), default=TrinocularConfig.min_agree,
                   help=f"three-camera rigs: pairs that must agree on a pixel's depth (default "
                        f"{TrinocularConfig.min_agree}; 2 keeps more, with more errors); a two-camera rig has one "
                        "pair, one camera its own rule")
    p.add_argument("--holdout", type=holdout, default=ReconConfig.holdout,
                   help=f"leave every n-th frame out of the cloud, for `bbcity eval` on held-out views (default "
                        f"{ReconConfig.holdout}: none; 4 uses 75 %% of the frames); `bbcity build` of this WORK "
                        "leaves the same frames out")
    p.add_argument("--max-image-size", type=nonnegative_int, default=ReconConfig.max_image_size,
                   help="stereo and SfM features work on images at most this many pixels along their longer side "
                        f"(default {ReconConfig.max_image_size}; 0: full size); a pair that does not fit in the "
                        "memory free is matched at half that, and half again")
    p.add_argument("--no-eval", action="store_true", help="skip the ground-truth evaluation")
    p.add_argument("--eval-only", action="store_true",
                   help="score the cloud an earlier run with --no-eval left in WORK against the dataset's ground "
                        "truth, with that run's settings, into its recon_report.json (the demo scores it while the "
                        "build runs)")
    p.set_defaults(func=run, check_options=config_from_args, own_output=WORK_FILES)


def config_from_args(args):
    """The ReconConfig the ``recon`` options describe (UsageError for a bad combination)."""
    from recon.fusion import FusionConfig
    from recon.pipeline import POSE_SOURCES, ReconConfig
    from recon.stereo import PRESETS
    from recon.trinocular import TrinocularConfig

    if args.eval_only and args.no_eval:
        raise UsageError("--eval-only and --no-eval contradict each other")
    if args.poses not in POSE_SOURCES:
        raise UsageError(f"--poses takes {', '.join(POSE_SOURCES)}; got {args.poses!r}")
    if args.poses == "colmap" and args.colmap_model is None:
        raise UsageError("--poses colmap needs --colmap-model DIR (the COLMAP model directory)")
    if args.poses != "colmap" and args.colmap_model is not None:
        raise UsageError(f"--colmap-model goes with --poses colmap, not --poses {args.poses}")
    if args.preset not in PRESETS:
        raise UsageError(f"unknown --preset {args.preset!r}; choose from {', '.join(PRESETS)}")
    stereo = PRESETS[args.preset]
    overrides = {k: v for k, v in (("min_depth", args.min_depth), ("max_depth", args.max_depth)) if v is not None}
    if args.wls:
        overrides["wls"] = True
    stereo = dataclasses.replace(stereo, **overrides)
    return ReconConfig(trinocular=TrinocularConfig(stereo=stereo, min_agree=args.min_agree),
                       fusion=FusionConfig(voxel_size=args.voxel_size),
                       poses=args.poses, colmap_model=None if args.colmap_model is None else str(args.colmap_model),
                       frame_stride=args.frame_stride, max_image_size=args.max_image_size or None,
                       evaluate=not args.no_eval, holdout=args.holdout)


def run(args) -> int:
    """Reconstruct; log the cloud and the report written."""
    from recon.pipeline import main as recon_main

    conf = config_from_args(args)
    if args.eval_only:
        from recon.pipeline import score_work
        logger.info("scored %s into %s", args.out / "cloud.ply", score_work(args.dataset, args.out))
        return 0
    with command_executor(args) as ex:
        cloud = recon_main(conf, args.dataset, args.out, executor=ex)
    logger.info("wrote %s and %s", cloud, cloud.with_name("recon_report.json"))
    return 0
