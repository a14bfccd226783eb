"""The world's up from the ground plane of sparse points (recon.ground_plane)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.ground_plane import GroundUpConfig, ground_up


def _street(rng, n_ground=800, n_facade=3000) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points of a walk along a facade 8 m away (more facade than ground, as SfM
    finds them) and the camera centres 1.6 m above the ground, z up."""
    x = rng.uniform(-5, 35, n_ground)
    ground = np.stack([x, rng.uniform(1, 8, n_ground), rng.normal(0, 0.01, n_ground)], 1)
    fx = rng.uniform(-5, 35, n_facade)
    facade = np.stack([fx, 8 + rng.normal(0, 0.01, n_facade), rng.uniform(0, 12, n_facade)], 1)
    centres = np.stack([np.arange(0, 30, 1.0), np.zeros(30), np.full(30, 1.6)], 1)
    return np.concatenate([ground, facade]), centres


def _turn(v: np.ndarray, deg: float) -> np.ndarray:
    """Rotate about the x axis (the travel direction) by ``deg``."""
    a = np.radians(deg)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return v @ R.T


@pytest.mark.parametrize("pitch", [0.0, 8.0, -12.0])
def test_the_ground_corrects_the_pitch_of_the_cameras(pitch):
    rng = np.random.default_rng(1)
    points, centres = _street(rng)
    # any SfM frame: rotated, moved and scaled
    a = np.radians(33.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ _turn(np.eye(3), 50.0)
    frame = lambda p: 0.13 * p @ R.T + [4.0, -7.0, 2.0]  # noqa: E731
    cameras_up = _turn(np.array([0.0, 0.0, 1.0]), pitch) @ R.T  # the cameras' estimate, off by the pitch
    up = ground_up(frame(points), frame(centres), cameras_up)
    truth = np.array([0.0, 0.0, 1.0]) @ R.T
    assert up is not None and np.degrees(np.arccos(np.clip(up @ truth, -1, 1))) < 0.5
    assert up @ cameras_up > 0  # on the cameras' side


@pytest.mark.parametrize("pitch", [0.0, 8.0, -12.0])
def test_with_no_ground_the_wall_corrects_the_pitch(pitch):
    # asphalt gives SIFT no points: only the facade, whose foot lies below the cameras
    rng = np.random.default_rng(2)
    points, centres = _street(rng, n_ground=0)
    up = ground_up(points, centres, _turn(np.array([0.0, 0.0, 1.0]), pitch))
    assert up is not None and np.degrees(np.arccos(np.clip(up[2], -1, 1))) < 0.5


def test_neither_ground_nor_wall_keeps_the_cameras_estimate():
    rng = np.random.default_rng(3)
    _, centres = _street(rng)
    # a ramp of 30° is no ground, nor a wall
    ramp = _turn(_street(rng, n_facade=0)[0], 30.0)
    assert ground_up(ramp, centres, np.array([0.0, 0.0, 1.0])) is None
    # points in no plane at all
    assert ground_up(rng.normal(0, 5, (2000, 3)) - [0, 0, 5], centres, np.array([0.0, 0.0, 1.0])) is None


def test_degenerate_inputs():
    up = np.array([0.0, 0.0, 1.0])
    assert ground_up(np.zeros((0, 3)), np.zeros((3, 3)), up) is None
    assert ground_up(np.full((100, 3), np.nan), np.zeros((3, 3)), up) is None
    assert ground_up(np.random.default_rng(0).normal(size=(100, 3)), np.zeros((0, 3)), up) is None
    assert ground_up(np.ones((100, 3)), np.ones((3, 3)), up) is None  # every point at the cameras
    with pytest.raises(ValueError):
        GroundUpConfig(max_tilt_deg=95.0)
    with pytest.raises(ValueError):
        GroundUpConfig(min_inliers=2)
