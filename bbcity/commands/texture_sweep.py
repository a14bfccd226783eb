"""``bbcity texture-sweep``: eigen-texture bytes and decode PSNR against build time, on
billboards of a recon WORK."""

from __future__ import annotations

import re

from ..options import MAX_TILE, int_range, positive_int
from .common import OwnOutput, logger, work_dataset, work_report_parser

#: What a texture sweep's report directory holds: its report files replace those there.
REPORT_FILES = OwnOutput(re.compile(r"texture_sweep\.(json|md|png)"), "a texture sweep's",
                         "its report files replace those there")


def add(sub) -> None:
    """The ``texture-sweep`` command on the subcommands ``sub``."""
    p = work_report_parser(sub, "texture-sweep", "dataset directory (default: WORK's)",
                           help="eigen-texture bytes and decode PSNR against build time",
                           description="""Sample neighbouring billboards from the middle of the street once per texel
                                          size, compress them under fixed ranks 0–16, contribution ratios, error
                                          bounds and quantisation modes; write a table, JSON and a work-precision
                                          plot.""")
    p.add_argument("--count", type=positive_int, default=1024, help="billboards to sample (default 1024)")
    p.add_argument("--tiles", type=int_range(1, MAX_TILE), nargs="+", default=[8, 16, 32],
                   help="texel sizes (default 8 16 32)")
    p.set_defaults(func=run, own_output=REPORT_FILES)


def run(args) -> int:
    """Run the sweep on WORK's cloud; log the table written."""
    from ..sweeps import texture_sweep

    dataset = work_dataset(args)
    texture_sweep(args.work / "cloud.ply", dataset, args.out, count=args.count, tiles=tuple(args.tiles))
    logger.info("wrote %s", args.out / "texture_sweep.md")
    return 0
