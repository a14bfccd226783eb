"""Depth → points, voxel fusion and cloud IO."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from core import DataFormatError
from recon.cloud_io import PlyStreamWriter, read_cloud, write_cloud
from recon.fusion import (FusionConfig, TileSpill, merge_to_cloud, outlier_mask, outlier_mask_reference, pack_keys,
                          reduce_records, reduce_records_reference, unpack_keys, voxel_sums)
from recon.points import depth_to_points, depth_to_points_reference


@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_depth_to_points_matches_reference(offset):
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 50, (12, 16)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = np.nan
    depth[0, 0] = 0.0  # not a measurement either
    rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    K = np.array([[20.0, 0, 7.5], [0, 21.0, 5.5], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = o3d.geometry.get_rotation_matrix_from_xyz([0.1, -0.4, 2.0])
    pose[:3, 3] = [offset, -offset, 3.0]
    p, c, conf = depth_to_points(depth, K, pose, rgb)
    p_ref, c_ref = depth_to_points_reference(depth, K, pose, rgb)
    assert p.dtype == np.float64 and len(p) == len(p_ref)
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(c, c_ref)
    assert np.all(conf == 1)


@pytest.mark.parametrize("n, k", [(1, 1), (50, 3), (1000, 40), (1000, 1000)])
def test_reduce_matches_reference(n, k):
    rng = np.random.default_rng(n + k)
    keys = rng.integers(-k, k, n).astype(np.int64)
    records = rng.normal(size=(n, 8))
    a_keys, a = reduce_records(keys, records)
    b_keys, b = reduce_records_reference(keys, records)
    np.testing.assert_array_equal(a_keys, b_keys)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def _clouds() -> dict:
    rng = np.random.default_rng(1)
    lattice = np.stack(np.meshgrid(*[np.arange(20) * 0.06] * 2, [0.0]), -1).reshape(-1, 3)  # neighbours at 3 voxels
    street = np.c_[rng.uniform(0, 4, (20_000, 2)), rng.normal(0, 0.004, 20_000)]
    street[:200] += rng.normal(0, 0.3, (200, 3))  # strays
    return {"none": np.zeros((0, 3)), "one": np.zeros((1, 3)), "five": rng.normal(size=(5, 3)) * 0.01,
            "sixteen": rng.normal(size=(16, 3)) * 0.03, "seventeen": rng.normal(size=(17, 3)) * 0.03,
            "lattice": lattice, "lattice far away": np.stack(np.meshgrid(*[np.arange(30) * 0.02] * 3), -1)
            .reshape(-1, 3) + 1e5, "duplicates": np.repeat(rng.normal(size=(200, 3)), 20, axis=0),
            "some duplicated": np.r_[street, np.repeat(street[:3], 16, axis=0)], "street": street}


@pytest.mark.parametrize("name", sorted(_clouds()))
@pytest.mark.parametrize("cfg", [FusionConfig(), FusionConfig(outlier_neighbours=0),
                                 FusionConfig(radius_min_points=0), FusionConfig(outlier_neighbours=3, radius_min_points=9,
                                                                                 outlier_std_ratio=0.5)])
def test_outlier_mask_keeps_the_points_open3d_filters_keep(name, cfg):
    points = _clouds()[name]
    keep = outlier_mask(points, cfg)
    assert keep.dtype == bool and keep.shape == (len(points),)
    assert np.array_equal(keep, outlier_mask_reference(points, cfg))
    if name == "street" and cfg == FusionConfig():
        assert 19_000 < keep.sum() < 20_000 and keep[:200].mean() < 0.5  # most strays go, the plane stays


def test_pack_unpack_roundtrip_and_range():
    idx = np.array([[0, 0, 0], [-(2**20), 2**20 - 1, 5], [123456, -654321, 7]], dtype=np.int64)
    np.testing.assert_array_equal(unpack_keys(pack_keys(idx)), idx)
    with pytest.raises(ValueError, match="model origin"):
        pack_keys(np.array([[2**20, 0, 0]]))


def test_voxel_sums_average_position_and_colour():
    pts = np.array([[0.001, 0.001, 0.001], [0.009, 0.009, 0.009], [0.5, 0.5, 0.5]]) + 1e6
    cols = np.array([[0, 0, 0], [200, 100, 50], [10, 10, 10]], np.uint8)
    keys, sums = voxel_sums(pts, cols, np.ones(3, np.float32), np.full(3, 1e6), 0.01)
    assert len(keys) == 2
    np.testing.assert_allclose(sums[0, :3] / sums[0, 6], [0.005] * 3, atol=1e-12)
    np.testing.assert_allclose(sums[0, 3:6] / sums[0, 6], [100, 50, 25])
    assert sums[0, 7] == 2


def test_tiles_merge_a_noisy_plane_and_drop_outliers(tmp_path):
    rng = np.random.default_rng(1)
    n = 200_000
    xy = rng.uniform(0, 30, (n, 2))  # spans several 16 m tiles
    pts = np.concatenate([xy, 0.003 * rng.normal(size=(n, 1))], axis=1)
    outliers = np.concatenate([rng.uniform(0, 30, (50, 2)), rng.uniform(1, 3, (50, 1))], axis=1)
    cfg = FusionConfig(voxel_size=0.1, min_observations=1)
    spill = TileSpill(tmp_path / "spill", np.zeros(3), cfg)
    for i, chunk in enumerate(np.array_split(np.concatenate([pts, outliers]), 4)):  # four "frames"
        spill.add_frame(f"{i:06d}", chunk, np.full((len(chunk), 3), 128, np.uint8), np.ones(len(chunk), np.float32))
    assert len(spill.tiles()) >= 4
    pcd = merge_to_cloud(spill, np.array([[15.0, 15.0, 10.0]]))
    p = np.asarray(pcd.points)
    assert np.abs(p[:, 2]).max() < 0.05  # the outliers floating above are gone
    assert len(p) > 0.95 * (300 * 300)  # nearly every 10 cm cell of the plane survives, seams included
    normals = np.asarray(pcd.normals)
    assert np.median(normals[:, 2]) > 0.99  # oriented up, towards the camera


def test_cloud_io_roundtrip_and_errors(tmp_path):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array([[1e6, 2.5, 3.0], [1e6 + 0.01, 2.5, 3.0]])))
    pcd.colors = o3d.utility.Vector3dVector(np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    path = write_cloud(tmp_path / "c.ply", pcd)
    back = read_cloud(path)
    np.testing.assert_array_equal(np.asarray(back.points), np.asarray(pcd.points))  # float64 kept
    bad = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array([[0.0, np.nan, 0.0], [1.0, 2.0, np.inf]])))
    bad.colors = o3d.utility.Vector3dVector(np.zeros((2, 3)))
    o3d.io.write_point_cloud(str(tmp_path / "bad.ply"), bad)
    with pytest.raises(DataFormatError, match=f"{tmp_path / 'bad.ply'}.*NaN or inf"):
        read_cloud(tmp_path / "bad.ply")
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\n")
    with pytest.raises(DataFormatError, match="junk.ply"):
        read_cloud(tmp_path / "junk.ply")
    with pytest.raises(DataFormatError, match="missing"):
        read_cloud(tmp_path / "nope.ply")


@pytest.mark.parametrize("normals", [True, False])
def test_streamed_ply_reads_back_in_open3d(tmp_path, normals):
    rng = np.random.default_rng(2)
    chunks = [(rng.normal(size=(n, 3)) * 100 + 1e6, rng.integers(0, 256, (n, 3), dtype=np.uint8),
               rng.normal(size=(n, 3))) for n in (5, 0, 17)]
    path = tmp_path / "s.ply"
    with PlyStreamWriter(path, normals=normals) as w:
        for p, c, n in chunks:
            w.append(p, c, n if normals else None)
    pcd = read_cloud(path)
    np.testing.assert_array_equal(np.asarray(pcd.points), np.concatenate([p for p, _, _ in chunks]))
    np.testing.assert_allclose(np.asarray(pcd.colors) * 255, np.concatenate([c for _, c, _ in chunks]), atol=1e-9)
    assert pcd.has_normals() == normals
    if normals:
        np.testing.assert_allclose(np.asarray(pcd.normals), np.concatenate([n for _, _, n in chunks]), rtol=1e-6)
    assert [f.name for f in tmp_path.iterdir()] == ["s.ply"]  # no body or temporary file left


def test_streamed_ply_leaves_nothing_when_interrupted(tmp_path):
    with pytest.raises(RuntimeError):
        with PlyStreamWriter(tmp_path / "s.ply") as w:
            w.append(np.zeros((3, 3)), np.zeros((3, 3), np.uint8), np.zeros((3, 3)))
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("n, c", [(0, 5), (1, 1), (1000, 3), (5000, 400)])
def test_nearest_camera_matches_brute_force(n, c):
    from recon.fusion import nearest_camera, nearest_camera_reference

    rng = np.random.default_rng(n + c)
    points, cameras = rng.uniform(-50, 50, (n, 3)), rng.uniform(-50, 50, (c, 3))
    np.testing.assert_array_equal(nearest_camera(points, cameras), nearest_camera_reference(points, cameras))
