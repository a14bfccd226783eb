"""``bbcity stereo-sweep``: stereo error against seconds per frame over SGBM settings."""

from __future__ import annotations

from ..options import positive_int
from .common import io_parser


def add(sub) -> None:
    """The ``stereo-sweep`` command on the subcommands ``sub``."""
    p = io_parser(sub, "stereo-sweep", "dataset", "dataset directory with gt/", "report directory",
                  help="stereo error against seconds per frame over SGBM settings",
                  description="""Run trinocular stereo on a few frames of a dataset with ground truth for several SGBM
                                 settings; write a table, JSON and a work-precision plot.""")
    p.add_argument("--frames", type=positive_int, default=4,
                   help="frames to evaluate, spread along the path (default 4)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run the sweep; print its table."""
    from ..sweeps import stereo_sweep

    stereo_sweep(args.dataset, args.out, args.frames)
    print((args.out / "stereo_sweep.md").read_text())
    return 0
