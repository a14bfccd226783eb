"""``bbcity bench`` section: the Dask executor against the local process pool.

The same recon and build of one benchmark street run through the local pool and through
an embedded Dask ``LocalCluster`` of as many single-threaded worker processes, one after
the other in this process, alternating which goes first. Each stage is timed as the
command runs it: the executor started, the stage, the executor stopped. The outputs of
the two must be the same bytes (the reports aside: they hold timings and paths).
"""

from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path

from .bench_config import BenchConfig
from .bench_pipeline import street_config
from .bench_report import Report
from .executor import executor_scope

logger = logging.getLogger(__name__)

#: The executors compared, the baseline first.
KINDS = ("local", "dask")

_SECTION = "Executors: Dask against the local pool"


def _run(kind: str, workers: int, dataset: Path, root: Path) -> tuple[float, float]:
    """Recon and build of ``dataset`` under ``root`` with the ``kind`` executor; wall seconds
    of each, its executor's start and stop included."""
    from billboards.build import BuildConfig, main as build_main
    from recon.pipeline import ReconConfig, main as recon_main

    t0 = time.perf_counter()
    with executor_scope(workers, kind=kind) as ex:
        recon_main(ReconConfig(evaluate=False), dataset, root / "work", executor=ex, progress=False)
    t1 = time.perf_counter()
    with executor_scope(workers, kind=kind) as ex:
        build_main(BuildConfig(), root / "work" / "cloud.ply", dataset, root / "model", executor=ex, progress=False)
    return t1 - t0, time.perf_counter() - t1


def outputs(root: Path) -> dict[Path, bytes]:
    """Every file under ``root`` but the stage reports, by relative path; ``root`` itself
    written as ROOT (a model names its cloud by its absolute path)."""
    return {p.relative_to(root): p.read_bytes().replace(str(root.resolve()).encode(), b"ROOT")
            for p in sorted(root.rglob("*")) if p.is_file() and not p.name.endswith("_report.json")}


def bench_executor(cfg: BenchConfig, report: Report, out: Path) -> None:
    """Wall time of recon + build of a ``cfg.street_length`` street with each executor of
    :data:`KINDS` (``cfg.workers`` workers, median of ``cfg.repeats``), the ratio of their
    speeds, and whether their outputs are byte-identical."""
    from data_synth import write_dataset

    root = Path(out) / "executor"
    dataset = root / "street"
    with executor_scope(cfg.workers) as ex:
        write_dataset(street_config(cfg, cfg.street_length), dataset, executor=ex, progress=False)
    times: dict[str, list[tuple[float, float]]] = {kind: [] for kind in KINDS}
    for repeat in range(cfg.repeats):
        for kind in KINDS if repeat % 2 == 0 else KINDS[::-1]:  # the machine drifts: alternate the order
            times[kind].append(_run(kind, cfg.workers, dataset, root / kind))
            logger.info("executor %s: recon %.1f s, build %.1f s", kind, *times[kind][-1])
    files = {kind: outputs(root / kind) for kind in KINDS}
    differ = sorted(str(p) for p in files["local"].keys() | files["dask"].keys()
                    if files["local"].get(p) != files["dask"].get(p))
    total = {kind: statistics.median(r + b for r, b in times[kind]) for kind in KINDS}
    names = {"local": "local process pool (baseline)", "dask": "Dask LocalCluster"}
    for kind in KINDS:
        report.add(_SECTION, {"executor": names[kind], "workers": cfg.workers,
                              "recon s": statistics.median(r for r, _ in times[kind]),
                              "build s": statistics.median(b for _, b in times[kind]), "total s": total[kind],
                              "speed vs local": total["local"] / total[kind],
                              "outputs": "baseline" if kind == "local" else
                              "byte-identical" if not differ else f"differ: {', '.join(differ[:5])}"})
    report.notes[_SECTION] = (
        f"Recon and build of a {cfg.street_length:g} m street, each stage timed as the command runs it: the "
        f"executor started (the pool's or the cluster's {cfg.workers} worker processes, one thread each), the "
        f"stage, the executor stopped; medians of {cfg.repeats} runs alternating which goes first. 'speed vs "
        f"local' is the pool's total time over this one's. Outputs compared byte for byte: the cloud, every "
        f"array and manifest of the model ({len(files['local'])} files; the reports, which hold timings, aside).")
