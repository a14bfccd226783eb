"""``bbcity bench``: the stages measured against same-run baselines, written as a report."""

from __future__ import annotations

from pathlib import Path

from ..options import MAX_CITY_SCALE, MAX_LENGTH, MAX_REPEATS, float_range, int_range, positive_int


def add(sub) -> None:
    """The ``bench`` command on the subcommands ``sub``."""
    from ..bench_config import SCENES, BenchConfig

    full, quick = BenchConfig(), BenchConfig.quick_config()
    p = sub.add_parser("bench", help="measure the stages against same-run baselines; write a report",
                       description="""Run the whole pipeline on the standard scenes and write report.md, report.json
                                      and PNG plots to --out: the stage table, octree, stereo, textures, rendering
                                      (street and town culling), novel views and scaling (1×, 2×, 4× street length).
                                      Every speed is paired with a baseline measured in the same run.""")
    p.add_argument("--out", type=Path, required=True, help="report directory")
    p.add_argument("--scene", choices=SCENES, default=full.scene,
                   help="street: the pipeline and everything measured on its model; town: culling on the town; "
                        "executor: recon and build through the local pool and through Dask; city (not in all): "
                        "streets of --city-scales × --street-length built tile by tile and paged by the viewer; demo "
                        "(not in all): make demo's steps and the facade layer's comparison build, each profiled: "
                        "its wall and CPU seconds, peak memory and the functions where the seconds went")
    p.add_argument("--city-scales", type=int_range(1, MAX_CITY_SCALE), nargs="+", default=None,
                   help="street lengths of the city runs in multiples of --street-length (default "
                        f"{' '.join(map(str, full.city_scales))})")
    p.add_argument("--gpu-budget", type=positive_int, default=None, metavar="MB",
                   help=f"city: the viewer's GPU budget ({full.city_gpu_budget_mb}); memory is flat from 1× only if "
                        "the 1× street fills it")
    p.add_argument("--lazy", action="store_true",
                   help="city: datasets cast on demand (kilobytes on disk, no ground-truth depth), for long streets")
    p.add_argument("--quick", action="store_true", help="small inputs, for a smoke run (under 3 minutes)")
    p.add_argument("--repeats", type=int_range(1, MAX_REPEATS), default=None,
                   help=f"timings are the median of this many runs ({full.repeats}; quick {quick.repeats})")
    p.add_argument("--street-length", type=float_range(1.0, MAX_LENGTH, lo_open=False), default=None,
                   help=f"metres of the 1× street of the pipeline runs ({full.street_length:g}; quick "
                        f"{quick.street_length:g})")
    p.add_argument("--work", type=Path, default=None,
                   help="a recon work directory (e.g. of the default street): the billboard build, texture and "
                        "rendering sections use its cloud and images instead of the 1× street's")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run the benchmark sections of ``--scene`` into ``--out``."""
    from ..bench import run_bench
    from ..bench_config import BenchConfig

    given = {"scene": args.scene, "work": None if args.work is None else str(args.work)}
    if args.repeats is not None:
        given["repeats"] = args.repeats
    if args.street_length is not None:
        given["street_length"] = args.street_length
    if args.city_scales is not None:
        given["city_scales"] = tuple(args.city_scales)
    if args.gpu_budget is not None:
        given["city_gpu_budget_mb"] = args.gpu_budget
    if args.lazy:
        given["city_lazy"] = True
    run_bench(BenchConfig.quick_config(**given) if args.quick else BenchConfig(**given), args.out)
    return 0
