"""Frame-rate figures without timing anything: percentiles of given frame times, per-frame
counts, the capture walk's poses, overdraw on quads of known area, and `bbcity fps`'s rows."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.model_writer import save
from core.fileio import DataFormatError
from render.benchmark import decode_fps, frame_time_stats, lod_psnr, mean_counts, path_fps
from render.camera import look_at
from render.lod import LodConfig
from render.overdraw import measure_overdraw
from render.paths import _quaternions, _rotations, capture_camera_poses, capture_walk, densify_poses
from render.renderer import BillboardRenderer

from .test_render_gpu import intrinsics, make_model

# ----------------------------------------------------------------------------------------------
# frame-time percentiles (pure numpy)


def test_frame_time_stats_of_known_lists():
    one = frame_time_stats([0.02])
    assert one["frames"] == 1 and one["ms"] == one["ms_p95"] == one["ms_mean"] == pytest.approx(20.0)
    assert one["fps"] == one["fps_p5"] == one["fps_mean"] == pytest.approx(50.0)
    same = frame_time_stats([0.01] * 7)
    assert same["fps"] == same["fps_p5"] == same["fps_mean"] == pytest.approx(100.0)
    ms = np.arange(1, 21, dtype=np.float64)  # 1 … 20 ms
    s = frame_time_stats(ms[::-1] / 1000)  # order does not matter
    assert s["ms"] == pytest.approx(10.5) and s["ms_mean"] == pytest.approx(10.5)
    assert s["ms_p95"] == pytest.approx(19.05)  # linear between the 19th and 20th frame: 19 + 0.05
    assert s["fps_p5"] == pytest.approx(1000 / 19.05) and s["fps"] == pytest.approx(1000 / 10.5)
    spike = frame_time_stats([0.01] * 99 + [1.0])  # one slow frame in a hundred: below the 95th percentile
    assert spike["fps_p5"] == pytest.approx(100.0) and spike["fps_mean"] < 51
    for bad in ([], [0.0], [0.01, float("nan")], [-0.01]):
        with pytest.raises(ValueError):
            frame_time_stats(bad)


def test_mean_counts_take_missing_keys_as_zero():
    stats = [{"instances": 10, "quads": 4, "decoded_tiles": 6, "lod": [3, 1, 0], "frustum_s": 0.001, "cull_s": 0.002},
             {"instances": 20, "quads": 6, "lod": [5, 0, 1], "frustum_s": 0.003},
             {"instances": 30, "lod": 0, "decode_s": 0.03}]  # the CPU decode under culling: no level counts
    m = mean_counts(stats)
    assert m["instances"] == pytest.approx(20) and m["quads"] == pytest.approx(10 / 3)
    assert m["decoded_tiles"] == pytest.approx(2) and m["draw_calls"] == 0
    assert [m["lod_full"], m["lod_reduced"], m["lod_mean"]] == pytest.approx([8 / 3, 1 / 3, 1 / 3])
    assert m["cull_ms"] == pytest.approx(2.0) and m["decode_ms"] == pytest.approx(10.0)
    assert mean_counts([])["quads"] == 0


# ----------------------------------------------------------------------------------------------
# the capture walk (pure numpy)


def test_quaternions_round_trip_including_half_turns():
    rng = np.random.default_rng(3)
    R = np.linalg.qr(rng.normal(size=(200, 3, 3)))[0]
    R[np.linalg.det(R) < 0] *= -1
    R = np.concatenate([R, np.eye(3)[None], np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None],
                        np.diag([-1.0, -1, 1])[None]])
    np.testing.assert_allclose(_rotations(_quaternions(R)), R, atol=1e-12)


def test_densify_poses_keeps_the_capture_poses_and_steps_at_most_step():
    poses = np.stack([look_at([0, 0, 2.0], [0, -10, 2.0]), look_at([1.5, 0, 2.0], [1.5, -10, 2.0]),
                      look_at([3.0, 0, 2.0], [13.0, 0, 2.0]),  # a quarter turn while moving
                      look_at([3.0, 0, 2.0], [-7.0, 0, 2.0])])  # a half turn on the spot
    out = densify_poses(poses, 0.25)
    eyes = out[:, :3, 3]
    assert np.linalg.norm(np.diff(eyes, axis=0), axis=1).max() <= 0.25 + 1e-12
    assert len(out) == 6 + 6 + 1 + 1  # 1.5 m in six steps twice, the turn on the spot one pose, the last
    for p in poses:
        assert np.min(np.abs(out - p).reshape(len(out), -1).max(1)) < 1e-12  # every capture pose is kept
    R = out[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.all(np.linalg.det(R) > 0)
    half = out[6 + 3]  # half way through the quarter turn: looking 45° between -y and +x
    np.testing.assert_allclose(half[:3, 2], np.array([1.0, -1.0, 0.0]) / np.sqrt(2), atol=1e-12)
    np.testing.assert_allclose(half[:3, 3], [2.25, 0, 2.0], atol=1e-12)
    assert np.array_equal(densify_poses(poses, 0.0), poses)


def test_capture_walk_is_a_stretch_around_a_quarter_of_the_way():
    poses = np.stack([look_at([x, 0, 2.0], [x, -10, 2.0]) for x in np.arange(0.0, 101.0, 1.0)])
    walk = capture_walk(poses, 0.5, 20)
    assert len(walk) == 20
    assert np.all(np.diff(walk[:, 0, 3]) == pytest.approx(0.5))
    assert walk[:, 0, 3].mean() == pytest.approx(25.0, abs=0.5)
    assert len(capture_walk(poses, 0.5, 0)) == 201 and len(capture_walk(poses, 0.0, 1000)) == 101


def test_capture_camera_poses_of_a_dataset(tiny_dataset, tmp_path):
    from dataclasses import replace

    from capture import load_dataset

    ds = load_dataset(tiny_dataset)
    model = make_model([[0.0, 0.0, 1.0]], rank=0)
    assert capture_camera_poses(model) is None  # the model records no dataset
    poses = capture_camera_poses(model, tiny_dataset)
    np.testing.assert_array_equal(poses, np.stack([ds.world_from_cam(f, 0) for f in range(ds.num_frames)]))
    own = replace(model, info={"dataset": str(tiny_dataset)})
    np.testing.assert_array_equal(capture_camera_poses(own), poses)
    moved = replace(model, info={"dataset": str(tmp_path / "gone")})
    assert capture_camera_poses(moved) is None
    with pytest.raises(DataFormatError):
        capture_camera_poses(model, tmp_path / "gone")


# ----------------------------------------------------------------------------------------------
# overdraw: opaque quads of known pixel area

SIZE = (128, 128)
K = intrinsics(256.0, *SIZE)
CENTRE = np.array([0.3, -0.2, 1.1])
EYE = CENTRE + [4.0, 0.0, 0.0]  # 1 m quad at 4 m with f = 256: 64 × 64 px, 8 px per texel


@pytest.mark.parametrize("mode,lod,cull", [("gpu", True, "none"), ("gpu", False, "frustum"), ("gpu", True, "occlusion"),
                                           ("cpu", False, "none"), ("cpu", False, "frustum")])
def test_overdraw_of_quads_of_known_area(ctx, mode, lod, cull):
    pose = look_at(EYE, CENTRE)
    one = make_model([CENTRE], base_yaw=0.0, rank=2, page_size=32)
    with BillboardRenderer(ctx, one, mode, cull=cull, lod=LodConfig() if lod else None) as renderer:
        od = measure_overdraw(renderer, K, pose, SIZE)
        image = renderer.targets.read(SIZE)
    assert od["pixels"] == 128 * 128
    assert od["layers"] == od["written"] == od["covered"] == 64 * 64 / (128 * 128)
    assert np.any(image[32:96, 32:96] != 0, axis=-1).all()  # the frame stays in the framebuffer
    # a second quad straight behind (8 m: 32 × 32 px, hidden) and a third beside, half overlapping the first
    three = make_model([CENTRE, CENTRE + [-4.0, 0, 0], CENTRE + [0.0, 0.5, 0]], base_yaw=0.0, rank=2,
                       page_size=32)
    with BillboardRenderer(ctx, three, mode, cull=cull, lod=LodConfig() if lod else None) as renderer:
        od = measure_overdraw(renderer, K, pose, SIZE)
        assert renderer.stats["instances"] == 3
    layers = (2 * 64 * 64 + 32 * 32) / (128 * 128)
    covered = (64 * 96) / (128 * 128)  # the third quad at the same depth, 32 px to the side
    assert od["layers"] == layers and od["covered"] == covered
    assert covered <= od["written"] <= layers


def test_overdraw_leaves_out_the_decoders_atlas_passes(ctx):
    """Quads over a pixel per texel are pre-blended per view into an atlas; its fragments are not the frame's."""
    model = make_model([CENTRE], base_yaw=0.0, rank=3, page_size=32)
    pose = look_at(CENTRE + [4.0, 0.5, 0.0], CENTRE)  # between sampled directions: several to blend
    with BillboardRenderer(ctx, model, "gpu") as renderer:
        od = measure_overdraw(renderer, K, pose, SIZE)
        image = renderer.targets.read(SIZE)
    covered = np.count_nonzero(np.any(image != 0, axis=-1)) / (128 * 128)
    assert od["layers"] == od["written"] == od["covered"] == pytest.approx(covered, abs=1e-9)


# ----------------------------------------------------------------------------------------------
# the rows of decode_fps / path_fps / lod_psnr


@pytest.fixture(scope="module")
def street():
    rng = np.random.default_rng(1)
    centres = np.stack([rng.uniform(0, 20, 200), rng.uniform(-2, 2, 200), rng.uniform(0, 5, 200)], 1)
    return make_model(centres, voxel_size=1.0, yaw_span_deg=360.0, origin=(1e6, 2e6, 0.0))


def test_decode_and_path_rows(ctx, street):
    views = {"facade": look_at(street.origin + [10.0, 6, 2.0], street.origin + [10.0, 0, 2.0])}
    rows = decode_fps(ctx, street, views, (96, 64), {"gpu": 3, "gpu exact": 2, "cpu": 1}, overdraw=True)
    assert [(r["decode"], r["lod"], r["frames"]) for r in rows] == [("gpu", True, 3), ("gpu exact", False, 2),
                                                                     ("cpu", False, 1)]
    for r in rows:
        assert r["fps"] > 0 and r["fps_p5"] <= r["fps"] and r["ms_p95"] >= r["ms"] and r["cull"] == "frustum"
        assert 0 < r["instances"] <= street.num_billboards
        assert ("layers" in r) == (r["decode"] != "cpu")
    for r in rows[:2]:
        assert r["lod_full"] + r["lod_reduced"] + r["lod_mean"] == pytest.approx(r["quads"])
        assert r["layers"] >= r["written"] >= r["covered"] > 0
    assert rows[1]["lod_reduced"] == rows[1]["lod_mean"] == 0  # exact: every eigen image
    poses = np.stack([look_at(street.origin + [x, 6, 2.0], street.origin + [x, 0, 2.0]) for x in (5.0, 5.1, 5.2)])
    p = path_fps(ctx, street, poses, (96, 64), "gpu", cull="none")
    assert p["frames"] == 3 and p["instances"] == street.num_billboards and p["lod"]
    assert p["decoded_tiles"] >= 0 and p["fps_p5"] <= p["fps"]
    assert not path_fps(ctx, street, poses[:1], (96, 64), "cpu")["lod"]
    quality = lod_psnr(ctx, street, views, (96, 64))
    assert set(quality) == {"facade"} and 20 < quality["facade"] <= 100


def test_fps_command_rows(street, tiny_dataset, tmp_path, capsys):
    from bbcity.cli import main as cli_main

    model_dir = save(street, tmp_path / "model")
    argv = ["-q", "fps", str(model_dir), "--size", "96", "64", "--gpu-frames", "2", "--cpu-frames", "1"]
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert "capture path: the model records no dataset" in out
    for view in ("facade -y", "facade +y", "along +x"):
        assert f"gpu LOD {view:>12}: " in out and f"cpu {view:>12}: " in out
        assert f"GPU/CPU decode fps ratio, {view}: " in out
    gpu = next(line for line in out.splitlines() if line.strip().startswith("gpu LOD    facade -y"))
    for part in ("fps median", "p5 (", "ms, p95", "2 frames", "billboards in", "quads", "tiles decoded", "LOD ",
                 "cull ", "overdraw ", "layers /", "written per pixel"):
        assert part in gpu, part
    assert cli_main([*argv, "--exact", "--dataset", str(tiny_dataset), "--path-step", "0.5", "--path-frames", "4",
                     "--cull-mode", "none"]) == 0
    out = capsys.readouterr().out
    assert "gpu exact    facade -y" in out and "none culling" in out and "gpu LOD" not in out
    assert "capture path: 4 of 6 camera-0 poses walked every 0.5 m" in out
    assert "gpu exact capture path: " in out and "4 frames" in out and "cpu capture path: " in out
    assert "GPU/CPU decode fps ratio, capture path: " in out
    assert cli_main([*argv, "--size", "1920", "1080", "--gpu-frames", "1", "--dataset", str(tiny_dataset),
                     "--path-frames", "2"]) == 0
    assert "1920×1080" in capsys.readouterr().out
    assert cli_main([*argv, "--dataset", str(tmp_path / "none")]) == 2  # a bad dataset: one line, exit 2
