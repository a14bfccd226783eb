"""The demo's cost in the benchmark: ``make demo``'s steps and the facade layer's comparison
build, each in its own process and profiled; each step's wall and CPU seconds and peak memory,
and the functions where its seconds went (all its processes together)."""

from __future__ import annotations

from pathlib import Path

from .bench_report import Report
from .demo import Step, comparison_steps, demo_steps, run_steps
from .profiling import summarise

#: Functions listed per step, by their own time.
TOP_FUNCTIONS = 12


def bench_demo(report: Report, out: Path, steps: list[Step] | None = None) -> None:
    """Run ``steps`` (default: the demo's and the comparison's, under ``out/demo``) profiled into
    ``out/demo/profile``; add the section "demo" (a row per step) and "demo profile: STEP"."""
    demo = out / "demo"
    demo.mkdir(parents=True, exist_ok=True)
    steps = demo_steps(demo) + comparison_steps(demo) if steps is None else steps
    profile = demo / "profile"
    costs = run_steps(steps, demo, profile=profile)
    report.notes["demo"] = ("`make demo`'s steps (then the layer's comparison: a build with --layer none and "
                            "eval of both), each a fresh process profiled by `bbcity --profile` (cProfile adds "
                            "its own overhead to Python-heavy code); CPU s and peak memory from the kernel's "
                            "accounting of the step's process tree (peak: its largest process)")
    for c in costs:
        report.add("demo", {"step": c.name, "wall s": c.wall_s, "cpu s": c.cpu_s, "peak MB": c.peak_bytes / 1e6,
                            "exit": c.exit_code, "command": c.command})
        section = f"demo profile: {c.name}"
        report.notes[section] = ("the functions with the most time of their own, the step's processes together "
                                 "(a pool's idle wait shows as lock acquire)")
        for f in summarise(profile / c.name, TOP_FUNCTIONS):
            report.add(section, {"function": f.function, "own s": f.own_s, "cumulative s": f.cumulative_s,
                                 "calls": f.calls})
