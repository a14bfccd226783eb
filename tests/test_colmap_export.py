"""Tests for data_synth.colmap_export: round trip through pycolmap, determinism, validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from capture.colmap import write_colmap_text
from capture.native import pycolmap

C = 3
W, H = 640, 480
BASELINES = [0.0, 0.4, 0.8]  # metres along camera x


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    return _rigid(T[:3, :3].T, -T[:3, :3].T @ T[:3, 3])


def _make_rig():
    """Return intrinsics (3,3,3), sizes, cam_from_rig (3,4,4), world_from_rig (5,4,4), names."""
    K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    intrinsics = np.stack([K] * C)
    sizes = [(W, H)] * C
    # Rig frame: x forward, y left, z up (vehicle-like); cameras look along rig x.
    # OpenCV camera axes in rig coordinates: x_cam = -y_rig, y_cam = -z_rig, z_cam = x_rig.
    rig_from_cam_R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cam_from_rig = np.empty((C, 4, 4))
    for i, b in enumerate(BASELINES):
        # camera i sits b metres along camera x (= -y_rig) from camera 0, rig origin offset a bit
        centre_in_rig = np.array([1.2, 0.3, 1.5]) + b * rig_from_cam_R[:, 0]
        cam_from_rig[i] = _inv(_rigid(rig_from_cam_R, centre_in_rig))
    poses = [
        (0.0, [0.0, 0.0, 0.0]),
        (0.3, [2.0, 0.5, 0.0]),
        (-0.7, [4.5, -1.0, 0.2]),
        (np.pi / 2 + 0.01, [-3.0, 7.0, 0.1]),
        (2.5, [1.0e6 + 0.123456, -2.0e5 + 0.654321, 35.0]),  # city-scale coordinates
    ]
    world_from_rig = np.stack([_rigid(_rot_z(yaw), t) for yaw, t in poses])
    names = [[f"cam{i}/{k:06d}.png" for i in range(C)] for k in range(len(poses))]
    return intrinsics, sizes, cam_from_rig, world_from_rig, names


def _mat4(rigid: pycolmap.Rigid3d) -> np.ndarray:
    T = np.eye(4)
    T[:3, :] = rigid.matrix()
    return T


def test_round_trip(tmp_path: Path) -> None:
    intrinsics, sizes, cam_from_rig, world_from_rig, names = _make_rig()
    out = write_colmap_text(tmp_path / "sparse", intrinsics, sizes, cam_from_rig, world_from_rig, names)
    assert out == tmp_path / "sparse"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["cameras.txt", "frames.txt", "images.txt", "points3D.txt", "rigs.txt"]
    )
    # no temporary siblings left behind
    assert [p.name for p in tmp_path.iterdir()] == ["sparse"]

    rec = pycolmap.Reconstruction(out)
    n = world_from_rig.shape[0]
    assert rec.num_cameras() == C
    assert rec.num_rigs() == 1
    assert rec.num_frames() == n
    assert rec.num_reg_frames() == n
    assert rec.num_images() == n * C
    assert rec.num_reg_images() == n * C
    assert rec.num_points3D() == 0

    for i in range(C):
        cam = rec.cameras[i + 1]
        assert cam.model_name == "PINHOLE"
        assert (cam.width, cam.height) == (W, H)
        np.testing.assert_array_equal(cam.params, [500.0, 500.0, 320.0, 240.0])  # cx, cy + 0.5

    rig = rec.rigs[1]
    assert rig.ref_sensor_id.id == 1
    assert rig.num_sensors() == C

    by_name = {im.name: im for im in rec.images.values()}
    assert sorted(by_name) == sorted(nm for row in names for nm in row)
    for k in range(n):
        frame = rec.frames[k + 1]
        np.testing.assert_allclose(
            _mat4(frame.rig_from_world), cam_from_rig[0] @ _inv(world_from_rig[k]), rtol=0, atol=1e-9
        )
        for i in range(C):
            im = by_name[names[k][i]]
            assert im.camera_id == i + 1
            assert im.frame_id == k + 1
            assert im.has_pose
            expected = cam_from_rig[i] @ _inv(world_from_rig[k])
            got = _mat4(im.cam_from_world())
            np.testing.assert_allclose(got[:3, :3], expected[:3, :3], rtol=0, atol=1e-12)
            # translations up to 1e6 m: float64 must hold ~1e-6 m (we get ~1e-10)
            np.testing.assert_allclose(got[:3, 3], expected[:3, 3], rtol=0, atol=1e-6)
            # camera centre in world coordinates, the quantity that matters at city scale
            centre = im.projection_center()
            np.testing.assert_allclose(centre, _inv(expected)[:3, 3], rtol=0, atol=1e-6)

    # baselines survive: camera centres of one frame are 0.4 m and 0.8 m from camera 0
    k = n - 1
    centres = np.array([by_name[names[k][i]].projection_center() for i in range(C)])
    np.testing.assert_allclose(np.linalg.norm(centres - centres[0], axis=1), BASELINES, atol=1e-6)


def test_deterministic_and_overwrite(tmp_path: Path) -> None:
    args = _make_rig()
    a = write_colmap_text(tmp_path / "a", *args)
    b = write_colmap_text(tmp_path / "b", *args)
    files = sorted(p.name for p in a.iterdir())
    assert files == sorted(p.name for p in b.iterdir())
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f

    # overwriting an existing model replaces it cleanly and gives the same bytes
    (a / "stale.txt").write_text("old run")
    write_colmap_text(a, *args)
    assert sorted(p.name for p in a.iterdir()) == files
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


def test_rejects_non_rotation(tmp_path: Path) -> None:
    intrinsics, sizes, cam_from_rig, world_from_rig, names = _make_rig()
    bad = world_from_rig.copy()
    bad[2, :3, :3] *= 1.1  # scaled, not a rotation
    with pytest.raises(ValueError, match=r"world_from_rig\[2\].*rotation"):
        write_colmap_text(tmp_path / "x", intrinsics, sizes, cam_from_rig, bad, names)
    bad = cam_from_rig.copy()
    bad[1, :3, :3] = np.diag([1.0, 1.0, -1.0])  # reflection
    with pytest.raises(ValueError, match=r"cam_from_rig\[1\]"):
        write_colmap_text(tmp_path / "x", intrinsics, sizes, bad, world_from_rig, names)
    assert not (tmp_path / "x").exists()
    assert list(tmp_path.iterdir()) == []


def test_rejects_bad_shapes_and_values(tmp_path: Path) -> None:
    intrinsics, sizes, cam_from_rig, world_from_rig, names = _make_rig()
    out = tmp_path / "x"
    with pytest.raises(ValueError, match="cam_from_rig"):
        write_colmap_text(out, intrinsics, sizes, cam_from_rig[:2], world_from_rig, names)
    with pytest.raises(ValueError, match="sizes"):
        write_colmap_text(out, intrinsics, sizes[:2], cam_from_rig, world_from_rig, names)
    with pytest.raises(ValueError, match="image_names"):
        write_colmap_text(out, intrinsics, sizes, cam_from_rig, world_from_rig, names[:-1])
    with pytest.raises(ValueError, match="duplicated"):
        dup = [row[:] for row in names]
        dup[1][0] = dup[0][0]
        write_colmap_text(out, intrinsics, sizes, cam_from_rig, world_from_rig, dup)
    nan = world_from_rig.copy()
    nan[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_colmap_text(out, intrinsics, sizes, cam_from_rig, nan, names)
    with pytest.raises(ValueError, match="shape"):
        write_colmap_text(out, intrinsics[:, :2], sizes, cam_from_rig, world_from_rig, names)
    assert not out.exists()
