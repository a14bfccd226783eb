"""Runs under real process trouble: an error inside a worker, Ctrl-C, a killed run, two runs
into one output, a work directory used from another directory.

Each test drives the real ``bbcity`` command in a subprocess (its own session, so that a
signal reaches its whole process group as a terminal's would) with two pool workers.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from core import DataFormatError
from core.workdir import exclusive_output, lock_path, owned_output, pid_alive, sweep_output
from bbcity.executor import WorkerPool, executor_scope
from bbcity.worker import WorkerError
from data_synth import write_dataset
from recon.work import Work
from recon.poses import MissingFramesError

from .conftest import tiny_config

ROOT = Path(__file__).resolve().parents[1]


def bbcity(*args, cwd=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bbcity.cli", *map(str, args)], cwd=cwd or ROOT, text=True,
                          capture_output=True, timeout=timeout, env=_env())


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def _default_sigint() -> None:
    """In the child: Ctrl-C as in a terminal, also when the tests run as a background job
    (which starts with SIGINT ignored, and a child inherits that)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Run:
    """A ``bbcity`` command running in its own session; its stderr is collected as it comes."""

    def __init__(self, *args, cwd=None):
        self.proc = subprocess.Popen([sys.executable, "-m", "bbcity.cli", *map(str, args)], cwd=cwd or ROOT,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True, env=_env(), preexec_fn=_default_sigint)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stderr), daemon=True)
        self._reader.start()

    @property
    def stderr(self) -> str:
        return "".join(self.lines)

    def wait_for(self, text: str, timeout: float = 120.0) -> None:
        end = time.monotonic() + timeout
        while text not in self.stderr:
            assert self.proc.poll() is None, f"ended before {text!r}:\n{self.stderr}"
            assert time.monotonic() < end, f"no {text!r} in {timeout} s:\n{self.stderr}"
            time.sleep(0.05)

    def workers(self, count: int, timeout: float = 60.0) -> list[int]:
        """Wait until the run has ``count`` pool workers; their pids."""
        end = time.monotonic() + timeout
        while True:
            pids = [p for p in children(self.proc.pid) if b"multiprocessing" in cmdline(p)]
            if len(pids) >= count:
                return pids
            assert self.proc.poll() is None and time.monotonic() < end, f"no {count} workers:\n{self.stderr}"
            time.sleep(0.05)

    def finish(self, timeout: float = 300.0) -> int:
        code = self.proc.wait(timeout)
        self._reader.join(10)
        return code


def children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return found


def cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def gone(pid: int) -> bool:
    """Dead or a zombie (whoever adopted it may not reap at once)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return not pid_alive(pid)
    return "\nState:\tZ" in status


def wait_until(condition, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.05)


def wait_gone(pids: list[int], timeout: float = 30.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all(gone(p) for p in pids):
            return True
        time.sleep(0.1)
    return False


def hidden_temporaries(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob(".*") if not p.name.endswith(".lock"))


def one_error_line(stderr: str, *needles: str) -> None:
    assert "Traceback" not in stderr and "BrokenProcessPool" not in stderr, stderr
    errors = [line for line in stderr.splitlines() if " ERROR " in line]
    assert len(errors) == 1, stderr
    for needle in needles:
        assert needle in errors[0], stderr


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """A 12-frame tiny street (recon takes a few seconds with two workers)."""
    return write_dataset(tiny_config(frames=6), tmp_path_factory.mktemp("proc") / "street", progress=False)


@pytest.fixture(scope="module")
def work(street):
    """The street's recon, run with relative paths from the street's parent directory."""
    result = bbcity("recon", street.name, "--out", "work", "--workers", "2", "--no-eval", cwd=street.parent)
    assert result.returncode == 0, result.stderr
    return street.parent / "work"


def damaged_copy(street: Path, dest: Path) -> tuple[Path, Path]:
    """A copy of the dataset with one PNG cut in half; returns (dataset, the damaged file)."""
    shutil.copytree(street, dest)
    png = sorted((dest / "images" / "cam1").glob("*.png"))[3]
    png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])
    return dest, png


# ----------------------------------------------------------------------------------------------
# errors inside workers


def test_data_format_errors_survive_pickling():
    error = DataFormatError("a/b.png", "truncated")
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is DataFormatError and str(back) == str(error)
    assert (back.path, back.problem) == (error.path, error.problem)
    missing = MissingFramesError("poses.json", ["f1", "f2"], 5, " (hint)")
    back = pickle.loads(pickle.dumps(missing))
    assert type(back) is MissingFramesError and str(back) == str(missing) and back.missing == ["f1", "f2"]


class _Unpicklable(Exception):
    def __init__(self, what: str, lock: object):
        super().__init__(what)
        self.lock = lock


def _raise_unpicklable(what: str):
    raise _Unpicklable(what, threading.Lock())


def _raise_data_error(path: str):
    raise DataFormatError(path, "broken on purpose")


def _square(x: int) -> int:
    return x * x


def test_worker_pool_returns_every_error_and_survives_it():
    with executor_scope(2) as pool:
        assert isinstance(pool, WorkerPool)
        with pytest.raises(DataFormatError, match="x.png: broken on purpose") as caught:
            pool.submit(_raise_data_error, "x.png").result()
        assert caught.value.path == Path("x.png")
        with pytest.raises(WorkerError, match="_Unpicklable: no pickle for a lock"):
            pool.submit(_raise_unpicklable, "no pickle for a lock").result()
        assert [f.result() for f in [pool.submit(_square, i) for i in range(4)]] == [0, 1, 4, 9]


@pytest.mark.parametrize("stage", ["recon", "build"])
def test_damaged_image_in_a_worker_is_one_line(stage, street, work, tmp_path):
    dataset, png = damaged_copy(street, tmp_path / "damaged")
    if stage == "recon":
        result = bbcity("recon", dataset, "--out", tmp_path / "w", "--workers", "2", "--no-eval")
    else:
        result = bbcity("build", work, "--images", dataset, "--out", tmp_path / "model", "--workers", "2",
                        "--layer", "none", "--photometry", "off")
    assert result.returncode == 2, result.stderr
    one_error_line(result.stderr, str(png.relative_to(tmp_path)), "truncated")
    assert not (tmp_path / "model").exists()


# ----------------------------------------------------------------------------------------------
# Ctrl-C, SIGKILL, concurrent runs


def test_ctrl_c_is_one_line_and_exit_130(street, tmp_path):
    run = Run("recon", street, "--out", tmp_path / "w", "--workers", "2", "--no-eval")
    workers = run.workers(2)
    run.wait_for("stereo on")
    # a frame done: both workers have started (a worker still starting when its parent is gone would
    # say so on the shared stderr, a race of the test's making, not the command's)
    wait_until(lambda: any((tmp_path / "w" / "spill" / "done").glob("*.json")))
    os.killpg(run.proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    assert run.finish(60) == 130, run.stderr
    one_error_line(run.stderr, "interrupted")
    assert wait_gone(workers, 10), "pool workers outlived the run"
    assert not (tmp_path / "w" / "cloud.ply").exists() and hidden_temporaries(tmp_path / "w") == []


def test_killed_run_takes_its_workers_along_and_the_next_run_sweeps_its_leftovers(street, work, tmp_path):
    out = tmp_path / "w"
    first = Run("recon", street, "--out", out, "--workers", "2", "--no-eval")
    workers = first.workers(2)
    os.killpg(first.proc.pid, signal.SIGSTOP)  # it lives (and holds its lock) however slow the second starts
    # a second run into the same work directory is refused while the first lives
    second = bbcity("recon", street, "--out", out, "--workers", "2", "--no-eval")
    assert second.returncode == 2, second.stderr
    one_error_line(second.stderr, str(out), f"pid {first.proc.pid}", "another bbcity run")

    first.proc.kill()  # SIGKILL: no handler runs (the OOM killer is no gentler)
    os.killpg(first.proc.pid, signal.SIGCONT)  # its stopped children see their parent gone
    first.finish(30)
    assert wait_gone(workers), "pool workers outlived their killed parent"
    # what killed runs leave: a PLY body and an atomic temporary of dead pids, a SfM folder
    dead = max(workers) + 100000
    assert not pid_alive(dead)
    leftovers = [out / f".cloud.ply.body-{dead}", out / f".cloud.ply.tmp-{dead}.ply", out / f".sparse.tmp-{'ab' * 16}"]
    for p in leftovers[:2]:
        p.write_bytes(b"x" * 1000)
    leftovers[2].mkdir()
    third = bbcity("recon", street, "--out", out, "--workers", "2", "--no-eval")
    assert third.returncode == 0, third.stderr
    assert hidden_temporaries(out) == []
    # the same cloud as an undisturbed run
    points = [json.loads((w / "recon_report.json").read_text())["points"] for w in (work, out)]
    assert points[0] == points[1] > 0


def test_lock_refuses_a_second_holder_and_frees_on_exit(tmp_path):
    out = tmp_path / "model"
    with exclusive_output(out):
        assert lock_path(out).read_text().strip() == str(os.getpid())
        with pytest.raises(BlockingIOError, match="another bbcity run") as caught:
            with exclusive_output(out):
                pass
        assert caught.value.filename == str(out)
    with exclusive_output(out):  # free again
        pass


def test_lock_is_taken_on_the_real_path_never_through_a_link(tmp_path):
    """Issue 35: a run reaching its output through a link and another through the real path held
    two locks and wrote one output at once; a lock planted as a link to another file had that
    file truncated and a pid written into it; a FIFO there ended in "Invalid argument"."""
    real, link = tmp_path / "work", tmp_path / "link"
    real.mkdir()
    link.symlink_to(real)
    assert lock_path(link) == lock_path(real)
    with exclusive_output(real):
        with pytest.raises(BlockingIOError, match="another bbcity run"):
            with exclusive_output(link):
                pass
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    lock_path(out).symlink_to(victim)
    with pytest.raises(OSError, match="lock file is a symbolic link"):
        with exclusive_output(out):
            pass
    assert victim.read_text() == "precious"
    fifo = tmp_path / "fifo_out"
    os.mkfifo(lock_path(fifo))
    with pytest.raises(OSError, match="not a plain file"):
        with exclusive_output(fifo):
            pass


def test_atomic_writes_never_write_through_a_planted_link(tmp_path):
    from core.fileio import write_bytes

    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "report.json"
    (tmp_path / f".report.json.tmp-{os.getpid()}.json").symlink_to(victim)
    write_bytes(out, b"new")
    assert out.read_bytes() == b"new" and victim.read_text() == "precious"


def test_sweep_removes_dead_runs_leftovers_and_restores_a_set_aside_model(tmp_path):
    out = tmp_path / "model"
    build_state = tmp_path / ".model.build-abc12345"
    half_model = tmp_path / ".model.tmp-k9j8h7g6"
    aside = tmp_path / f".model.old-{'5e' * 16}"  # replace_dir's: a uuid's hex
    other = tmp_path / ".other.build-abc12345"  # another output's: not ours to touch
    mine = tmp_path / f".model.tmp-{os.getpid()}.json"  # a live process's (this one)
    for d in (build_state, half_model, other, aside):
        d.mkdir(parents=True)
    (aside / "manifest.json").write_text("{}")
    mine.write_text("{}")
    with owned_output(out):  # the previous model was set aside and the new one never renamed in
        assert (out / "manifest.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [".model.lock", "model", other.name, mine.name])
    assert sweep_output(out) == []


def test_an_output_name_of_250_bytes_has_a_lock_and_temporaries_within_255(tmp_path):
    """A legal name of 250 bytes: its hidden files shorten it (the same in every run) to stay
    within the 255 bytes of a file name; the sweep still restores a set-aside output of it."""
    from core.fileio import atomic_dir, atomic_path
    from core.workdir import MAX_HIDDEN_NAME, hidden_name, sweep_temporaries

    long = "é" + "m" * 248  # 250 bytes in UTF-8
    assert hidden_name("model") == "model" and hidden_name(long) == hidden_name(long) != long
    assert len(hidden_name(long).encode()) <= MAX_HIDDEN_NAME and hidden_name(long).startswith("é")
    cut = hidden_name("m" * 182 + "é" * 40)  # a character across the cut is left out whole
    assert len(cut.encode()) <= MAX_HIDDEN_NAME and cut.startswith("m" * 182 + "~")
    out = tmp_path / long
    with owned_output(out):
        for _ in range(2):  # the second replaces the first: the first is set aside, then removed
            with atomic_dir(out) as tmp:
                assert len(tmp.name.encode()) <= 255
                with atomic_path(tmp / long) as part:
                    assert len(part.name.encode()) <= 255
                    part.write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f".{hidden_name(long)}.lock", long])
    assert (out / long).read_text() == "{}"
    aside = tmp_path / f".{hidden_name(long)}.old-{'5e' * 16}"  # a replacement killed between its renames
    out.rename(aside)
    assert sweep_temporaries(tmp_path, locked=True) == [] and aside.is_dir()  # whose it is: not known here
    with owned_output(out):
        assert (out / long).is_file() and not aside.exists()


def test_build_into_an_output_name_of_250_bytes(work, tmp_path):
    out = tmp_path / ("m" * 250)
    result = bbcity("build", work, "--out", out, "--workers", "1", "--layer", "none", "--photometry", "off")
    assert result.returncode == 0, result.stderr
    assert (out / "manifest.json").is_file() and hidden_temporaries(tmp_path) == []


# ----------------------------------------------------------------------------------------------
# a work directory means the same thing from anywhere


def test_work_names_its_dataset_from_any_directory(street, work, tmp_path, monkeypatch):
    report = json.loads((work / "recon_report.json").read_text())
    assert Path(report["dataset"]).is_absolute()
    decoy = tmp_path / street.name  # a directory of the same relative name elsewhere
    decoy.mkdir()
    monkeypatch.chdir(tmp_path)
    assert Work.open(work).dataset() == street.resolve()

    # moved together: found relative to the work directory
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.copytree(street, moved / "data" / street.name)
    shutil.copytree(work, moved / "data" / "work")
    doc = dict(report, dataset=str(tmp_path / "nowhere"))
    (moved / "data" / "work" / "recon_report.json").write_text(json.dumps(doc))
    assert Work.open(moved / "data" / "work").dataset() == (moved / "data" / "work" / report["dataset_from_work"]).resolve()

    # moved together, another capture now at the old absolute path: the one beside WORK, not that one
    other = tmp_path / "other"
    shutil.copytree(street, other)
    poses = json.loads((other / "poses.json").read_text())
    poses["frames"] = poses["frames"][:-1]
    (other / "poses.json").write_text(json.dumps(poses))
    doc = dict(report, dataset=str(other))
    (moved / "data" / "work" / "recon_report.json").write_text(json.dumps(doc))
    assert Work.open(moved / "data" / "work").dataset() == (moved / "data" / street.name).resolve()
    # and with the moved copy gone, that other capture is refused, not used
    shutil.rmtree(moved / "data" / street.name)
    with pytest.raises(DataFormatError, match="holds another capture"):
        Work.open(moved / "data" / "work").dataset()

    # an old report's relative path is not guessed at
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    (legacy / "recon_report.json").write_text(json.dumps({"dataset": street.name}))
    with pytest.raises(DataFormatError, match="relative to the directory recon ran in"):
        Work.open(legacy).dataset()


def test_work_poses_are_read_in_work_and_only_as_recon_wrote_them(work, tmp_path):
    """Issue 35: a WORK whose poses.json was truncated or removed silently used the poses.json
    of the directory it was first reconstructed in (an absolute "poses_file")."""
    from recon.work import file_digest

    moved = tmp_path / "work"
    shutil.copytree(work, moved)
    report = json.loads((moved / "recon_report.json").read_text())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "poses.json").write_text((work / "recon_report.json").read_text())  # any file at the old path
    (moved / "poses.json").write_text("{}")
    doc = dict(report, poses_file=str(elsewhere / "poses.json"), poses_digest=file_digest(moved / "poses.json"))
    (moved / "recon_report.json").write_text(json.dumps(doc))
    assert Work.open(moved).poses_file() == moved / "poses.json"
    (moved / "poses.json").write_text("{")  # truncated
    with pytest.raises(ValueError, match="not the poses file recon wrote"):
        Work.open(moved).poses_file()
    (moved / "poses.json").unlink()
    with pytest.raises(ValueError, match="its poses file .* is missing"):
        Work.open(moved).poses_file()


def test_killed_synth_stops_writing_and_the_next_run_completes_it(tmp_path):
    out = tmp_path / "street"
    argv = ("synth", "street", "--out", out, "--frames", "10", "--length", "30", "--width", "320", "--height", "240",
            "--no-gt-depth", "--workers", "2")
    first = Run(*argv)
    workers = first.workers(2)
    end = time.monotonic() + 120
    while not list(out.glob("images/cam*/*.png")):
        assert first.proc.poll() is None and time.monotonic() < end, first.stderr
        time.sleep(0.05)
    first.proc.kill()
    first.finish(30)
    assert wait_gone(workers), "synth workers outlived their killed parent"
    written = sorted(out.rglob("*"))
    time.sleep(1.0)
    assert sorted(out.rglob("*")) == written, "something still writes into the dataset"
    second = bbcity(*argv)
    assert second.returncode == 0, second.stderr
    assert len(list(out.glob("images/cam*/*.png"))) == 20 * 3 and hidden_temporaries(out) == []


def test_killed_build_takes_its_workers_along_and_the_next_build_sweeps_its_state(street, work, tmp_path):
    model = tmp_path / "model"
    argv = ("build", work, "--out", model, "--workers", "2", "--layer", "none", "--photometry", "off",
            "--voxel-size", "0.25")
    first = Run(*argv)
    workers = first.workers(2)
    end = time.monotonic() + 120
    while not list(tmp_path.glob(".model.build-*")):  # the build's state directory: sampling has begun
        assert first.proc.poll() is None and time.monotonic() < end, first.stderr
        time.sleep(0.05)
    first.proc.kill()
    first.finish(30)
    assert wait_gone(workers), "build workers outlived their killed parent"
    assert list(tmp_path.glob(".model.build-*")) and not model.exists()
    second = bbcity(*argv)
    assert second.returncode == 0, second.stderr
    assert (model / "manifest.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".model.lock", "model"]


@pytest.mark.parametrize("delay", [0.4, 0.8, 1.2, 2.0])
def test_ctrl_c_while_starting_is_one_line(delay, street, tmp_path):
    """Ctrl-C while the command parses and imports its libraries (OpenCV, Open3D, moderngl)."""
    run = Run("recon", street, "--out", tmp_path / "w", "--workers", "2", "--no-eval")
    time.sleep(delay)
    os.killpg(run.proc.pid, signal.SIGINT)
    code = run.finish(60)
    if code == 0:  # finished before the signal: nothing to judge
        return
    assert code == 130, run.stderr
    one_error_line(run.stderr, "interrupted")


@pytest.fixture(scope="module")
def model(work, tmp_path_factory):
    out = tmp_path_factory.mktemp("model") / "model"
    result = bbcity("build", work, "--out", out, "--workers", "1", "--layer", "none", "--photometry", "off")
    assert result.returncode == 0, result.stderr
    return out


def test_sigterm_unwinds_without_a_native_stack_dump(model, tmp_path):
    """pycolmap (glog) installs a SIGTERM handler that prints a stack dump; ours must stay."""
    frames = tmp_path / "frames"
    run = Run("render", model, "--out", frames, "--frames", "2000", "--size", "64", "48")
    end = time.monotonic() + 120
    # frames are written into a hidden directory and moved into place at the end: terminate while
    # they are being rendered, not in the moment between the move and the exit
    while not list(frames.glob(".frames.tmp-*/*.png")):
        assert run.proc.poll() is None and time.monotonic() < end, run.stderr
        time.sleep(0.05)
    run.proc.terminate()
    assert run.finish(60) == 143, run.stderr
    assert "Aborted at" not in run.stderr and "stack trace" not in run.stderr and "Traceback" not in run.stderr
    assert hidden_temporaries(frames) == []


def test_a_background_job_ignores_ctrl_c_as_it_was_started_to(street, tmp_path):
    """A shell starts `bbcity … &` of a script with SIGINT ignored: Ctrl-C at the script is not for it."""
    proc = subprocess.Popen([sys.executable, "-m", "bbcity.cli", "recon", str(street), "--out", str(tmp_path / "w"),
                             "--workers", "2", "--no-eval"], cwd=ROOT, env=_env(), start_new_session=True,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    time.sleep(1.5)
    os.killpg(proc.pid, signal.SIGINT)
    _, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    assert (tmp_path / "w" / "cloud.ply").is_file()


def test_a_dead_worker_is_told_apart_from_other_errors():
    from concurrent.futures.process import BrokenProcessPool

    from bbcity.lifecycle import worker_died

    class KilledWorker(Exception):  # Dask's, by name
        pass

    assert worker_died(BrokenProcessPool("a worker died")) and worker_died(KilledWorker("task", "worker"))
    assert not worker_died(RuntimeError("a bug")) and not worker_died(ValueError("bad input"))


@pytest.mark.parametrize("holdout", [-3, 1, 2.5, "4", True])
def test_bad_holdout_in_a_work_report_names_the_file_and_the_key(work, tmp_path, holdout):
    """Issue 35: a bad holdout in recon_report.json named neither the file nor the key."""

    moved = tmp_path / "work"
    shutil.copytree(work, moved)
    report = json.loads((moved / "recon_report.json").read_text())
    report["config"]["holdout"] = holdout
    (moved / "recon_report.json").write_text(json.dumps(report))
    with pytest.raises(DataFormatError, match="config.holdout must be 0") as err:
        Work.open(moved).holdout()
    assert err.value.path == moved / "recon_report.json"
