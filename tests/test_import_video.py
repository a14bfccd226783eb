"""``bbcity import video``: frames sampled from a video, blurred ones dropped, and its bad inputs."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import pytest

from bbcity.cli import main
from core import DataFormatError
from capture import load_dataset
from recon.importers.video import VideoConfig, import_video, sharp_enough, slot_window

W, H, FPS = 96, 64, 12
K_LINE = "80 80 47.5 31.5\n"


def _texture(seed: int = 0) -> np.ndarray:
    """A smooth random texture four frames wide (detail the video codec keeps)."""
    rng = np.random.default_rng(seed)
    small = (rng.random((H // 4, W, 3)) * 255).astype(np.uint8)
    return cv2.resize(small, (4 * W, H), interpolation=cv2.INTER_CUBIC)


def _frames(count: int, blurred=()) -> list[np.ndarray]:
    """``count`` frames panning across the texture; those in ``blurred`` Gaussian-blurred."""
    tex = _texture()
    frames = [np.ascontiguousarray(tex[:, 8 * i:8 * i + W]) for i in range(count)]
    return [cv2.GaussianBlur(f, (0, 0), 3) if i in blurred else f for i, f in enumerate(frames)]


def _video(path: Path, frames: list[np.ndarray]) -> Path:
    iio.imwrite(path, np.stack(frames), fps=FPS, codec="libx264")
    return path


@pytest.fixture
def k_file(tmp_path) -> Path:
    path = tmp_path / "K.txt"
    path.write_text(K_LINE)
    return path


def test_slot_windows():
    # 6 frames a slot, the 5 at its middle; 2.5 frames a slot (alternating 3 and 2 frames)
    assert [slot_window(k, 6.0, 5) for k in range(3)] == [range(0, 5), range(6, 11), range(12, 17)]
    assert [slot_window(k, 2.5, 5) for k in range(4)] == [range(0, 3), range(3, 5), range(5, 8), range(8, 10)]
    assert slot_window(1, 6.0, 1) == range(8, 9)  # one frame: the middle one
    assert len(slot_window(1, 0.4, 5)) == 0  # slots shorter than a frame: some hold none
    # below 0.3 × the median (80), or below 2 grey levels²: blurred or featureless
    assert sharp_enough([100.0, 90.0, 80.0, 20.0, 1.0], VideoConfig()).tolist() == [True, True, True, False, False]
    assert sharp_enough([1.5, 1.5], VideoConfig()).tolist() == [False, False]


def test_video_frames_are_sampled_and_the_blurred_dropped(tmp_path, k_file):
    # 2 s at 12 fps, 2 kept per second: slots of 6 frames, each choosing among its first 5.
    # Slot 0 is blurred throughout (dropped by the median rule); in slot 2 frames 14–16 are.
    video = _video(tmp_path / "walk.mp4", _frames(24, blurred={0, 1, 2, 3, 4, 5, 14, 15, 16}))
    out = import_video(video, tmp_path / "ds", VideoConfig(intrinsics=k_file, step_length=0.7))
    ds = load_dataset(out)
    assert ds.frame_names[0] in ("frame_000006", "frame_000007", "frame_000008", "frame_000009", "frame_000010")
    assert len(ds.frame_names) == 3 and ds.frame_names[1] in ("frame_000012", "frame_000013")
    assert 18 <= int(ds.frame_names[2][-6:]) <= 22
    assert ds.rig.num_cameras == 1 and ds.rig.sizes[0] == (W, H) and np.isnan(ds.world_from_rig).all()
    np.testing.assert_allclose(ds.rig.intrinsics[0], [[80, 0, 47.5], [0, 80, 31.5], [0, 0, 1]])
    source = json.loads((out / "dataset.json").read_text())["source"]
    assert source["kind"] == "video" and source["step_length"] == 0.7 and source["gps_enu_m"] is None
    dropped = source["blur_filter"]["dropped_frames"]
    assert len(dropped) == 1 and dropped[0] <= 4  # slot 0's sharpest, still blurred
    # each stored image is the frame its name gives: of the encoded frames, the nearest to it
    sources = np.array(_frames(24), dtype=np.int64)
    for f, name in enumerate(ds.frame_names):
        error = np.abs(sources - ds.image(f, 0)).mean(axis=(1, 2, 3))
        assert int(np.argmin(error)) == int(name[-6:])


def test_frames_spread_over_the_video_through_the_cli(tmp_path, k_file):
    video = _video(tmp_path / "walk.mp4", _frames(24))
    assert main(["-q", "import", "video", str(video), "--out", str(tmp_path / "ds"), "--intrinsics", str(k_file),
                 "--frames", "4"]) == 0
    names = load_dataset(tmp_path / "ds").frame_names
    # 4 slots of 6 frames: one frame of each
    assert [int(n[-6:]) // 6 for n in names] == [0, 1, 2, 3]


def test_a_phone_video_with_a_rotation_tag_comes_out_upright(tmp_path, k_file):
    video = _video(tmp_path / "walk.mp4", _frames(12))
    turned = tmp_path / "turned.mp4"  # the same stream, shown turned 90° (a phone held upright)
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-display_rotation", "90", "-i",
                    str(video), "-c", "copy", str(turned)], check=True)
    k_upright = tmp_path / "K_upright.txt"  # the K file describes the upright frames
    k_upright.write_text("80 80 31.5 47.5\n")
    upright = load_dataset(import_video(turned, tmp_path / "up", VideoConfig(intrinsics=k_upright, frames=2)))
    plain = load_dataset(import_video(video, tmp_path / "plain", VideoConfig(intrinsics=k_file, frames=2)))
    assert upright.rig.sizes[0] == (H, W) and upright.frame_names == plain.frame_names
    assert np.array_equal(upright.image(0, 0), np.rot90(plain.image(0, 0)))  # turned 90° counter-clockwise


def _error(caplog) -> str:
    lines = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(lines) == 1 and "\n" not in lines[0] and "Traceback" not in caplog.text, caplog.text
    return lines[0]


@pytest.mark.parametrize("case", ["not a video", "missing", "no intrinsics", "blank"])
def test_bad_videos_are_one_clear_line(tmp_path, k_file, caplog, case):
    video = tmp_path / "walk.mp4"
    if case == "not a video":
        video.write_text("this is text, not a video\n")
    elif case == "blank":  # featureless frames: nothing left after the blur filter
        _video(video, [np.full((H, W, 3), 128, np.uint8)] * 12)
    elif case != "missing":
        _video(video, _frames(12))
    argv = ["import", "video", str(video), "--out", str(tmp_path / "ds")]
    if case != "no intrinsics":
        argv += ["--intrinsics", str(k_file)]
    assert main(argv) == 2
    line = _error(caplog)
    assert str(video) in line, line
    assert {"not a video": "is not a video ffmpeg can decode", "missing": "video file is missing",
            "no intrinsics": "give --intrinsics", "blank": "no frame is left after the blur filter"}[case] in line
    assert not (tmp_path / "ds").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".ds.") and not p.name.endswith(".lock")] == []


@pytest.mark.parametrize("options, message", [
    (["--fps", "2", "--frames", "5"], "not allowed with argument"),
    (["--fps", "0"], "--fps"),
    (["--fps", "-1"], "--fps"),
    (["--frames", "0"], "--frames"),
])
def test_bad_rates_are_refused_as_they_are_parsed(tmp_path, capsys, options, message):
    with pytest.raises(SystemExit) as e:
        main(["import", "video", str(tmp_path / "v.mp4"), "--out", str(tmp_path / "ds"), *options])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "error:" in err[-1] and message in err[-1], err


def test_video_config_is_validated():
    for bad in (dict(fps=2.0, frames=3), dict(fps=0.0), dict(fps=float("nan")), dict(frames=0), dict(frames=True),
                dict(sharpest_of=0), dict(min_relative_sharpness=1.0), dict(min_sharpness=-1.0),
                dict(step_length=0.0)):
        with pytest.raises(ValueError):
            VideoConfig(**bad)
    assert VideoConfig().rate == 2.0 and VideoConfig(fps=5).rate == 5.0


def test_import_video_refuses_a_video_too_short_for_its_slots(tmp_path, k_file):
    # 0.5 fps at 12 fps: a slot of 24 frames, whose middle window starts after the video's 3 frames
    video = _video(tmp_path / "walk.mp4", _frames(3))
    with pytest.raises(DataFormatError, match=r"walk\.mp4: its 3 frames are too few"):
        import_video(video, tmp_path / "ds", VideoConfig(intrinsics=k_file, fps=0.5))
