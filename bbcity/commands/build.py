"""``bbcity build``: a fused cloud and its images → a billboard model (octree, angular
sampling, PCA, atlases)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from recon.work import Work

from ..executor import default_workers
from ..options import GL_MAX_SIZE, MAX_LENGTH, MAX_TILE, MIN_LENGTH, UsageError, build_bytes, check_memory, \
    dimension, float_range, holdout, int_range, length, nonnegative_float, nonnegative_int, positive_int
from .common import command_executor, logger, refuse_out_over, work_dataset, workers_parent


def _on_off(value) -> str:
    """A config's default as an on/off option's: "off" when it is False or None (no config), else "on"."""
    return "off" if value is None or value is False else "on"


def add(sub) -> None:
    """The ``build`` command on the subcommands ``sub``."""
    from billboards.build_config import BuildConfig
    from billboards.geometry import MAX_SPLIT
    from billboards.octree import MAX_DEPTH, MAX_MIN_POINTS

    d = BuildConfig()
    octree, sampling, directions, layer, fit = d.octree, d.sampling, d.sampling.directions, d.layer, d.fit
    p = sub.add_parser(
        "build", help="cloud + images → billboard model (octree, angular sampling, PCA, atlases)",
        description="""Voxelise the fused cloud with an octree, give each voxel a view-facing billboard, sample its
                       texture in d directions from the captured images (occlusion-aware), compress each billboard's
                       stack by PCA into eigen-textures and pack them into atlas pages. Writes MODEL/ (manifest.json,
                       .npy arrays, atlas pages) and MODEL/build_report.json.""",
        parents=[workers_parent()])
    p.add_argument("work", type=Path, nargs="?", default=None,
                   help="recon work directory (cloud.ply; recon_report.json names the dataset)")
    p.add_argument("--out", type=Path, required=True, help="model directory (replaced atomically)")
    p.add_argument("--cloud", type=Path, default=None, help="a PLY/PCD cloud of your own (instead of WORK/cloud.ply)")
    p.add_argument("--images", type=Path, default=None, help="dataset directory with rig.json, poses.json and "
                   "images/ (default: the one WORK was built from)")
    p.add_argument("--poses", type=Path, default=None,
                   help="a poses.json to use instead of the dataset's (default: WORK/poses.json when the recon "
                        "computed its poses, e.g. --poses sfm on a photo folder: the cloud is in their frame)")
    p.add_argument("--texture-source", choices=("images", "points"), default=d.source,
                   help="sample textures from the images (default) or splat the cloud's own points")
    p.add_argument("--voxel-size", type=length, default=octree.voxel_size,
                   help=f"billboard/voxel edge in metres (default {octree.voxel_size:g})")
    p.add_argument("--depth", type=int_range(0, MAX_DEPTH, "a Morton code's bits"), default=None,
                   help="octree depth instead of --voxel-size")
    p.add_argument("--min-points", type=int_range(1, MAX_MIN_POINTS), default=octree.min_points,
                   help=f"points a voxel needs to get a billboard (default {octree.min_points})")
    p.add_argument("--directions", type=positive_int, default=directions.count,
                   help=f"yaw directions per billboard (default {directions.count})")
    p.add_argument("--spacing", type=float_range(0.0, 360.0), default=directions.spacing_deg,
                   help=f"degrees between directions (default {directions.spacing_deg:g})")
    p.add_argument("--pitches", type=float_range(-90.0, 90.0, hi_open=True), nargs="+",
                   default=list(directions.pitches_deg),
                   help=f"pitch rows in degrees (default {' '.join(f'{x:g}' for x in directions.pitches_deg)})")
    p.add_argument("--pitched-quads", action="store_true", help="quads also tilt toward the viewer's elevation")
    p.add_argument("--tile", type=int_range(1, MAX_TILE), default=sampling.tile,
                   help=f"texels per billboard side, at most --page-size and {MAX_TILE} (default {sampling.tile})")
    p.add_argument("--naive", action="store_true", help="nearest-frame sampling without the occlusion test")
    p.add_argument("--fill-below", choices=("on", "off"), default=_on_off(sampling.fill_below),
                   help="a billboard's texel whose ray points down shows the image where neither the cloud nor the "
                        "facade layer (the ground, the facades) lies behind it (a sparse far leaf; default "
                        f"{_on_off(sampling.fill_below)})")
    p.add_argument("--ratio", type=float_range(0.0, 1.0), default=None,
                   help="PCA cumulative contribution ratio (default: the PcaConfig's)")
    p.add_argument("--max-error", type=nonnegative_float, default=None,
                   help="PCA RMS error bound in 8-bit units (default: the PcaConfig's; 0 turns the rule off)")
    p.add_argument("--rank", type=nonnegative_int, default=None,
                   help="fixed rank for every billboard (overrides the rules)")
    p.add_argument("--max-rank", type=nonnegative_int, default=None, help="largest rank (default: the PcaConfig's)")
    p.add_argument("--tile-mode", choices=("u8", "f16"), default=d.tile_mode,
                   help=f"eigen image precision (default {d.tile_mode})")
    p.add_argument("--coef-mode", choices=("f32", "f16", "u8"), default=d.coef_mode,
                   help=f"coefficient precision (default {d.coef_mode})")
    p.add_argument("--page-size", type=dimension, default=d.page_size,
                   help=f"atlas page edge in texels, at most {GL_MAX_SIZE} (default {d.page_size})")
    p.add_argument("--holdout", type=holdout, default=None,
                   help="leave every n-th frame's images out of the textures (for `bbcity eval`; default: the "
                        "recon's --holdout, else 0: none)")
    p.add_argument("--layer", choices=("facades+ground", "facades", "ground", "none"),
                   default="+".join(k for k in ("facades", "ground") if getattr(layer, k)) or "none",
                   help="the facade layer under the billboards: slits on the facades found in the EPIs and/or "
                        "blocks on flat ground (default both; none: billboards only)")
    # bounded like a street's length: a larger block overflows the octree's grid, an error that
    # blamed the voxel size (issue 35)
    p.add_argument("--block-size", type=float_range(MIN_LENGTH, MAX_LENGTH, lo_open=False), default=None,
                   help="edge of the layer's blocks in metres (default: the voxel size)")
    p.add_argument("--ground-reach", type=nonnegative_float, default=layer.ground_reach,
                   help="continue the ground across gaps up to this wide (m) between ground cells where nothing "
                        "stands; blocks no camera saw get a texture synthesised from ground nearby, marked in the "
                        f"model (0: off; default {layer.ground_reach:g})")
    res = layer.resolution
    p.add_argument("--ground-splits", type=int, choices=range(0, MAX_SPLIT + 1), default=res.max_split,
                   help="halve ground blocks up to this many times where the capture saw them finer than their "
                        f"texels (a texel at most {res.texel_pixels:g} capture pixels wide; 0: never; default "
                        f"{res.max_split})")
    p.add_argument("--side-walls", choices=("on", "off"), default=_on_off(layer.side_walls),
                   help="slits on the walls at the ends of the facades (a building's side seen from the path), "
                        f"instead of billboards (default {_on_off(layer.side_walls)})")
    p.add_argument("--wall-reach", type=nonnegative_float, default=layer.wall_depth.reach,
                   help="grow side walls up to this far (m) beyond their deepest cloud point where the images show "
                        f"them against the sky (0: off; default {layer.wall_depth.reach:g})")
    p.add_argument("--wall-rise", type=nonnegative_float, default=layer.wall_depth.rise,
                   help="grow side walls up to this far (m) above their top where the images show them against "
                        f"the sky (0: off; default {layer.wall_depth.rise:g})")
    p.add_argument("--kerbs", choices=("on", "off"), default=_on_off(layer.kerbs),
                   help="a fixed face on each step between two ground levels (a kerb) instead of billboards "
                        f"(default {_on_off(layer.kerbs)})")
    p.add_argument("--planes", choices=("on", "off"), default=_on_off(d.planes),
                   help="a leaf whose points lie on one vertical plane (a wall, a car's side) gets a fixed quad in "
                        f"that plane instead of a view-facing billboard (default {_on_off(d.planes)})")
    p.add_argument("--photometry", choices=("on", "off"), default=_on_off(d.photometry),
                   help="estimate per-image exposure and white-balance gains from the overlaps and divide them "
                        f"out before sampling textures (default {_on_off(d.photometry)})")
    p.add_argument("--fit", choices=("on", "off"), default=_on_off(fit),
                   help="fit the sampled textures to the training images through the rendering, then compress "
                        f"(default {_on_off(fit)})")
    p.add_argument("--fit-seconds", type=nonnegative_float, default=fit.seconds,
                   help=f"wall-clock budget of the fit's iterations in seconds (default {fit.seconds:g}; "
                        "each tile's with --tile-metres)")
    p.add_argument("--fit-alpha", choices=("on", "off"), default=_on_off(fit.alpha),
                   help="let the training images decide which texels of the facade layer and the ground are shown "
                        "and which are seen through, before the colours are fitted (default "
                        f"{_on_off(fit.alpha)}; a tiled build keeps the sampled alpha)")
    p.add_argument("--tile-metres", type=length, default=None,
                   help="build a model set of square tiles this wide, one at a time, so that memory does not grow "
                        "with the street (a whole number of voxels; the viewer pages them; a killed build resumes "
                        "its unfinished tiles; default: one model)")
    p.set_defaults(func=run, check_options=check)


def build_config_from_args(args):
    """The BuildConfig the ``build`` options describe."""
    from billboards.build_config import BuildConfig
    from billboards.fit import FitConfig
    from billboards.geometry import DirectionConfig
    from billboards.layer import LayerConfig
    from billboards.octree import OctreeConfig
    from billboards.pca import PcaConfig
    from billboards.photometry import PhotometryConfig
    from billboards.planes import PlaneConfig
    from billboards.resolution import ResolutionConfig
    from billboards.sampling import SamplingConfig
    from billboards.wall_depth import WallDepthConfig

    pca = PcaConfig()
    overrides = {}
    if args.ratio is not None:
        overrides["ratio"] = args.ratio
    if args.max_error is not None:
        overrides["max_error"] = args.max_error if args.max_error > 0 else None
    if args.rank is not None:
        overrides["fixed_rank"] = args.rank
    if args.max_rank is not None:
        overrides["max_rank"] = args.max_rank
    pca = dataclasses.replace(pca, **overrides)
    directions = DirectionConfig(count=args.directions, spacing_deg=args.spacing, pitches_deg=tuple(args.pitches),
                                 pitched_quads=args.pitched_quads)
    octree = OctreeConfig(voxel_size=None if args.depth is not None else args.voxel_size, depth=args.depth,
                          min_points=args.min_points)
    sampling = SamplingConfig(tile=args.tile, directions=directions, occlusion=not args.naive,
                              fill_below=args.fill_below == "on")
    layer = None if args.layer == "none" else LayerConfig(
        facades="facades" in args.layer, ground="ground" in args.layer, block_size=args.block_size,
        ground_reach=args.ground_reach, side_walls=args.side_walls == "on", kerbs=args.kerbs == "on",
        resolution=ResolutionConfig(max_split=args.ground_splits),
        wall_depth=WallDepthConfig(reach=args.wall_reach, rise=args.wall_rise))
    return BuildConfig(octree=octree, sampling=sampling, pca=pca, source=args.texture_source,
                       tile_mode=args.tile_mode, coef_mode=args.coef_mode, page_size=args.page_size,
                       holdout=args.holdout, layer=layer, planes=PlaneConfig() if args.planes == "on" else None,
                       photometry=PhotometryConfig() if args.photometry == "on" else None,
                       fit=FitConfig(seconds=args.fit_seconds, alpha=args.fit_alpha == "on") if args.fit == "on"
                       else None,
                       tile_metres=args.tile_metres)


def check(args) -> None:
    """UsageError when the ``build`` options contradict each other or the atlas pages, or
    when the workers' sampled textures would not fit in the available memory."""
    if args.tile > args.page_size:
        raise UsageError(f"--tile {args.tile} is larger than the atlas page (--page-size {args.page_size})")
    if args.tile_metres is not None:
        if args.depth is not None:
            raise UsageError("--tile-metres needs --voxel-size, not --depth (tiles share one voxel grid)")
        voxels = args.tile_metres / args.voxel_size
        if abs(voxels - round(voxels)) > 1e-9:
            raise UsageError(f"--tile-metres {args.tile_metres:g} is not a whole number of voxels "
                             f"(--voxel-size {args.voxel_size:g})")
    d = args.directions * len(args.pitches)
    if d > args.page_size:  # a billboard's coefficient row (d texels) fills one atlas page row at most
        raise UsageError(f"--directions × --pitches = {d} directions do not fit an atlas page row "
                         f"(--page-size {args.page_size})")
    # every config validates its values; the work directory's --holdout is not read yet
    conf = build_config_from_args(argparse.Namespace(**{**vars(args), "holdout": args.holdout or 0}))
    n = args.workers or default_workers()
    check_memory(build_bytes(args.tile, d, conf.chunk, n, conf.chunk * conf.task_chunks if conf.fit else 0),
                 f"build --tile {args.tile} with {d} directions and {n} workers")


def run(args) -> int:
    """Build the model from WORK (or ``--cloud``); log its size, compression and quality."""
    from billboards.build import main as build_main

    if args.work is None and args.cloud is None:
        raise UsageError("give a recon WORK directory or --cloud")
    cloud = args.cloud or args.work / "cloud.ply"
    refuse_out_over(args.out, [cloud] + ([args.work / "recon_report.json"] if args.work is not None else []))
    dataset = work_dataset(args) if args.work is not None and args.texture_source == "images" else args.images
    refuse_out_over(args.out, [p for p in (dataset, args.poses) if p is not None])
    if args.holdout is None:
        args.holdout = Work.open(args.work).holdout() if args.work is not None and args.cloud is None else 0
    poses = args.poses
    if poses is None and args.work is not None and args.cloud is None and dataset is not None:
        poses = Work.open(args.work).poses_file()  # WORK's cloud lies in the frame of the poses its recon used
    conf = build_config_from_args(args)
    with command_executor(args) as ex:
        result = build_main(conf, cloud, dataset, args.out, executor=ex, poses=poses)
    r = result.report
    psnr = r["psnr"]["decoded_rgb_opaque_db"]  # None: no opaque texel measured
    logger.info("%d billboards, compression %.1f× at %s dB (decoded RGB), %.1f s → %s", r["billboards"],
                r["compression_ratio"], "n/a" if psnr is None else f"{psnr:.2f}", r["total_s"], result.model)
    return 0
