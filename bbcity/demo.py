"""The demo: the default street from synthesis to evaluation, each step a ``bbcity`` command
in its own process, with what each cost.

:func:`demo_steps` is the one list of the demo's commands (``make demo`` runs them through
``bbcity demo``; ``bbcity bench --scene demo`` runs them profiled, with the comparison build
:func:`comparison_steps`). :func:`run_steps` prints each command before it runs and its cost
after (wall and CPU seconds of the command and its workers, the peak memory of its largest
process, from the kernel's accounting of the ended process tree), and writes them to
``OUT/demo_report.json``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from core.fileio import write_json

logger = logging.getLogger("bbcity")

#: Every HOLDOUT-th frame of the demo street is held out of the model and scored by eval.
HOLDOUT = 10
#: Frames of the demo's fly-through.
FLYTHROUGH_FRAMES = 300
#: The lower CPU priority of a step beside the one its group waits for (a nice increment).
SIDE = 10


@dataclass(frozen=True)
class Step:
    """One command of the demo: its name (a file name: its profile's directory) and its
    ``bbcity`` arguments; ``fresh``: a directory the step writes whole, removed before it runs
    (the web site: export refuses an existing one); ``alongside``: it runs at the same time as
    the step before it (both read what earlier steps wrote; neither reads what the other
    writes, save a file replaced whole, whose reader sees it before or after); ``after``: an
    alongside step starts when this step of its group has ended (a queue on the core the
    group's first step leaves free), not at once; ``nice``: the step runs at this much lower CPU
    priority (its workers too), so that the step of its group the others wait for is not slowed
    by it: it takes the cycles that step leaves idle."""

    name: str
    argv: tuple[str, ...]
    fresh: Path | None = None
    alongside: bool = False
    after: str | None = None
    nice: int = 0

    def __post_init__(self):
        if self.after is not None and not self.alongside:
            raise ValueError(f"step {self.name}: 'after' needs 'alongside'")


@dataclass(frozen=True)
class StepCost:
    """What a step cost: when it started (seconds after the first step), its wall and CPU
    seconds (its process tree), the peak resident memory of its largest process (bytes) and its
    exit code."""

    name: str
    command: str
    start_s: float
    wall_s: float
    cpu_s: float
    peak_bytes: int
    exit_code: int


def demo_steps(out: Path) -> list[Step]:
    """The demo's commands, writing under ``out``: synth, recon, build (and the cloud's score beside it),
    fly-through, web site, eval."""
    street, work, model = out / "street", out / "work", out / "model"
    return [
        Step("synth", ("synth", "street", "--out", str(street))),
        # the cloud scored against the ground truth while the build runs: the build's serial stretches leave a
        # core free (the build reads the report at its start; the score replaces it whole, the same but for it)
        Step("recon", ("recon", str(street), "--out", str(work), "--no-eval")),
        Step("build", ("build", str(work), "--out", str(model), "--holdout", str(HOLDOUT))),
        Step("recon-eval", ("recon", str(street), "--out", str(work), "--eval-only"), alongside=True, nice=SIDE),
        # then eval's Poisson baseline, kept beside the cloud: eval takes it made
        Step("mesh", ("mesh", str(work / "cloud.ply")), alongside=True, after="recon-eval", nice=SIDE),
        # the three read the model and write apart: side by side, the two cores are kept busy (eval, the longest,
        # first)
        Step("render", ("render", str(model), "--path", "capture", "--frames", str(FLYTHROUGH_FRAMES),
                        "--out", str(out / "flythrough.mp4")), nice=SIDE),
        Step("export", ("export", "web", str(model), "--out", str(out / "site")), fresh=out / "site", alongside=True,
             nice=SIDE),
        # the model against Poisson depth 10 (the comparison's eval adds depths 8, 9 and 11)
        Step("eval", ("eval", str(model), str(street), "--cloud", str(work / "cloud.ply"), "--workprecision-depths",
                      "--out", str(out / "eval")), alongside=True),
    ]


def comparison_steps(out: Path) -> list[Step]:
    """The facade layer's comparison on the demo's reconstruction (after :func:`demo_steps`): a
    model without the layer (``--layer none``) and eval scoring both."""
    street, work = out / "street", out / "work"
    billboards = out / "model-billboards"
    return [
        Step("build-billboards", ("build", str(work), "--out", str(billboards), "--holdout", str(HOLDOUT),
                                  "--layer", "none")),
        Step("eval-layer", ("eval", str(out / "model"), str(street), "--cloud",
                                   str(work / "cloud.ply"), "--billboards-only", str(billboards),
                                   "--out", str(out / "eval-layer"))),
    ]


def run_steps(steps: list[Step], out: Path, profile: Path | None = None) -> list[StepCost]:
    """Run ``steps`` in order, each as ``python -m bbcity.cli`` in its own process (profiled into
    ``profile/<step>`` when given), a step marked ``alongside`` at the same time as the one
    before it; stop after the first group of steps in which one failed. Each step's cost is
    logged and all are written to ``out/demo_report.json``, in the order they ended. Ctrl-C reaches the running steps
    too (one process group): they are waited for, then KeyboardInterrupt propagates."""
    groups: list[list[Step]] = []
    for step in steps:
        if step.alongside and groups:
            groups[-1].append(step)
        else:
            groups.append([step])
    costs: list[StepCost] = []
    t0 = time.perf_counter()
    for group in groups:
        running = {}
        try:
            for step in group:
                if step.after is None:
                    running.update(_start(step, profile))
            while running:  # in the order they end: each one's wall time is its own
                pid, status, usage = os.wait4(-1, 0)
                if pid not in running:
                    continue
                step, shown, started, child = running.pop(pid)
                child.returncode = os.waitstatus_to_exitcode(status)
                cost = StepCost(step.name, shown, started - t0, time.perf_counter() - started,
                                usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024, child.returncode)
                costs.append(cost)
                write_json(out / "demo_report.json", {"steps": [asdict(c) for c in costs]})
                if cost.exit_code == 0:
                    logger.info("<== %s: %.1f s wall, %.1f s CPU, peak memory %.2f GB", step.name, cost.wall_s,
                                cost.cpu_s, cost.peak_bytes / 1e9)
                    for queued in group:
                        if queued.after == step.name:
                            running.update(_start(queued, profile))
        except KeyboardInterrupt:
            for _, _, _, child in running.values():
                child.wait()  # it got the same Ctrl-C: let it clean up
            raise
        if any(c.exit_code != 0 for c in costs):
            break
    return costs


def _start(step: Step, profile: Path | None) -> dict[int, tuple]:
    """Start ``step`` as ``python -m bbcity.cli`` (profiled into ``profile/<step>`` when given):
    {pid: (step, the command as shown, start time, Popen)}."""
    if step.fresh is not None and step.fresh.exists():
        shutil.rmtree(step.fresh)
    argv = [sys.executable, "-m", "bbcity.cli"]
    if profile is not None:
        argv += ["--profile", str(profile / step.name)]
    shown = "bbcity " + shlex.join(step.argv)
    logger.info("==> %s%s", shown, f" (alongside, after {step.after})" if step.after
                else " (alongside the step before)" if step.alongside else "")
    child = subprocess.Popen(argv + list(step.argv))
    if step.nice:  # before it starts its workers (they inherit it): it is still importing
        with contextlib.suppress(ProcessLookupError):
            os.setpriority(os.PRIO_PROCESS, child.pid, os.getpriority(os.PRIO_PROCESS, 0) + step.nice)
    return {child.pid: (step, shown, time.perf_counter(), child)}


def cost_table(costs: list[StepCost]) -> str:
    """The steps' costs as a Markdown table, with a total row (wall: from the first step's start
    to the last one's end, steps that ran alongside each other counted once)."""
    lines = ["| step | started at s | wall s | CPU s | peak memory GB |", "|---|---|---|---|---|"]
    lines += [f"| {c.name} | {c.start_s:.1f} | {c.wall_s:.1f} | {c.cpu_s:.1f} | {c.peak_bytes / 1e9:.2f} |"
              for c in costs]
    lines.append(f"| **total** | | {max((c.start_s + c.wall_s for c in costs), default=0.0):.1f} | "
                 f"{sum(c.cpu_s for c in costs):.1f} | {max((c.peak_bytes for c in costs), default=0) / 1e9:.2f} |")
    return "\n".join(lines) + "\n"
