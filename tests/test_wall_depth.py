"""Side walls as deep as the images show them (billboards.wall_depth)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest

from billboards.voxels import zbuffer
from billboards.sky import Sky
from billboards.wall_depth import (WallDepthConfig, column_blocks, deepen_side_walls, front_steps, grown_columns,
                                   side_wall_faces, upward_blocks, wall_votes, wall_votes_reference)

SKY = (0.4, 0.6, 0.9)
WALL = (0.6, 0.25, 0.2)


def _look_minus_y(x: float, y: float = 0.0, z: float = 2.0) -> np.ndarray:
    """Pose of a camera at (x, y, z) looking along −y (its x axis along +x, its y axis down)."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]]).T
    pose[:3, 3] = (x, y, z)
    return pose


@dataclass
class _Views:
    K: np.ndarray
    world_from_cam: np.ndarray
    sizes: np.ndarray
    images: list

    @property
    def centres(self) -> np.ndarray:
        return self.world_from_cam[:, :3, 3]

    def image(self, i: int) -> np.ndarray:
        return self.images[i]


def _wall_views(xs, rear: float = 15.0, size=(160, 120), f=60.0) -> _Views:
    """Cameras at (x, 0, 2) looking −y at a wall on the plane x = 10 (facing +x) from y = −5
    to y = −rear, 10 m high, against a plain sky."""
    w, h = size
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    poses, images = [], []
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    for x in xs:
        pose = _look_minus_y(x)
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ pose[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (10.0 - x) / rays[..., 0]
        hit = pose[:3, 3] + t[..., None] * rays
        on = (t > 0) & (hit[..., 1] <= -5) & (hit[..., 1] >= -rear) & (hit[..., 2] >= 0) & (hit[..., 2] <= 10)
        images.append(np.where(on[..., None], np.array(WALL), np.array(SKY)).__mul__(255).round().astype(np.uint8))
        poses.append(pose)
    return _Views(np.repeat(K[None], len(xs), 0), np.array(poses), np.tile([w, h], (len(xs), 1)), images)


def _known_wall(depth: float = 8.0, height: float = 10.0):
    """The side wall's blocks stereo found: x = 10, y from −5 to −depth, rows to ``height``,
    facing +x; its cloud points."""
    ys = -(5.25 + 0.5 * np.arange(int(round((depth - 5) / 0.5))))
    zs = 0.25 + 0.5 * np.arange(int(round(height / 0.5)))
    centres = np.array([(10.0, y, z) for y in ys for z in zs])
    rng = np.random.default_rng(0)
    cloud = np.stack([np.full(3000, 10.0), rng.uniform(-depth, -5, 3000), rng.uniform(0, 10, 3000)], 1)
    return centres, np.zeros(len(centres)), cloud


def test_a_wall_grows_to_its_rear_where_the_images_show_it_and_no_farther():
    centres, yaw, cloud = _known_wall()
    views = _wall_views(np.arange(14.0, 32.0, 1.5))
    sky = Sky(np.tile(np.array(SKY, np.float32), (8, 1)))
    c, y, report = deepen_side_walls(centres, yaw, cloud, views, sky, 0.5)
    assert report["walls"] == 1 and report["walls_grown"] == 1 and len(c) == report["blocks"]
    assert np.allclose(c[:, 0], 10.0) and np.allclose(y, 0.0)
    depths = np.unique(np.round(-c[:, 1], 3))
    assert np.isclose(depths.min(), 8.25) and np.isclose(depths.max(), 14.75)   # the rear is at 15 m
    assert c[:, 2].max() < 10.0
    # the views read in runs by a pool of workers: the same blocks
    with ThreadPoolExecutor(3) as pool:
        c_pool, y_pool, report_pool = deepen_side_walls(centres, yaw, cloud, views, sky, 0.5, executor=pool)
    assert np.array_equal(c_pool, c) and np.array_equal(y_pool, y) and report_pool == report
    # against a sky-coloured wall nothing grows; without a sky nothing either
    plain = _Views(views.K, views.world_from_cam, views.sizes,
                   [np.broadcast_to((np.array(SKY) * 255).round().astype(np.uint8), i.shape).copy() for i in views.images])
    assert len(deepen_side_walls(centres, yaw, cloud, plain, sky, 0.5)[0]) == 0
    assert len(deepen_side_walls(centres, yaw, cloud, views, None, 0.5)[0]) == 0
    assert len(deepen_side_walls(centres, yaw, cloud, views, sky, 0.5, WallDepthConfig(reach=0.0))[0]) == 0


def test_a_wall_known_to_part_of_its_height_grows_up_to_its_top_and_no_higher():
    """The wall found up to 6 m (as tall as the lower front beside it) belongs to a building 10 m
    tall: its columns, the stereo's and the grown ones, rise from their top without a gap, as far
    as cameras see them hold (the columns nearest the path are above every camera's view, or
    behind the wall's own points at grazing views), and none above 10 m; with rise 0 none rises."""
    centres, yaw, cloud = _known_wall(height=6.0)
    views = _wall_views(np.arange(14.0, 32.0, 1.5))
    sky = Sky(np.tile(np.array(SKY, np.float32), (8, 1)))
    c, _, report = deepen_side_walls(centres, yaw, cloud, views, sky, 0.5)
    assert report["walls_grown"] == 1
    high = c[c[:, 2] > 6.0]
    assert np.isclose(high[:, 2].max(), 9.75)
    depth = np.round(-high[:, 1], 3)
    for d in np.unique(depth):
        rows = np.sort(high[depth == d, 2])
        assert np.allclose(rows, 6.25 + 0.5 * np.arange(len(rows)))       # from the top up, no gap
        if d >= 8.0:                                                        # the columns grown deeper: whole
            assert len(rows) == 8
    stereo = np.unique(np.round(-centres[:, 1], 3))
    assert np.isin(np.round(stereo, 3), depth).sum() >= 3                 # the stereo's columns rise too
    flat, _, _ = deepen_side_walls(centres, yaw, cloud, views, sky, 0.5, WallDepthConfig(rise=0.0))
    assert flat[:, 2].max() < 6.0


def _stepped_front(low_top: float = 4.0):
    """A front on y = −5 along +x (the path on y = 0 looks −y), its columns 0.5 m wide from x = 0:
    10 m tall up to x = 10, ``low_top`` beyond."""
    from types import SimpleNamespace

    epi = SimpleNamespace(origin=np.zeros(3), axis=np.array([1.0, 0, 0]), facing=np.array([0, -1.0, 0]))
    along = (np.arange(40) + 0.5) * 0.5
    return SimpleNamespace(epi=epi, size=0.5, first=0, offset=np.full(40, 5.0),
                           bottom=np.zeros(40), top=np.where(along < 10, 10.0, low_top))


def test_a_taller_buildings_end_above_a_lower_neighbour_grows_from_the_step():
    """No side wall, no cloud point on it: where the front steps down from 10 m to 4 m at x = 10,
    the taller building's end (x = 10, facing +x, toward the lower roof) shows in the images
    between the two roofs; it grows from the front's plane to its rear, no higher than 10 m."""
    steps = front_steps([_stepped_front()], 0.5, 0.0, 2.0)
    assert len(steps) == 1 and steps[0].step
    wall = steps[0]
    assert np.allclose(wall.normal, [1, 0, 0]) and np.isclose(wall.plane[0], 10.0) and np.allclose(wall.deeper, [0, -1, 0])
    np.testing.assert_allclose(wall.rows, 4.25 + 0.5 * np.arange(12))
    assert front_steps([_stepped_front(low_top=8.5)], 0.5, 0.0, 2.0) == []            # a step of 1.5 m: none
    views = _wall_views(np.arange(14.0, 32.0, 1.5))
    sky = Sky(np.tile(np.array(SKY, np.float32), (8, 1)))
    cloud = np.zeros((0, 3))
    c, y, report = deepen_side_walls(np.zeros((0, 3)), np.zeros(0), cloud, views, sky, 0.5, steps=steps)
    assert report["steps"] == 1 and report["walls_grown"] == 1
    assert np.allclose(c[:, 0], 10.0) and np.allclose(y, 0.0)
    assert np.isclose(c[:, 2].min(), 4.25) and np.isclose(c[:, 2].max(), 9.75)
    depth = -c[:, 1]
    assert np.isclose(depth.min(), 5.25) and np.isclose(depth.max(), 14.75)   # the rear is at 15 m
    # a side wall already on that plane facing that way takes the step's place
    centres, yaw, wall_cloud = _known_wall()
    _, _, report = deepen_side_walls(centres, yaw, wall_cloud, views, sky, 0.5, steps=steps)
    assert report["steps"] == 0 and report["walls"] == 1


def test_upward_blocks_stop_below_open_space():
    holds = np.array([[True, True, False, False], [False, True, True, False], [True, False, True, True],
                      [False] * 4])
    observed = np.array([[True, True, True, False], [False, True, True, True], [True, True, True, True],
                         [True] * 4])
    # up to the highest hold with nothing seen open below it; an unobserved row below counts as wall
    assert upward_blocks(observed, holds).tolist() == [[True, True, False, False], [True, True, True, False],
                                                       [True, False, False, False], [False] * 4]
    assert upward_blocks(np.zeros((0, 3), bool), np.zeros((0, 3), bool)).shape == (0, 3)


def test_cameras_on_the_walls_hidden_side_do_not_vote():
    centres, yaw, cloud = _known_wall()
    views = _wall_views(np.arange(-10.0, 6.0, 1.5))     # x < 10: behind the face
    sky = Sky(np.tile(np.array(SKY, np.float32), (8, 1)))
    assert len(deepen_side_walls(centres, yaw, cloud, views, sky, 0.5)[0]) == 0


def test_wall_votes_match_the_reference_loop():
    rng = np.random.default_rng(1)
    views = _wall_views([18.0, 25.0])
    sky = Sky(np.tile(np.array(SKY, np.float32), (8, 1)))
    config = WallDepthConfig()
    occluders = np.stack([rng.uniform(12, 20, 2000), rng.uniform(-6, -3, 2000), rng.uniform(0, 4, 2000)], 1)
    beyond = np.stack([rng.uniform(2, 6, 4000), rng.uniform(-25, -12, 4000), rng.uniform(0, 3, 4000)], 1)
    occluders = np.concatenate([occluders, beyond])            # a building behind the wall's plane: seen through
    origin = occluders.mean(axis=0)
    for v in range(2):
        points = np.stack([np.full(500, 10.0), rng.uniform(-20, 0, 500), rng.uniform(-1, 12, 500)], 1)
        normals = np.tile([1.0, 0, 0], (500, 1))
        normals[::7] *= -1
        _, nearest = zbuffer((occluders - origin).astype(np.float32), origin, views.K[v], views.world_from_cam[v],
                             tuple(views.sizes[v]), config.zbuffer_scale)
        got = wall_votes(points, normals, views.K[v], views.world_from_cam[v], views.image(v), nearest, sky, config)
        want = wall_votes_reference(points, normals, views.K[v], views.world_from_cam[v], views.image(v), nearest,
                                    sky, config)
        assert got[0].any() and got[1].any() and (got[0] & ~got[1]).any() and (~got[0]).any()
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_a_camera_whose_cloud_lies_beyond_a_block_saw_through_it():
    """The wall's colour at the pixel, and the cloud's z-buffer there: empty (solid), well beyond
    the block (seen through: open), nearer (hidden: no vote); as the reference does."""
    views = _wall_views([20.0])
    sky = Sky(np.tile(np.array(SKY, np.float32), (8, 1)))
    config = WallDepthConfig()
    point, normal = np.array([[10.0, -10.0, 4.0]]), np.array([[1.0, 0.0, 0.0]])
    pose = views.world_from_cam[0]
    z = float((point[0] - pose[:3, 3]) @ pose[:3, 2])
    shape = tuple(-(-int(n) // config.zbuffer_scale) for n in views.sizes[0][::-1])
    for depth, want in ((np.inf, (True, True)), (1.5 * z, (True, False)), (1.05 * z, (True, True)),
                        (0.5 * z, (False, False))):
        buffer = np.full(shape, depth, np.float32)
        got = wall_votes(point, normal, views.K[0], pose, views.image(0), buffer, sky, config)
        ref = wall_votes_reference(point, normal, views.K[0], pose, views.image(0), buffer, sky, config)
        assert (bool(got[0][0]), bool(got[1][0])) == want == (bool(ref[0][0]), bool(ref[1][0])), depth


def test_columns_grow_on_their_observed_blocks_until_one_fails():
    config = WallDepthConfig()
    observed = np.ones((5, 4), bool)
    observed[:, :2] = False                       # the lower rows hidden by a neighbour
    holds = observed.copy()
    holds[3] = False                              # the rear
    assert grown_columns(observed, holds, config) == 3
    observed[1] = False                           # a column no camera sees ends the wall
    assert grown_columns(observed, holds, config) == 1
    assert grown_columns(np.zeros((0, 4), bool), np.zeros((0, 4), bool), config) == 0
    holds = np.array([[False, False, True, False, True], [False, False, False, False, False],
                      [False, True, False, True, False]])
    seen = np.array([[False, False, True, True, True], [True, True, True, True, True],
                     [True, True, True, True, False]])
    # down to the ground where nothing was seen below, up to the highest holding row; a column
    # with open space seen below stops above it; one that holds nowhere has no block
    assert column_blocks(seen, holds).tolist() == [[True, True, True, True, True], [False] * 5,
                                                   [False, True, True, True, False]]


def test_side_wall_faces_group_by_plane_and_facing_and_point_away_from_the_path():
    centres, yaw, _ = _known_wall()
    other = centres + np.array([5.0, 0, 0])
    walls = side_wall_faces(np.concatenate([centres, other, centres]),
                            np.concatenate([yaw, yaw, np.full(len(yaw), np.pi)]), 0.5, np.array([[20.0, 0, 2]]))
    assert len(walls) == 3
    for wall in walls:
        assert np.allclose(wall.deeper, [0, -1, 0]) and len(wall.rows) == 20
        assert np.isclose(wall.columns.max(), 7.75)


def test_wall_depth_config_is_validated():
    with pytest.raises(ValueError):
        WallDepthConfig(reach=-1.0)
    with pytest.raises(ValueError):
        WallDepthConfig(rise=float("nan"))
    with pytest.raises(ValueError):
        WallDepthConfig(agree=0.0)
    with pytest.raises(ValueError):
        WallDepthConfig(min_views=0)

