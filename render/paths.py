"""Camera paths: the poses to render a model from or to drive along.

Every pose is a ``world_from_cam`` (4, 4) float64 (OpenCV camera axes, world z up).
Pure numpy (no moderngl), so they are made and tested without a GPU.

* :class:`DrivePath`, :func:`drive_path_for` — the capture path as a looping polyline
  (the viewer's drive mode; :func:`capture_poses` samples it);
* ``bbcity render --path``, :func:`camera_path`: ``capture`` drives the capture path
  (the model's dataset poses, else along its extent), ``orbit`` circles the model from
  above (:func:`orbit_poses`), or a file (:func:`file_poses`): a dataset directory (its
  camera-0 poses) or a JSON list of 4×4 ``world_from_cam`` matrices
  (:func:`save_poses_json` writes one);
* the benchmark's viewpoints: :func:`street_views`, :func:`town_views` and :func:`walk`;
  along the capture path, :func:`capture_camera_poses` (camera 0 of every posed frame of
  the model's dataset), :func:`densify_poses` (a walk: poses at most a step apart) and
  :func:`capture_walk` (a stretch of that walk).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from capture.dataset import load_dataset
from capture.poses import load_poses
from core.errors import InputError
from core.fileio import DataFormatError, as_matrix, check_rigid, read_json, write_bytes

from .camera import look_at

logger = logging.getLogger(__name__)


class DrivePath:
    """A looping polyline of camera positions (world, float64) parametrised by arc length."""

    def __init__(self, points, speed: float = 8.0, lookahead: float = 5.0):
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if len(pts) == 0:
            raise InputError("a drive path needs at least one point")
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        pts = pts[keep]
        if len(pts) == 1:
            pts = np.stack([pts[0], pts[0] + [1.0, 0.0, 0.0]])
        self.points = pts
        self.cumlen = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        self.speed = float(speed)
        self.lookahead = float(lookahead)
        self.s = 0.0

    @property
    def length(self) -> float:
        return float(self.cumlen[-1])

    def position(self, s: float) -> np.ndarray:
        """Point at arc length ``s`` (wraps around: the path loops)."""
        s = float(s) % self.length
        i = int(np.clip(np.searchsorted(self.cumlen, s, side="right") - 1, 0, len(self.points) - 2))
        seg = self.cumlen[i + 1] - self.cumlen[i]
        a = (s - self.cumlen[i]) / seg if seg > 0 else 0.0
        return self.points[i] * (1 - a) + self.points[i + 1] * a

    def heading(self, s: float) -> np.ndarray:
        """Unit viewing direction at ``s``: toward the point ``lookahead`` metres ahead (smooth at corners)."""
        d = self.position(s + self.lookahead) - self.position(s)
        if np.linalg.norm(d[:2]) < 1e-6:  # wrapped onto itself: use the local segment
            d = self.position(s + 1e-3) - self.position(s)
        if np.linalg.norm(d[:2]) < 1e-9:
            d = np.array([1.0, 0.0, 0.0])
        return d / np.linalg.norm(d)

    def pose(self, s: float | None = None) -> np.ndarray:
        s = self.s if s is None else s
        p = self.position(s)
        return look_at(p, p + self.heading(s))

    def step(self, dt: float) -> np.ndarray:
        self.s = (self.s + self.speed * dt) % self.length
        return self.pose()


def drive_path_for(model, height: float = 2.0) -> DrivePath:
    """The capture path from the poses the model was built with (``model.info["poses"]``, a
    recon's WORK/poses.json, else ``model.info["dataset"]``'s poses.json; frames without a
    pose skipped), at ``height`` above the rig, else a straight line at ``height`` along the
    model's x extent."""
    info = model.info if isinstance(model.info, dict) else {}
    dataset = info.get("dataset")
    if dataset:
        try:
            poses = info.get("poses") or Path(dataset) / "poses.json"
            world_from_rig, _ = load_poses(poses)
            pts = world_from_rig[:, :3, 3] + [0.0, 0.0, height]
            pts = pts[np.isfinite(pts).all(axis=1)]
            if len(pts) < 2:
                raise InputError(f"{poses}: fewer than two frames have a pose")
            return DrivePath(pts)
        except Exception as e:  # missing or moved dataset: fall back to the model's extent
            logger.info("no capture path from %s (%s); driving along the model", dataset, e)
    origin = np.asarray(model.origin, np.float64)
    c = np.asarray(model.centres, np.float64)
    if len(c) == 0:
        return DrivePath([origin + [0, 0, height], origin + [10.0, 0, height]])
    lo, hi = c.min(0), c.max(0)
    y = float(np.median(c[:, 1]))
    z = float(lo[2]) + height
    start = origin + [lo[0] - 10.0, y, z]
    end = origin + [hi[0] + 10.0, y, z]
    return DrivePath([start, end])


def capture_poses(model, frames: int) -> np.ndarray:
    """(frames, 4, 4) float64 poses evenly spaced along the capture (drive) path."""
    path = drive_path_for(model)
    return np.stack([path.pose(path.length * i / max(frames, 1)) for i in range(frames)])


def orbit_poses(model, frames: int, height: float = 15.0) -> np.ndarray:
    """(frames, 4, 4) float64 poses on a circle around the model's centre, looking at it."""
    c = np.asarray(model.centres, np.float64)
    origin = np.asarray(model.origin, np.float64)
    if len(c) == 0:
        centre, radius = origin, 10.0
    else:
        lo, hi = c.min(0), c.max(0)
        centre = origin + (lo + hi) / 2
        radius = max(5.0, 0.6 * float(np.linalg.norm(hi[:2] - lo[:2])))
    angles = 2 * np.pi * np.arange(frames) / max(frames, 1)
    eyes = centre + np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(frames, height)], 1)
    return np.stack([look_at(e, centre) for e in eyes]) if frames else np.zeros((0, 4, 4))


#: Poses a path file may hold (as ``render --frames`` at most): each becomes a frame.
MAX_PATH_POSES = 100_000


def file_poses(path: os.PathLike | str) -> np.ndarray:
    """Poses from a dataset directory (camera 0 of every frame) or a JSON list of 4×4
    ``world_from_cam`` matrices, at most :data:`MAX_PATH_POSES`; errors name the file."""
    path = Path(path)
    if path.is_dir():
        ds = load_dataset(path)
        posed = np.flatnonzero(ds.posed).tolist()
        if len(posed) > MAX_PATH_POSES:
            raise DataFormatError(path / "poses.json", f"holds {len(posed)} posed frames; a path renders at most "
                                                       f"{MAX_PATH_POSES} frames")
        if not posed:
            raise DataFormatError(path / "poses.json", "no frame has a pose (--path capture follows the poses "
                                                       "the model was built with)")
        return np.stack([ds.world_from_cam(f, 0) for f in posed])
    data = read_json(path)
    if not isinstance(data, list) or not data:
        raise DataFormatError(path, "expected a non-empty JSON list of 4×4 world_from_cam matrices")
    if len(data) > MAX_PATH_POSES:
        raise DataFormatError(path, f"holds {len(data)} poses; a path renders at most {MAX_PATH_POSES} frames")
    return np.stack([check_rigid(as_matrix(m, (4, 4), path, f"[{i}]"), path, f"[{i}]") for i, m in enumerate(data)])


def camera_path(model, path: str, frames: int) -> np.ndarray:
    """(n, 4, 4) world_from_cam poses for ``path`` = "capture", "orbit" or a file."""
    if path == "capture":
        return capture_poses(model, frames)
    if path == "orbit":
        return orbit_poses(model, frames)
    return file_poses(path)


def save_poses_json(path: os.PathLike | str, poses: np.ndarray) -> Path:
    """Write poses (n, 4, 4) as the JSON list :func:`file_poses` reads."""
    return write_bytes(path, json.dumps([p.tolist() for p in np.asarray(poses, np.float64)]).encode())


def street_views(length: float = 300.0, height: float = 2.0, lane: float = 2.0) -> dict[str, np.ndarray]:
    """Capture-like world_from_cam poses (world coordinates) for a street along +x."""
    mid = length / 2
    return {"facade -y": look_at([mid, lane, height], [mid, -10.0, height]),
            "facade +y": look_at([mid, -lane, height], [mid, 10.0, height]),
            "along +x": look_at([0.1 * length, 0.0, height], [0.1 * length + 40.0, 0.0, height])}


def town_views(world_from_rig: np.ndarray, height: float = 1.0) -> list[np.ndarray]:
    """Street-level world_from_cam poses along a capture path: the rig's position
    ``height`` m higher, looking along its direction of travel (the long view down a
    town street, where almost everything in the frustum hides behind the first houses)."""
    views = []
    for pose in np.asarray(world_from_rig, np.float64).reshape(-1, 4, 4):
        eye = pose[:3, 3] + [0.0, 0.0, height]
        views.append(look_at(eye, eye + 10.0 * pose[:3, 0]))
    return views


def walk(world_from_cam: np.ndarray, count: int, step: float = 0.05) -> list[np.ndarray]:
    """``count`` poses stepping ``step`` metres along the camera's x axis from ``world_from_cam``,
    so that every timed frame has a new eye (nothing view-dependent can be reused)."""
    poses = []
    for i in range(count):
        pose = np.array(world_from_cam, dtype=np.float64)
        pose[:3, 3] += step * (i + 1) * pose[:3, 0]
        poses.append(pose)
    return poses


def capture_camera_poses(model, dataset: os.PathLike | str | None = None) -> np.ndarray | None:
    """(n, 4, 4) float64 world_from_cam of camera 0 in every posed frame of ``dataset`` (a
    dataset directory), in frame order; by default the model's own (``model.info["dataset"]``),
    then with the poses it was built with (``info["poses"]``, e.g. from SfM). None when no
    dataset is given and the model's is not recorded or no longer readable; a given
    dataset that cannot be read raises (DataFormatError naming the file)."""
    info = model.info if isinstance(model.info, dict) else {}
    recorded = info.get("dataset")
    if dataset is None:
        if not isinstance(recorded, str):
            return None
        try:
            return capture_camera_poses(model, recorded)
        except (OSError, ValueError) as e:  # a moved or deleted dataset: no capture path
            logger.info("no capture path from %s (%s)", recorded, e)
            return None
    own = isinstance(recorded, str) and Path(recorded).resolve() == Path(dataset).resolve()
    poses = info.get("poses") if own and isinstance(info.get("poses"), str) else None
    ds = load_dataset(dataset, poses=poses)
    posed = np.flatnonzero(ds.posed).tolist()
    if not posed:
        raise DataFormatError(Path(poses or Path(dataset) / "poses.json"), "no frame has a pose")
    return np.stack([ds.world_from_cam(f, 0) for f in posed])


def _quaternions(R: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (w, x, y, z), sign arbitrary, of rotation matrices ``R`` (n, 3, 3)."""
    m = np.asarray(R, np.float64).reshape(-1, 3, 3)
    d0, d1, d2 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    # each row of a case is 4·q_k·(w, x, y, z); the case of the largest q_k is the best conditioned
    cases = np.stack([
        np.stack([1 + d0 + d1 + d2, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], 1),
        np.stack([m[:, 2, 1] - m[:, 1, 2], 1 + d0 - d1 - d2, m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], 1),
        np.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 - d0 + d1 - d2, m[:, 1, 2] + m[:, 2, 1]], 1),
        np.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1], 1 - d0 - d1 + d2], 1),
    ])  # (4, n, 4)
    k = np.argmax(np.stack([cases[i, :, i] for i in range(4)]), axis=0)
    q = cases[k, np.arange(len(m))]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _rotations(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of quaternions ``q`` (n, 4) (w, x, y, z), normalised first."""
    q = np.asarray(q, np.float64) / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)


def densify_poses(poses: np.ndarray, step: float) -> np.ndarray:
    """(m, 4, 4) float64 poses along ``poses`` (n, 4, 4) world_from_cam with consecutive eyes at
    most ``step`` metres apart: each gap split evenly, positions interpolated linearly and
    rotations by spherical interpolation (a turn on the spot stays one pose: its eyes do not
    move). The input poses are kept; ``step`` ≤ 0 returns them as they are."""
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    if step <= 0 or len(poses) < 2:
        return poses.copy()
    eye = poses[:, :3, 3]
    parts = np.maximum(np.ceil(np.linalg.norm(np.diff(eye, axis=0), axis=1) / step).astype(np.int64), 1)
    seg = np.repeat(np.arange(len(poses) - 1), parts)  # the gap each output pose (but the last) lies in
    t = (np.arange(len(seg)) - np.repeat(np.cumsum(parts) - parts, parts)) / np.repeat(parts, parts)
    q = _quaternions(poses[:, :3, :3])
    q0, q1 = q[seg], q[seg + 1]
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)  # the shorter way round
    angle = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sin(angle)
        a = np.where(s > 1e-9, np.sin((1 - t) * angle) / s, 1 - t)
        b = np.where(s > 1e-9, np.sin(t * angle) / s, t)
    out = np.tile(np.eye(4), (len(seg) + 1, 1, 1))
    out[:-1, :3, :3] = _rotations(a[:, None] * q0 + b[:, None] * q1)
    out[:-1, :3, 3] = eye[seg] * (1 - t[:, None]) + eye[seg + 1] * t[:, None]
    out[:-1][t == 0] = poses[seg[t == 0]]  # the input poses exactly
    out[-1] = poses[-1]
    return out


def capture_walk(poses: np.ndarray, step: float, frames: int, at: float = 0.25) -> np.ndarray:
    """A walk along a capture path: ``poses`` (n, 4, 4) densified to ``step`` metres
    (:func:`densify_poses`), then the ``frames`` consecutive poses centred ``at`` (a fraction)
    of the way along it — a quarter of the way is the middle of the outbound pass of a
    there-and-back drive; ``frames`` ≤ 0 or more than there are: all of them."""
    walk_poses = densify_poses(poses, step)
    if frames <= 0 or frames >= len(walk_poses):
        return walk_poses
    first = int(np.clip(round(at * (len(walk_poses) - 1) - frames / 2), 0, len(walk_poses) - frames))
    return walk_poses[first:first + frames]
