"""``bbcity sampling-eval``: texture error of occlusion-aware against naive sampling, measured
against the synthetic ground truth."""

from __future__ import annotations

from ..options import length, positive_int
from .common import logger, work_dataset, work_report_parser


def add(sub) -> None:
    """The ``sampling-eval`` command on the subcommands ``sub``."""
    from billboards.octree import OctreeConfig

    p = work_report_parser(sub, "sampling-eval", "dataset directory with gt/ (default: WORK's)",
                           help="texture error of occlusion-aware vs naive sampling against ground truth",
                           description="""On a synthetic dataset: sample billboards near occluders and at random with
                                          occlusion-aware and naive nearest-frame sampling, render the ground-truth
                                          texture of every sampled direction cut to the voxel's slab, and report PSNR
                                          (all texels, and the texels an occluder hides from the first camera).""")
    p.add_argument("--count", type=positive_int, default=200, help="billboards per set (default 200)")
    p.add_argument("--voxel-size", type=length, default=OctreeConfig.voxel_size,
                   help=f"billboard/voxel edge in metres (default {OctreeConfig.voxel_size:g})")
    p.set_defaults(func=run)


def run(args) -> int:
    """Compare the samplings on WORK's cloud; write sampling_eval.json and .md."""
    from billboards.evaluate import compare_sampling, markdown
    from billboards.octree import OctreeConfig
    from core.fileio import write_bytes, write_json

    dataset = work_dataset(args)
    report = compare_sampling(dataset, args.work / "cloud.ply", OctreeConfig(voxel_size=args.voxel_size),
                              count=args.count)
    write_json(args.out / "sampling_eval.json", report)
    write_bytes(args.out / "sampling_eval.md", markdown(report).encode())
    logger.info("wrote %s", args.out / "sampling_eval.md")
    return 0
