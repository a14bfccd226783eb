"""`bbcity render`: frames and a video along camera paths, bad pose files named."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.fileio import read_png
from bbcity.cli import main as cli_main
from billboards.model_writer import save
from render.camera import look_at
from render.paths import orbit_poses, save_poses_json

from .test_render_gpu import make_model


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    rng = np.random.default_rng(1)
    centres = np.stack([rng.uniform(0, 20, 200), rng.uniform(-2, 2, 200), rng.uniform(0, 5, 200)], 1)
    model = make_model(centres, voxel_size=1.0, yaw_span_deg=360.0, origin=(1e6, 2e6, 0.0))
    return save(model, tmp_path_factory.mktemp("m") / "model")


def test_orbit_frames_show_the_model(model_dir, tmp_path):
    out = tmp_path / "frames"
    assert cli_main(["-q", "render", str(model_dir), "--path", "orbit", "--frames", "3", "--size", "160", "120",
                     "--out", str(out)]) == 0
    frames = sorted(out.glob("frame_*.png"))
    assert len(frames) == 3
    for f in frames:
        image = read_png(f, (160, 120))
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20  # billboards, not just sky


def test_video_and_pose_file(model_dir, tmp_path):
    from billboards.model_reader import load

    poses = orbit_poses(load(model_dir), 4)
    pose_file = save_poses_json(tmp_path / "poses.json", poses)
    video = tmp_path / "fly.mp4"
    assert cli_main(["-q", "render", str(model_dir), "--path", str(pose_file), "--size", "96", "64",
                     "--out", str(video)]) == 0
    import imageio.v2 as imageio

    with imageio.get_reader(video) as reader:
        frames = [f for f in reader]
    assert len(frames) == 4 and frames[0].shape == (64, 96, 3)
    assert not list(tmp_path.glob(".*tmp*"))


def test_bad_pose_file_is_named(model_dir, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([look_at([0, 0, 0.0], [1, 0, 0.0]).tolist(), [[1, 2], [3, 4]]]))
    assert cli_main(["-q", "render", str(model_dir), "--path", str(bad), "--out", str(tmp_path / "f")]) == 2
    assert not (tmp_path / "f").exists()


def test_fps_prints_each_decode_and_culling_mode(model_dir, capsys):
    assert cli_main(["-q", "fps", str(model_dir), "--size", "96", "64", "--gpu-frames", "1", "--cpu-frames", "1",
                     "--cull"]) == 0
    out = capsys.readouterr().out
    assert "200 billboards" in out and "GPU/CPU decode fps ratio, facade -y:" in out
    for mode in ("none", "frustum", "occlusion", "auto"):
        assert f"cull {mode:>9}" in out
