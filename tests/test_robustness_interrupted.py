"""Interrupted runs: a stage killed mid-write leaves no file that looks complete,
the previous complete output (if any) intact, and the next run resumes or starts clean.

Stages: the dataset writer (a real SIGKILL while a PNG is half written), recon's cloud and
report, the billboard build (model directory and report), and the fly-through renderer
(PNG frames and video). Writer-level interruption (atomic_path, PlyStreamWriter,
AtlasWriter, ModelWriter, save) is tested beside each writer.
"""

from __future__ import annotations

import dataclasses
import json
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from core import DataFormatError
from core.fileio import load_npy, read_json, read_png
from billboards import build as build_mod
from billboards import texture_tasks as texture_tasks_mod
from billboards.build import BuildConfig, main as build_main
from billboards.geometry import DirectionConfig
from billboards.model_reader import load
from billboards.octree import OctreeConfig
from billboards.pca import PcaConfig
from billboards.sampling import SamplingConfig
from capture import load_dataset
from data_synth import write_dataset
from recon import pipeline as recon_pipeline
from recon.cloud_io import PlyStreamWriter, read_cloud_arrays
from recon.fusion import FusionConfig
from recon.pipeline import ReconConfig, main as recon_main

from .conftest import tiny_config
from .test_dataset_io import digest_tree

ROOT = Path(__file__).resolve().parents[1]


def visible_files(root: Path) -> list[Path]:
    """Files under ``root`` that no path component hides (temporaries are hidden)."""
    return sorted(p for p in root.rglob("*") if p.is_file()
                  and not any(part.startswith(".") for part in p.relative_to(root).parts))


def hidden_entries(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob(".*"))


# ----------------------------------------------------------------------------------------------
# dataset: SIGKILL while a PNG is half written, then resume


KILLER = textwrap.dedent("""
    import os, signal, sys
    import core.fileio as fileio
    from data_synth import write_dataset
    from tests.conftest import tiny_config

    original, pngs = fileio.write_bytes, [0]

    def write_bytes(path, data):
        if data.startswith(b"\\x89PNG"):
            pngs[0] += 1
            if pngs[0] == 5:  # frame 1, camera 1: half of it in the temporary file, then killed
                with fileio.atomic_path(path) as tmp:
                    with open(tmp, "wb") as f:
                        f.write(data[: len(data) // 2])
                        f.flush()
                        os.fsync(f.fileno())
                    os.kill(os.getpid(), signal.SIGKILL)
        return original(path, data)

    fileio.write_bytes = write_bytes
    write_dataset(tiny_config(), sys.argv[1], progress=False)
""")


def test_dataset_killed_mid_write_resumes_to_the_same_bytes(tmp_path, tiny_dataset):
    out = tmp_path / "street"
    run = subprocess.run([sys.executable, "-c", KILLER, str(out)], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == -signal.SIGKILL, run.stderr
    # the half-written PNG exists only under a temporary name
    [partial] = hidden_entries(out / "images")
    assert re.fullmatch(r"\.000001\.png\.tmp-\d+\.png", partial.name) and partial.parent.name == "cam1"
    assert not partial.read_bytes().endswith(b"IEND\xaeB`\x82")
    # every file under its final name is complete
    for p in visible_files(out):
        if p.suffix == ".png":
            read_png(p)
        elif p.suffix == ".npy":
            load_npy(p)
        elif p.suffix == ".json":
            read_json(p)
    assert not (out / "dataset.json").exists()  # written last: the dataset does not look complete
    with pytest.raises(DataFormatError, match="cam1/000001.png"):
        load_dataset(out)
    # the next run resumes: same bytes as an uninterrupted run, no temporaries left
    write_dataset(tiny_config(), out, progress=False)
    assert hidden_entries(out) == []
    assert digest_tree(out) == digest_tree(tiny_dataset)


def test_dataset_killed_before_its_first_file_starts_clean(tmp_path, tiny_dataset):
    """Only a directory and a temporary were left: that is no foreign data, the next run writes the dataset."""
    out = tmp_path / "street"
    (out / "gt").mkdir(parents=True)
    (out / "gt" / ".scene.json.tmp-4242.json").write_text('{"half": ')
    write_dataset(tiny_config(frames=1), out, progress=False)
    assert hidden_entries(out) == []
    assert load_dataset(out).num_frames == 2
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep")
    with pytest.raises(FileExistsError):
        write_dataset(tiny_config(frames=1), tmp_path / "other", progress=False)
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep"


# ----------------------------------------------------------------------------------------------
# recon: cloud.ply and recon_report.json


RECON = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1), frame_stride=3, evaluate=False)


def test_recon_interrupted_keeps_the_previous_run_or_leaves_no_report(tiny_dataset, tmp_path, monkeypatch):
    work = tmp_path / "work"
    recon_main(RECON, tiny_dataset, work, progress=False)
    cloud_a = (work / "cloud.ply").read_bytes()
    report_a = (work / "recon_report.json").read_bytes()
    other = dataclasses.replace(RECON, pixel_stride=2)

    # killed while the merge streams points: the previous cloud and its report stay as they were
    real_merge = recon_pipeline.merge_tiles

    def dying_merge(spill, centres, append, executor=None):
        def append_then_die(*args, **kwargs):
            append(*args, **kwargs)
            raise KeyboardInterrupt("killed while writing cloud.ply")
        return real_merge(spill, centres, append_then_die, executor)

    monkeypatch.setattr(recon_pipeline, "merge_tiles", dying_merge)
    with pytest.raises(KeyboardInterrupt):
        recon_main(other, tiny_dataset, work, progress=False)
    monkeypatch.undo()
    assert (work / "cloud.ply").read_bytes() == cloud_a
    assert (work / "recon_report.json").read_bytes() == report_a
    assert hidden_entries(work) == []  # no body or temporary file

    # killed after the new cloud is in place, before its report: no report describes the wrong cloud
    def dying_evaluation(*args, **kwargs):
        raise KeyboardInterrupt("killed during the evaluation")

    monkeypatch.setattr(recon_pipeline, "evaluate_cloud", dying_evaluation)
    monkeypatch.setattr(recon_pipeline, "evaluate_cloud_tiles", dying_evaluation)
    with pytest.raises(KeyboardInterrupt):
        recon_main(dataclasses.replace(other, evaluate=True), tiny_dataset, work, progress=False)
    monkeypatch.undo()
    assert (work / "cloud.ply").read_bytes() != cloud_a
    assert not (work / "recon_report.json").exists()

    # the next run starts clean: report and cloud agree
    recon_main(other, tiny_dataset, work, progress=False)
    report = json.loads((work / "recon_report.json").read_text())
    points, _ = read_cloud_arrays(work / "cloud.ply")
    assert report["points"] == len(points) > 100 and report["config"]["pixel_stride"] == 2
    assert not (work / "spill").exists() and hidden_entries(work) == []


# ----------------------------------------------------------------------------------------------
# build: the model directory and build_report.json


def small_build(**overrides) -> BuildConfig:
    base = dict(octree=OctreeConfig(voxel_size=0.5, min_points=5), source="points",
                sampling=SamplingConfig(tile=4, directions=DirectionConfig(count=4, spacing_deg=90.0)),
                pca=PcaConfig(max_rank=2), chunk=8, task_chunks=1, page_size=16)
    base.update(overrides)
    return BuildConfig(**base)


@pytest.fixture(scope="module")
def wall_cloud(tmp_path_factory):
    """A 6 m × 3 m textured wall of points (as recon writes them)."""
    rng = np.random.default_rng(4)
    n = 6000
    points = np.column_stack([rng.uniform(0, 6, n), rng.normal(0, 0.01, n), rng.uniform(0, 3, n)]) + [5e5, 4e6, 0]
    colours = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    path = tmp_path_factory.mktemp("wall") / "cloud.ply"
    with PlyStreamWriter(path, normals=False) as writer:
        writer.append(points, colours)
    return path


def test_build_interrupted_keeps_the_old_model_and_the_next_run_starts_clean(wall_cloud, tmp_path, monkeypatch):
    out = tmp_path / "model"
    build_main(small_build(), wall_cloud, None, out)
    before = digest_tree(out)
    assert (out / "build_report.json").is_file() and load(out).num_billboards > 10

    # killed in the middle of the billboards (several chunks already in the atlas pages)
    calls = [0]
    real_compress = texture_tasks_mod.compress_chunk

    def dying_compress(rgba, conf, eig=None):
        calls[0] += 1
        if calls[0] == 3:
            raise KeyboardInterrupt("killed mid-build")
        return real_compress(rgba, conf, eig)

    monkeypatch.setattr(texture_tasks_mod, "compress_chunk", dying_compress)
    with pytest.raises(KeyboardInterrupt):
        build_main(small_build(tile_mode="f16"), wall_cloud, None, out)
    monkeypatch.undo()
    assert calls[0] == 3
    assert digest_tree(out) == before  # the old model and its report, untouched
    assert hidden_entries(tmp_path) == []  # no temporary model or build state left
    assert load(out).tile_mode == "u8"

    # killed after the new model is in place, before its report: no stale report in it
    def dying_report(path, obj):
        raise KeyboardInterrupt("killed writing the report")

    monkeypatch.setattr(build_mod, "write_json", dying_report)
    with pytest.raises(KeyboardInterrupt):
        build_main(small_build(tile_mode="f16"), wall_cloud, None, out)
    monkeypatch.undo()
    assert load(out).tile_mode == "f16" and not (out / "build_report.json").exists()
    assert hidden_entries(tmp_path) == []

    # the next run writes a complete model with its report
    result = build_main(small_build(tile_mode="f16"), wall_cloud, None, out)
    assert result.report["config"]["tile_mode"] == "f16" and load(out).num_billboards == result.report["billboards"]
    assert json.loads((out / "build_report.json").read_text())["voxels"] == result.report["voxels"]


# ----------------------------------------------------------------------------------------------
# render: PNG frames and video


@pytest.fixture(scope="module")
def small_model():
    from .test_render_gpu import make_model

    rng = np.random.default_rng(2)
    centres = np.stack([rng.uniform(0, 6, 40), rng.uniform(-1, 1, 40), rng.uniform(0, 3, 40)], 1)
    return make_model(centres, voxel_size=1.0, yaw_span_deg=360.0, origin=(1e6, 2e6, 0.0))


def _dying_renderer(monkeypatch, after: int):
    """Make render.fly_through's renderer raise on its ``after``-th frame (counting from 1)."""
    from render import fly_through

    class Dying(fly_through.BillboardRenderer):
        calls = 0

        def render(self, *args, **kwargs):
            Dying.calls += 1
            if Dying.calls == after:
                raise KeyboardInterrupt("killed mid-render")
            return super().render(*args, **kwargs)

    monkeypatch.setattr(fly_through, "BillboardRenderer", Dying)


def test_frames_interrupted_keep_the_old_render_and_a_new_one_leaves_no_stale_frames(small_model, tmp_path,
                                                                                        monkeypatch):
    from render.fly_through import render_path
    from render.paths import orbit_poses

    poses = orbit_poses(small_model, 3)
    out = tmp_path / "frames"
    render_path(small_model, poses, out, size=(32, 24), progress=False)
    before = digest_tree(out)
    assert sorted(before) == [f"frame_{i:06d}.png" for i in range(3)]

    _dying_renderer(monkeypatch, after=2)
    with pytest.raises(KeyboardInterrupt):
        render_path(small_model, poses[1:], out, size=(32, 24), progress=False)
    monkeypatch.undo()
    assert digest_tree(out) == before and hidden_entries(tmp_path) == []  # no mix of old and new frames

    render_path(small_model, poses[1:], out, size=(32, 24), progress=False)
    after = digest_tree(out)
    assert sorted(after) == ["frame_000000.png", "frame_000001.png"]  # the old third frame is gone
    assert after["frame_000000.png"] == before["frame_000001.png"]  # same pose, same image
    assert after["frame_000001.png"] == before["frame_000002.png"]
    (out / "notes.txt").write_text("keep")  # only frames are replaced
    render_path(small_model, poses[:1], out, size=(32, 24), progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["frame_000000.png", "notes.txt"]


def test_video_interrupted_keeps_the_old_video(small_model, tmp_path, monkeypatch):
    from render.fly_through import render_path
    from render.paths import orbit_poses

    poses = orbit_poses(small_model, 3)
    video = tmp_path / "fly.mp4"
    _dying_renderer(monkeypatch, after=2)
    with pytest.raises(KeyboardInterrupt):
        render_path(small_model, poses, video, size=(32, 24), progress=False)
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []  # nothing, not even a short video

    render_path(small_model, poses, video, size=(32, 24), progress=False)
    old = video.read_bytes()
    _dying_renderer(monkeypatch, after=3)
    with pytest.raises(KeyboardInterrupt):
        render_path(small_model, poses[::-1], video, size=(32, 24), progress=False)
    monkeypatch.undo()
    assert video.read_bytes() == old and [p.name for p in tmp_path.iterdir()] == ["fly.mp4"]
    import imageio.v2 as imageio

    with imageio.get_reader(video) as reader:
        assert sum(1 for _ in reader) == 3
