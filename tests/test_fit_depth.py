"""The fit's geometry (billboards.fit_depth): the photo-consistency cost against its
one-ray-at-a-time reference, and a billboard placed off its surface moved back onto it by
the rays of a few views."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.fit import FitConfig, cast_view, quads_of, view_records
from billboards.fit_depth import costs, costs_reference, depth_moves, offsets_of, ray_geometry
from billboards.geometry import BILLBOARD, FACADE


def billboards(centres, kind=BILLBOARD):
    n = len(centres)
    return quads_of(np.zeros(3), np.asarray(centres, np.float32), np.full(n, -np.pi / 2, np.float32),
                    np.full(n, kind, np.uint8), 0.5, 0.5, 8, np.linspace(-0.6, 0.6, 5), np.zeros(1))


def cameras(count=5):
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    poses = []
    for x in np.linspace(-2.0, 2.0, count):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = [[1.0, 0, 0], [0, 0, 1], [0, -1, 0]], [x, -4.0, 1.5]    # looking along +y
        poses.append(T)
    return np.repeat(K[None], count, axis=0), np.stack(poses), (160, 120)


def truth_image(K, pose, size):
    """A checkered wall in the plane y = 0 (squares of 15 cm)."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ pose[:3, :3].T
    t = -pose[1, 3] / d[..., 1]
    p = pose[:3, 3] + t[..., None] * d
    odd = (np.floor(p[..., 0] / 0.15) + np.floor(p[..., 2] / 0.15)) % 2 == 1
    return np.where(odd[..., None], np.array([220, 60, 40], np.uint8), np.array([30, 90, 200], np.uint8))


def records_of(quads, K, poses, size):
    alpha = np.full((len(quads.kind), quads.num_directions, quads.tile ** 2), 255, np.uint8)
    rec = [view_records(cast_view(quads, alpha, K[i], poses[i], size), truth_image(K[i], poses[i], size), i)
           for i in range(len(poses))]
    return np.concatenate(rec)


@pytest.mark.parametrize("seed", [0, 1])
def test_costs_match_their_reference(seed):
    rng = np.random.default_rng(seed)
    quads = billboards([[0.0, -0.1, 1.5], [0.6, 0.05, 1.4]])
    K, poses, size = cameras()
    rec = records_of(quads, K, poses, size)
    rec = rec[rng.choice(len(rec), 300, replace=False)]
    eye, direction = ray_geometry(rec, K, poses)
    ids, local = np.unique(rec["quad"].astype(np.int64), return_inverse=True)
    colour = rec["colour"] / 255.0
    offsets = offsets_of(FitConfig())
    np.testing.assert_allclose(costs(quads, ids, local, eye, direction, colour, offsets),
                               costs_reference(quads, ids, local, eye, direction, colour, offsets), rtol=1e-9, atol=1e-6)


def test_ray_geometry_points_back_at_the_pixel():
    K, poses, size = cameras()
    rec = records_of(billboards([[0.0, 0.0, 1.5]]), K, poses, size)
    assert len(np.unique(rec["view"])) >= 3
    eye, direction = ray_geometry(rec, K, poses)
    for i in (0, len(rec) - 1):
        cam = np.linalg.inv(poses[rec["view"][i]]) @ np.append(eye[i] + 3.0 * direction[i], 1.0)
        np.testing.assert_allclose(K[0] @ (cam[:3] / cam[2]), [*rec["pixel"][i], 1.0], atol=1e-6)


@pytest.mark.parametrize("off", [0.2, -0.2])
def test_a_billboard_off_its_surface_moves_back_onto_it(off):
    # base direction (0, −1, 0): toward the cameras; the wall is at y = 0, the billboard off it by ``off``
    quads = billboards([[0.0, -off, 1.5]])
    K, poses, size = cameras()
    rec = records_of(quads, K, poses, size)
    ids, centres = depth_moves(quads, rec, K, poses, np.array([[0.0, 0.0, 1.5]]), 0.5, FitConfig())
    np.testing.assert_array_equal(ids, [0])
    np.testing.assert_allclose(centres[0], [0.0, 0.0, 1.5], atol=1e-6)


def test_on_its_surface_or_with_few_rays_a_billboard_stays():
    K, poses, size = cameras()
    quads = billboards([[0.0, 0.0, 1.5]])
    rec = records_of(quads, K, poses, size)
    assert len(depth_moves(quads, rec, K, poses, quads.centres, 0.5, FitConfig())[0]) == 0
    off = billboards([[0.0, -0.2, 1.5]])
    rec = records_of(off, K, poses, size)
    few = FitConfig(depth_min_rays=len(rec) + 1)
    assert len(depth_moves(off, rec, K, poses, off.centres, 0.5, few)[0]) == 0
    one_view = rec[rec["view"] == 0]
    assert len(depth_moves(off, one_view, K, poses, off.centres, 0.5, FitConfig())[0]) == 0
    # blocks of the layer keep their places
    block = billboards([[0.0, -0.2, 1.5]], kind=FACADE)
    rec = records_of(block, K, poses, size)
    assert len(depth_moves(block, rec, K, poses, block.centres, 0.5, FitConfig())[0]) == 0
    assert len(depth_moves(off, rec[:0], K, poses, off.centres, 0.5, FitConfig())[0]) == 0


def test_a_billboard_stays_inside_its_voxel():
    quads = billboards([[0.0, -0.2, 1.5]])
    K, poses, size = cameras()
    rec = records_of(quads, K, poses, size)
    # its voxel's centre 0.3 m toward the cameras: a move to y = 0 would leave the slab (±0.25 m)
    ids, centres = depth_moves(quads, rec, K, poses, np.array([[0.0, -0.3, 1.5]]), 0.5, FitConfig())
    np.testing.assert_allclose(centres[0], [0.0, -0.05, 1.5], atol=1e-6)


def test_config_refuses_bad_depth_settings():
    for bad in ({"depth_step": 0.0}, {"depth_step": float("inf")}, {"depth_steps": -1}, {"depth_gain": 1.0},
                {"depth_gain": -0.1}, {"depth_min_rays": 0}, {"depth": 1}):
        with pytest.raises(ValueError):
            FitConfig(**bad)
