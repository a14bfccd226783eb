"""The demo's steps, their costs and the profile of a command (``bbcity --profile``).

The demo itself takes minutes; these tests run its machinery on a tiny street and check
that the demo's own command lines are what the real parser accepts.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bbcity.bench_demo import bench_demo
from bbcity.bench_report import Report
from bbcity.cli import build_parser
from bbcity.demo import Step, comparison_steps, cost_table, demo_steps, run_steps
from bbcity.profiling import ProcessCost, profile_table, summarise

ROOT = Path(__file__).resolve().parents[1]
TINY = ("synth", "street", "--length", "6", "--frames", "2", "--width", "48", "--height", "64", "--workers", "2")


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def test_every_demo_step_is_a_command_the_parser_accepts(tmp_path):
    parser = build_parser()
    steps = demo_steps(tmp_path) + comparison_steps(tmp_path)
    assert [s.name for s in steps] == ["synth", "recon", "build", "recon-eval", "mesh", "render", "export", "eval",
                                       "build-billboards", "eval-layer"]
    # recon leaves the score of its cloud to the step beside the build, then eval's mesh is made there
    assert "--no-eval" in steps[1].argv and "--eval-only" in steps[3].argv and steps[3].alongside
    assert steps[4].alongside and steps[4].after == "recon-eval"
    for step in steps:
        args = parser.parse_args(list(step.argv))
        assert (args.out if args.out is not None else args.cloud).is_relative_to(tmp_path), step
    assert parser.parse_args(list(steps[4].argv)).cloud == parser.parse_args(list(steps[7].argv)).cloud
    # the comparison reads what the demo wrote, and scores the layer against the model without it
    assert "--billboards-only" in comparison_steps(tmp_path)[1].argv


def test_profile_covers_the_process_and_its_workers(tmp_path):
    prof = tmp_path / "prof"
    r = subprocess.run([sys.executable, "-m", "bbcity.cli", "--profile", str(prof), *TINY, "--out",
                        str(tmp_path / "s")], capture_output=True, text=True, env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    names = sorted(p.name.split("-")[0] for p in prof.glob("*.prof"))
    assert names == ["main", "worker", "worker"]
    rows = summarise(prof)
    assert rows and rows == sorted(rows, key=lambda f: f.own_s, reverse=True)
    # the frames were cast in the workers: their functions are in the merged table
    assert any("data_synth/raycast.py" in f.function for f in summarise(prof, top=10_000))
    table = (prof / "profile.md").read_text()
    assert table.startswith("| function | own s |") and table.count("\n") == len(rows) + 2
    # every command ends with its cost
    cost = [line for line in r.stderr.splitlines() if "bbcity: synth: " in line]
    assert len(cost) == 1 and " s wall, " in cost[0] and " s CPU, peak memory " in cost[0]


def test_summarise_of_no_profile_is_empty(tmp_path):
    assert summarise(tmp_path) == []
    assert profile_table([]).count("\n") == 2


def test_process_cost_counts_this_process():
    import time

    start = time.perf_counter()
    sum(i * i for i in range(200_000))
    cost = ProcessCost.since(start)
    assert cost.wall_s > 0 and cost.cpu_s > 0 and cost.peak_bytes > 10_000_000
    assert cost.line().endswith("GB") or "largest child process" in cost.line()


def test_steps_run_in_order_with_their_costs_and_stop_at_a_failure(tmp_path, caplog):
    street = tmp_path / "street"
    steps = [Step("synth", (*TINY, "--out", str(street))),
             Step("recon", ("recon", str(tmp_path / "no such dataset"), "--out", str(tmp_path / "work"))),
             Step("never", ("synth", "street", "--out", str(tmp_path / "never")))]
    costs = run_steps(steps, tmp_path)
    assert [c.name for c in costs] == ["synth", "recon"]
    assert costs[0].exit_code == 0 and costs[1].exit_code == 2
    assert costs[0].cpu_s > 0 and costs[0].wall_s >= costs[0].cpu_s / 4  # two workers at most, and the parent
    assert costs[0].peak_bytes > 50_000_000  # a Python process with numpy and Open3D
    assert (street / "dataset.json").is_file() and not (tmp_path / "never").exists()
    report = json.loads((tmp_path / "demo_report.json").read_text())
    assert [s["name"] for s in report["steps"]] == ["synth", "recon"]
    assert report["steps"][0]["command"].startswith("bbcity synth street --length 6")
    assert cost_table(costs).splitlines()[-1].startswith("| **total** |")


def test_fresh_step_replaces_its_directory(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    (site / "old").write_text("x")
    costs = run_steps([Step("check", ("synth", "street", "--out", str(site), "--length", "nan"), fresh=site)],
                      tmp_path)
    assert costs[0].exit_code == 2 and not site.exists()


def test_bench_demo_reports_each_step_and_its_profile(tmp_path):
    report = Report(settings={})
    bench_demo(report, tmp_path, steps=[Step("synth", (*TINY, "--out", str(tmp_path / "demo" / "street")))])
    (row,) = report.sections["demo"]
    assert row["step"] == "synth" and row["exit"] == 0 and row["wall s"] > 0 and row["peak MB"] > 50
    functions = report.sections["demo profile: synth"]
    assert 0 < len(functions) <= 12 and all(f["own s"] >= 0 for f in functions)
    report.write(tmp_path / "report")
    assert "## demo profile: synth" in (tmp_path / "report" / "report.md").read_text()


def test_a_step_alongside_runs_with_the_one_before(tmp_path):
    steps = [Step("first", (*TINY, "--out", str(tmp_path / "a"))),
             Step("second", ("synth", "street", "--out", str(tmp_path / "b"), "--length", "-1"), alongside=True),
             Step("never", ("synth", "street", "--out", str(tmp_path / "never")))]
    costs = run_steps(steps, tmp_path)
    assert [c.name for c in costs] == ["second", "first"]  # in the order they ended
    second, first = costs
    assert (first.exit_code, second.exit_code) == (0, 2) and not (tmp_path / "never").exists()
    assert second.start_s < first.start_s + first.wall_s  # started before the first ended
    assert second.wall_s < first.wall_s  # its own time, not the time until the first ended
    total = cost_table(costs).splitlines()[-1].split("|")
    assert float(total[3]) == pytest.approx(max(c.start_s + c.wall_s for c in costs), abs=0.1)
    assert [s.alongside for s in demo_steps(tmp_path)] == [False, False, False, True, True, False, True, True]


def test_a_step_after_another_starts_when_it_has_ended(tmp_path):
    bad = ("synth", "street", "--length", "-1")
    steps = [Step("first", (*TINY, "--out", str(tmp_path / "a"))),
             Step("second", (*bad, "--out", str(tmp_path / "b")), alongside=True),
             Step("third", (*bad, "--out", str(tmp_path / "c")), alongside=True, after="first"),
             Step("never", (*bad, "--out", str(tmp_path / "d")), alongside=True, after="second")]
    costs = {c.name: c for c in run_steps(steps, tmp_path)}
    assert set(costs) == {"first", "second", "third"}  # a step after one that failed never starts
    first, second, third = costs["first"], costs["second"], costs["third"]
    assert second.start_s < first.start_s + first.wall_s  # alongside: at once
    assert third.start_s >= first.start_s + first.wall_s  # after: once the first has ended
    with pytest.raises(ValueError, match="needs 'alongside'"):
        Step("x", bad, after="first")


def test_a_step_with_nice_runs_at_lower_priority(tmp_path):
    """The priority is read off the running step's process (/proc), as the kernel schedules it."""
    import threading

    out = tmp_path / "low"
    seen: set[int] = set()
    done = threading.Event()

    def watch():
        while not done.is_set():
            for proc in Path("/proc").glob("[0-9]*"):
                try:
                    if str(out) in (proc / "cmdline").read_bytes().decode(errors="replace"):
                        seen.add(int((proc / "stat").read_text().rsplit(")", 1)[1].split()[16]))
                except (OSError, ValueError, IndexError):
                    pass
            time.sleep(0.02)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        costs = run_steps([Step("low", (*TINY, "--out", str(out)), nice=7)], tmp_path)
    finally:
        done.set()
        watcher.join()
    assert costs[0].exit_code == 0
    assert min(19, os.getpriority(os.PRIO_PROCESS, 0) + 7) in seen  # (the kernel caps it at 19)
