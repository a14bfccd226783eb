"""File-system errors end in one line naming the path, exit 2, and nothing half-written:
a read-only directory, a full disk (a real tiny tmpfs where this machine may mount one,
else an injected ENOSPC), ``--out`` naming an existing file, a name too long.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import os
import subprocess
from pathlib import Path

import pytest

from bbcity.cli import main
from core import fileio

from .conftest import tiny_config, write_ground_truth_cloud


def can_mount() -> bool:
    probe = Path("/proc/self/status").read_text()
    return os.geteuid() == 0 and "CapEff:\t0000000000000000" not in probe


@pytest.fixture
def tmpfs(tmp_path):
    """mount(name, kilobytes, read_only) → a fresh tmpfs of that size under tmp_path."""
    mounted: list[Path] = []

    def mount(name: str, kilobytes: int = 1024, read_only: bool = False) -> Path:
        point = tmp_path / name
        point.mkdir()
        options = f"size={kilobytes}k" + (",ro" if read_only else "")
        result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)], capture_output=True)
        if result.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {result.stderr.decode().strip()}")
        mounted.append(point)
        return point

    if not can_mount():
        pytest.skip("mounting a tmpfs needs root")
    yield mount
    for point in reversed(mounted):
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, tiny_dataset):
    """A dataset, a cloud of it and a built model, for the commands that read them."""
    from billboards.build import BuildConfig, main as build_main
    from billboards.octree import OctreeConfig

    root = tmp_path_factory.mktemp("fs")
    cloud = write_ground_truth_cloud(tiny_dataset, root / "cloud.ply", stride=4)
    model = build_main(BuildConfig(octree=OctreeConfig(voxel_size=1.0), layer=None, photometry=None), cloud,
                       tiny_dataset, root / "model").model
    work = root / "work"
    work.mkdir()
    (work / "cloud.ply").write_bytes(cloud.read_bytes())
    (work / "recon_report.json").write_text(f'{{"dataset": "{tiny_dataset}"}}')
    return {"dataset": tiny_dataset, "cloud": cloud, "model": model, "work": work}


def commands(inputs: dict, out: Path) -> dict[str, list[str]]:
    """Every writing command, its output ``out``, inputs small enough to fail fast."""
    d, m, w = str(inputs["dataset"]), str(inputs["model"]), str(inputs["work"])
    o = str(out)
    return {
        "synth": ["synth", "street", "--out", o, "--frames", "2", "--length", "20", "--width", "64", "--height", "48"],
        "import": ["import", "kitti", d, "--out", o],
        "recon": ["recon", d, "--out", o, "--workers", "2", "--no-eval"],
        "build": ["build", w, "--out", o, "--workers", "1", "--layer", "none", "--photometry", "off"],
        "render": ["render", m, "--out", o, "--frames", "2", "--size", "64", "48"],
        "eval": ["eval", m, d, "--out", o, "--views", "1", "--size", "64", "48"],
        "texture-sweep": ["texture-sweep", w, "--out", o, "--count", "4", "--tiles", "8"],
        "sampling-eval": ["sampling-eval", w, "--out", o, "--count", "2"],
        "stereo-sweep": ["stereo-sweep", d, "--out", o, "--frames", "1"],
        "bench": ["bench", "--out", o, "--quick"],
    }


def run_cli(argv: list[str], caplog) -> tuple[int, list[str]]:
    """Exit status and error lines: logged errors, or the usage error of options refused as parsed."""
    caplog.clear()
    stderr = io.StringIO()
    with caplog.at_level(logging.INFO), contextlib.redirect_stderr(stderr):
        try:
            code = main(argv)
        except SystemExit as e:
            code = e.code
    usage = [line for line in stderr.getvalue().splitlines() if ": error: " in line]
    return code, usage + [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


WRITING = ["synth", "import", "recon", "build", "render", "eval", "texture-sweep", "sampling-eval", "stereo-sweep",
           "bench"]


@pytest.mark.parametrize("command", WRITING)
def test_read_only_directory(command, inputs, tmpfs, caplog):
    read_only = tmpfs("ro", read_only=True)
    out = read_only / "out"
    code, errors = run_cli(commands(inputs, out)[command], caplog)
    assert code == 2 and len(errors) == 1, errors
    assert str(read_only) in errors[0] and "Read-only file system" in errors[0]
    assert list(read_only.iterdir()) == []


@pytest.mark.parametrize("command", WRITING)
def test_out_is_an_existing_file(command, inputs, tmp_path, caplog):
    out = tmp_path / ("x.mp4" if command == "render" else "x")
    out.write_bytes(b"precious")
    code, errors = run_cli(commands(inputs, out)[command], caplog)
    if command == "render":  # a video is a file: replaced whole
        assert code == 0 and out.read_bytes()[4:8] == b"ftyp"
        return
    assert code == 2 and len(errors) == 1, errors
    assert str(out) in errors[0]
    assert out.read_bytes() == b"precious"


@pytest.mark.parametrize("command", WRITING)
def test_name_too_long(command, inputs, tmp_path, caplog):
    out = tmp_path / ("n" * 300)
    code, errors = run_cli(commands(inputs, out)[command], caplog)
    assert code == 2 and len(errors) == 1, errors
    assert "File name too long" in errors[0] and "n" * 300 in errors[0]
    assert list(tmp_path.iterdir()) == []


def hidden(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob(".*") if not p.name.endswith(".lock"))


@pytest.mark.parametrize("command, kilobytes", [("synth", 64), ("recon", 256), ("build", 256), ("eval", 64),
                                                ("render", 16), ("video", 64)])
def test_full_disk(command, kilobytes, inputs, tmpfs, caplog):
    disk = tmpfs("full", kilobytes)
    out = disk / ("out.mp4" if command == "video" else "out")
    argv = commands(inputs, out)["render" if command == "video" else command]
    if command in ("synth", "render", "video"):
        argv[argv.index("--frames") + 1] = "4" if command == "synth" else "40"
    if command == "video":  # ffmpeg fails only at the end, when it writes the trailer: exit 0 once
        argv[argv.index("--size") + 1:argv.index("--size") + 3] = ["640", "480"]
    code, errors = run_cli(argv, caplog)
    assert code == 2 and len(errors) == 1, errors
    assert "No space left on device" in errors[0] and str(disk) in errors[0], errors
    assert hidden(disk) == [], "temporaries left behind"
    if command == "video":
        assert not out.exists()
    if command == "recon":
        assert not (out / "cloud.ply").exists() and not (out / "spill").exists()
    if command in ("build", "eval"):  # no partial model or report
        assert not out.exists()


def test_injected_enospc_leaves_nothing_half_written(tmp_path, monkeypatch, caplog):
    """Where no tmpfs can be mounted: the disk fills while a PNG is renamed into place."""
    from data_synth import write_dataset

    calls = {"n": 0}
    real_replace = os.replace

    def replace(src, dst):
        calls["n"] += 1
        if calls["n"] == 7:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(fileio.os, "replace", replace)
    out = tmp_path / "street"
    with pytest.raises(OSError, match="No space left"):
        write_dataset(tiny_config(), out, progress=False)
    assert hidden(out) == []
    monkeypatch.setattr(fileio.os, "replace", real_replace)
    write_dataset(tiny_config(), out, progress=False)  # the next run completes it: the same bytes as a clean run
    clean = write_dataset(tiny_config(), tmp_path / "clean", progress=False)
    files = sorted(p.relative_to(clean) for p in clean.rglob("*") if p.is_file() and p.name != "synth_report.json")
    assert files and files == sorted(p.relative_to(out) for p in out.rglob("*")
                                     if p.is_file() and p.name != "synth_report.json")
    assert all((out / f).read_bytes() == (clean / f).read_bytes() for f in files)
    assert hidden(out) == []


def test_eval_does_not_replace_a_directory_of_other_files(inputs, tmp_path, caplog):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    code, errors = run_cli(commands(inputs, out)["eval"], caplog)
    assert code == 2 and len(errors) == 1 and "not an eval report's" in errors[0]
    assert (out / "notes.txt").read_text() == "precious"


def test_eval_refuses_a_directory_that_is_not_its_report_before_any_sweep(inputs, tmp_path, caplog):
    """An earlier eval report may be replaced; a directory with anything else (even beside a report)
    is refused when the options are parsed, before the sweep of temporaries looks inside it."""
    out = tmp_path / "demo"
    (out / "work").mkdir(parents=True)
    (out / "eval.json").write_text("{}")
    (out / ".draft.tmp-original").write_text("mine")  # looks like a temporary; it is the user's
    with pytest.raises(SystemExit) as caught:
        main(commands(inputs, out)["eval"])
    assert caught.value.code == 2
    assert sorted(p.name for p in out.iterdir()) == [".draft.tmp-original", "eval.json", "work"]


def test_eval_replaces_its_own_earlier_report(inputs, tmp_path, caplog):
    """Every file an eval report writes (training panels too) marks the directory as a report."""
    out = tmp_path / "eval"
    out.mkdir()
    for name in ("eval.json", "eval.md", "workprecision.png", "view_000003_on_path.png",
                 "view_000003_off_path.png", "view_000000_training.png"):
        (out / name).write_bytes(b"old")
    code, errors = run_cli(commands(inputs, out)["eval"], caplog)
    assert code == 0 and errors == []
    assert "view_000000_training.png" not in {p.name for p in out.iterdir()}
    assert (out / "eval.json").read_bytes() != b"old"


def test_build_into_what_it_reads_is_refused(inputs, tmp_path, caplog):
    """`build W --out W` (or --out above W, or over the dataset) would replace what it reads."""
    import shutil

    work = tmp_path / "work"
    shutil.copytree(inputs["work"], work)
    before = {p.name: p.read_bytes() for p in work.iterdir()}
    for out in (work, tmp_path):
        code, errors = run_cli(["build", str(work), "--out", str(out), "--workers", "1", "--layer", "none",
                                "--photometry", "off"], caplog)
        assert code == 2 and len(errors) == 1, errors
        assert f"--out {out} holds {work / 'cloud.ply'}, which this command reads" in errors[0]
    dataset = Path(inputs["dataset"])
    code, errors = run_cli(["build", "--cloud", str(work / "cloud.ply"), "--images", str(dataset), "--out",
                            str(dataset), "--workers", "1", "--layer", "none", "--photometry", "off"], caplog)
    assert code == 2 and len(errors) == 1 and f"holds {dataset}" in errors[0], errors
    assert {p.name: p.read_bytes() for p in work.iterdir()} == before and (dataset / "rig.json").is_file()


def test_a_short_write_without_an_errno_is_a_full_disk_naming_the_output(tmp_path):
    """numpy's tofile reports a full disk as "N requested and M written", with no errno and no path."""
    import numpy as np

    from bbcity.lifecycle import os_error_line

    out = tmp_path / "model"
    line = os_error_line(OSError("1312056 requested and 386016 written"), out)
    assert line == (f"{out}: No space left on device (or over a quota): a write of 1312056 items stopped at "
                    "386016")
    assert os_error_line(OSError("something else"), out) == "something else"
    if Path("/dev/full").exists():  # numpy's own words on a full device, as it says them today
        with pytest.raises(OSError) as error:
            np.zeros(1000).tofile("/dev/full")
        assert os_error_line(error.value, out).startswith(f"{out}: No space left on device")
