"""The Dask executor: the same stage code on an embedded LocalCluster gives the local pool's
bytes; failures are retried unless they are bad input; errors are one line at the command
line; no cluster process outlives its scope or a Ctrl-C."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")

from core import DataFormatError
from core.tasks import executor_workers, ordered_results, run_tasks, settled
from bbcity.cli import main as run_cli
from bbcity.executor import executor_scope, make_executor
from bbcity.executor_config import ExecutorConfig

from .test_robustness_processes import Run, bbcity, damaged_copy, one_error_line, wait_gone


@pytest.fixture(scope="module")
def dask_ex():
    """An embedded two-worker cluster shared by the unit tests of this module."""
    with executor_scope(2, kind="dask", retries=2) as ex:
        yield ex


def _worker_pids(ex) -> list[int]:
    return sorted(ex.client.run(os.getpid).values())


def _square(x: int) -> int:
    return x * x


def _fail_first(marker: str) -> str:
    """Fails on its first run (a transient fault), succeeds on the next: the marker file says which."""
    path = Path(marker)
    if not path.exists():
        path.write_text("failed once")
        raise OSError(f"{marker}: transient failure")
    return "done"


def _bad_input(counter: str) -> None:
    """Bad input: fails the same way every time; counts its runs in ``counter``."""
    with open(counter, "a") as f:
        f.write("x")
    raise DataFormatError(counter, "malformed on purpose")


def _nap_then_write(path: str, seconds: float) -> str:
    time.sleep(seconds)
    Path(path).write_text("written")
    return path


# ----------------------------------------------------------------------------------------------
# the executor interface


def test_dask_executor_runs_tasks_and_says_how_many_run_at_once(dask_ex):
    assert executor_workers(dask_ex) == 2
    assert sorted(run_tasks(_square, list(range(12)), dask_ex, progress=False)) == [i * i for i in range(12)]
    assert list(ordered_results(_square, list(range(12)), dask_ex, window=3, progress=False)) == \
        [i * i for i in range(12)]
    assert list(dask_ex.map(_square, range(5))) == [0, 1, 4, 9, 16]


def test_a_transient_failure_is_retried(dask_ex, tmp_path, monkeypatch):
    assert dask_ex.submit(_fail_first, str(tmp_path / "marker")).result() == "done"
    monkeypatch.setattr(dask_ex, "retries", 0)
    with pytest.raises(OSError, match="transient failure"):
        dask_ex.submit(_fail_first, str(tmp_path / "marker0")).result()


def test_bad_input_fails_at_once_as_itself(dask_ex, tmp_path):
    counter = tmp_path / "runs"
    with pytest.raises(DataFormatError, match="malformed on purpose") as caught:
        dask_ex.submit(_bad_input, str(counter)).result()
    assert caught.value.path == counter
    assert counter.read_text() == "x"  # run once: a bad input fails the same way again


def test_cancel_waits_for_running_tasks_like_a_pool(dask_ex, tmp_path):
    # two tasks run (one per worker), the others wait; settled cancels them all and returns
    # only once the running ones have written their files (a worker cannot stop a running task)
    futures = [dask_ex.submit(_nap_then_write, str(tmp_path / f"{i}"), 1.0) for i in range(6)]
    time.sleep(0.5)
    with pytest.raises(RuntimeError):
        with settled(futures):
            raise RuntimeError("a failure elsewhere")
    assert all(f.done() for f in futures)
    written = sorted(p.name for p in tmp_path.iterdir())
    assert 1 <= len(written) <= 3, written
    time.sleep(1.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == written  # nothing ran on after settled returned
    assert dask_ex.submit(_square, 3).result() == 9  # the cluster carries on


def test_embedded_cluster_leaves_no_process_behind(dask_ex):
    def children() -> set[int]:
        return {p.pid for p in multiprocessing.active_children()}

    before = children()  # the module's cluster
    with executor_scope(2, kind="dask") as ex:
        pids = _worker_pids(ex)
        assert len(pids) == 2 and ex.submit(_square, 4).result() == 16
    assert wait_gone(pids, 10) and children() == before
    # Ctrl-C (or SIGTERM's SystemExit) in the middle of running tasks: the workers are killed
    with pytest.raises(KeyboardInterrupt):
        with executor_scope(2, kind="dask") as ex:
            pids = _worker_pids(ex)
            futures = [ex.submit(time.sleep, 30) for _ in range(4)]
            time.sleep(0.3)
            raise KeyboardInterrupt
    assert wait_gone(pids, 10) and children() == before
    assert all(f.done() for f in futures)


def test_executor_config_refuses_what_cannot_run():
    for bad in (dict(kind="spark"), dict(workers=0), dict(workers=True), dict(retries=-1),
                dict(kind="local", scheduler="tcp://h:8786"), dict(kind="dask", scheduler=" "),
                dict(kind="dask", scheduler="tcp://h:8786", workers=2)):
        with pytest.raises(ValueError):
            ExecutorConfig(**bad)
    with pytest.raises(ValueError, match="at least 1"):
        make_executor(0, kind="dask")


# ----------------------------------------------------------------------------------------------
# the stages through dask: the same bytes as the local pool


@pytest.mark.slow
def test_recon_and_build_give_the_local_pools_bytes(tiny_dataset, tmp_path):
    from billboards.build import BuildConfig, main as build_main
    from recon.pipeline import ReconConfig, main as recon_main

    # small chunks: many build tasks, completing in any order (the facade layer and photometry
    # run in the calling process: left out)
    build = BuildConfig(chunk=32, task_chunks=1, layer=None, photometry=None)
    outputs = {}
    for kind in ("local", "dask"):
        root = tmp_path / kind
        with executor_scope(2, kind=kind) as ex:
            recon_main(ReconConfig(evaluate=False), tiny_dataset, root / "work", executor=ex, progress=False)
            build_main(build, root / "work" / "cloud.ply", tiny_dataset, root / "model", executor=ex, progress=False)
        # every file but the reports (timings); manifests name the cloud by its absolute path
        outputs[kind] = {p.relative_to(root): p.read_bytes().replace(str(root).encode(), b"ROOT")
                         for p in sorted(root.rglob("*")) if p.is_file() and not p.name.endswith("_report.json")}
    assert len(outputs["local"]) > 10 and Path("work/cloud.ply") in outputs["local"]
    assert outputs["dask"].keys() == outputs["local"].keys()
    assert [p for p in outputs["local"] if outputs["local"][p] != outputs["dask"][p]] == []


# ----------------------------------------------------------------------------------------------
# the command line


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    from data_synth import write_dataset

    from .conftest import tiny_config

    return write_dataset(tiny_config(frames=4), tmp_path_factory.mktemp("dask") / "street", progress=False)


@pytest.mark.slow
def test_bad_input_inside_a_dask_worker_is_one_line(street, tmp_path):
    dataset, png = damaged_copy(street, tmp_path / "damaged")
    result = bbcity("recon", dataset, "--out", tmp_path / "w", "--executor", "dask", "--workers", "2", "--no-eval")
    assert result.returncode == 2, result.stderr
    one_error_line(result.stderr, str(png.relative_to(tmp_path)), "truncated")
    assert "distributed" not in result.stderr and "WARNING" not in result.stderr, result.stderr
    assert not (tmp_path / "w" / "cloud.ply").exists()


@pytest.mark.slow
def test_ctrl_c_stops_the_embedded_cluster(street, tmp_path):
    run = Run("recon", street, "--out", tmp_path / "w", "--executor", "dask", "--workers", "2", "--no-eval")
    workers = run.workers(2)
    run.wait_for("stereo on")
    os.killpg(run.proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    assert run.finish(60) == 130, run.stderr
    one_error_line(run.stderr, "interrupted")
    assert wait_gone(workers, 10), "dask workers outlived the run"


def test_executor_options_contradicting_each_other_are_one_line(caplog, monkeypatch, tmp_path):
    import bbcity.dask_executor as dask_executor

    missing, out = str(tmp_path / "missing"), str(tmp_path / "out")
    for argv in (["--executor", "local", "--scheduler", "tcp://127.0.0.1:1"], ["--retries", "3"],
                 ["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"]):
        caplog.clear()
        assert run_cli(["recon", missing, "--out", out, *argv]) == 2
        errors = [r for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and "--" in errors[0].getMessage(), caplog.text
    # a scheduler that does not answer: one line naming it (before the missing dataset is read)
    monkeypatch.setattr(dask_executor, "CONNECT_TIMEOUT_S", 1.0)
    caplog.clear()
    assert run_cli(["recon", missing, "--out", out, "--scheduler", "tcp://127.0.0.1:1"]) == 2
    errors = [r for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "tcp://127.0.0.1:1" in errors[0].getMessage(), caplog.text


def test_a_port_that_accepts_and_never_answers_is_one_line_within_the_timeout(caplog, monkeypatch, tmp_path):
    """A client alone would wait without end on such a port (its timeout covers connecting only)."""
    import socket
    import threading

    import bbcity.dask_executor as dask_executor

    server = socket.create_server(("127.0.0.1", 0))
    accepted = []
    threading.Thread(target=lambda: accepted.append(server.accept()), daemon=True).start()
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    monkeypatch.setattr(dask_executor, "CONNECT_TIMEOUT_S", 1.0)
    try:
        assert run_cli(["recon", str(tmp_path / "missing"), "--out", str(tmp_path / "out"),
                        "--scheduler", address]) == 2
    finally:
        server.close()
    assert accepted, "the client never connected"
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert errors == [f"{address}: no Dask scheduler answers within 1 s (TimeoutError)"], caplog.text
