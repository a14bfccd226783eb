"""``bbcity bench``: stage timings paired with baselines measured in the same run.

Shared machines are noisy, so every figure is the median of several runs and
every speed is reported as a ratio against a baseline timed in this process.
This module composes the sections of :attr:`BenchConfig.scene <bbcity.bench_config.BenchConfig>`
(:mod:`bbcity.bench_synthesis`, :mod:`bbcity.bench_pipeline`, :mod:`bbcity.bench_stages`,
:mod:`bbcity.bench_render`, :mod:`bbcity.bench_city`, :mod:`bbcity.bench_executor`,
:mod:`bbcity.bench_demo`) into one
:class:`~bbcity.bench_report.Report`.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict
from pathlib import Path

from recon.work import Work

from .bench_city import bench_city
from .bench_config import BenchConfig
from .bench_demo import bench_demo
from .bench_executor import bench_executor
from .bench_pipeline import HOLDOUT, bench_pipeline
from .bench_render import bench_decode_and_cull, bench_novel_views, bench_town
from .bench_report import Report
from .bench_stages import bench_billboards, bench_octree, bench_stereo, build_rows
from .bench_synthesis import bench_synthesis

logger = logging.getLogger(__name__)


def run_bench(cfg: BenchConfig, out: Path) -> Path:
    """Run the benchmark sections of ``cfg.scene`` and write the report to ``out``.

    The street sections run the pipeline on a ``street_length`` street at each scale
    (:mod:`bbcity.bench_pipeline`), then measure stereo, textures, rendering and novel
    views on the 1× run (the billboard sections on ``cfg.work`` instead when given).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = Report(settings={**asdict(cfg), "rig": asdict(cfg.rig())})
    start = time.perf_counter()
    timings = report.settings.setdefault("section_seconds", {})

    def section(name: str, fn, *args) -> None:
        t0 = time.perf_counter()
        fn(*args)
        timings[name] = time.perf_counter() - t0
        logger.info("bench: %s took %.0f s", name, timings[name])

    if cfg.scene in ("all", "street"):
        section("synthesis", bench_synthesis, cfg, report)
        runs: list = []
        section("pipeline", lambda: runs.append(bench_pipeline(cfg, report, out)))
        run = runs[0]
        section("octree", bench_octree, cfg, report)
        section("stereo", bench_stereo, cfg, report, run.dataset, out)
        work = Path(cfg.work) if cfg.work is not None else run.work
        section("textures", bench_billboards, cfg, report, out, work, cfg.work is not None)
        if cfg.work is None:
            build_rows(report, json.loads((run.model / "build_report.json").read_text()))
        model = out / "model" if cfg.work is not None else run.model
        dataset = Work.open(work).dataset()
        length = json.loads((dataset / "dataset.json").read_text())["synth"]["street"]["length"]
        section("rendering", bench_decode_and_cull, cfg, report, model, float(length), dataset)
        section("novel views", bench_novel_views, cfg, report, run.dataset, run.work, run.model, out, HOLDOUT)
    if cfg.scene in ("all", "town"):
        section("town", bench_town, cfg, report)
    if cfg.scene == "city":  # not in "all": an hour on this machine
        section("city", bench_city, cfg, report, out, cfg.city_scales)
    if cfg.scene == "demo":  # not in "all": make demo's steps and the comparison build, profiled (15 minutes)
        section("demo", bench_demo, report, out)
    if cfg.scene == "executor" or (cfg.scene == "all" and not cfg.quick):
        # (a quick run of everything leaves it out: two more recons and builds, whose outputs'
        # byte identity the executor's own tests check; --scene executor --quick runs it)
        section("executor", bench_executor, cfg, report, out)
    report.settings["total_seconds"] = time.perf_counter() - start
    report.write(out)
    logger.info("wrote %s", out / "report.md")
    return out
