"""The viewpoints of a novel-view evaluation: which frames, where the camera stands (on path,
off path, training), and a real capture's held-out images as views.

The ground truth of a synthetic view is rendered by :func:`render.evaluate.prepare_views`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .eval_config import EvalConfig


def off_path(world_from_cam: np.ndarray, sideways: float = 2.0, up: float = 1.0) -> np.ndarray:
    """The camera moved ``sideways`` metres back along its horizontal viewing direction
    (away from what it looks at, toward the middle of the street) and ``up`` metres up."""
    pose = np.array(world_from_cam, dtype=np.float64)
    forward = pose[:3, 2].copy()
    forward[2] = 0.0
    norm = np.linalg.norm(forward)
    if norm > 1e-9:
        pose[:3, 3] -= sideways * forward / norm
    pose[2, 3] += up
    return pose


@dataclass(eq=False)
class EvalView:
    """One viewpoint with its ground truth: truth (h, w, 3) uint8; geometry (h, w) bool
    (the ground truth hits a surface); seen (h, w) bool (a capture camera saw it); real:
    the truth is a captured image (geometry and seen: the pixels below the horizon); near
    (h, w) bool: seen pixels nearer than :attr:`EvalConfig.near` (None: not known)."""

    frame: int
    where: str              # "on path" | "off path"
    K: np.ndarray
    world_from_cam: np.ndarray
    size: tuple[int, int]
    truth: np.ndarray
    geometry: np.ndarray
    seen: np.ndarray
    real: bool = False
    near: np.ndarray | None = None


def choose_frames(info: dict | None, num_frames: int, views: int | None,
                  posed: np.ndarray | None = None) -> tuple[np.ndarray, list[int], bool]:
    """(frames, texture_frames, held_out): up to ``views`` frames (None: all) spread over the
    frames a model left out of its textures (``info["held_out_frames"]``), else over all
    frames; the frames the textures came from; whether the viewpoints were held out.
    posed: (num_frames,) bool, the frames that have a pose (None: all); the others are
    never chosen."""
    posed = np.ones(num_frames, bool) if posed is None else np.asarray(posed, bool)
    held = sorted({int(f) for f in (info or {}).get("held_out_frames", []) or []
                   if 0 <= int(f) < num_frames and posed[int(f)]})
    pool = np.asarray(held) if held else np.flatnonzero(posed)
    views = len(pool) if views is None else views
    frames = np.unique(pool[np.linspace(0, len(pool) - 1, max(1, views)).round().astype(int)])
    texture_frames = [f for f in range(num_frames) if f not in set(held) and posed[f]]
    return frames, texture_frames, bool(held)


def training_frames(texture_frames, count: int) -> np.ndarray:
    """(k,) int64: up to ``count`` of ``texture_frames`` (the frames the textures came from),
    spread evenly over them."""
    pool = np.asarray(texture_frames, np.int64)
    if count <= 0 or len(pool) == 0:
        return np.zeros(0, np.int64)
    return np.unique(pool[np.linspace(0, len(pool) - 1, count).round().astype(int)])


def view_camera(rig, size: tuple[int, int] | None) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """Camera 0 of ``rig`` rendered at ``size`` (w, h; None: its own): K (3, 3) float64
    scaled to that size, the size, and the camera's own size."""
    K = rig.intrinsics[0]
    native = tuple(int(s) for s in rig.sizes[0])
    size = native if size is None else tuple(int(s) for s in size)
    if size != native:
        K = np.diag([size[0] / native[0], size[1] / native[1], 1.0]) @ K
    return K, size, native


def below_horizon(K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: the pixels whose viewing ray points down (world z < 0) — for a camera on
    a car, everything that is ground or stands on it, never the sky."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    return (rays @ np.asarray(world_from_cam, np.float64)[:3, :3].T)[..., 2] < 0


def prepare_real_views(dataset, frames, config: EvalConfig = EvalConfig(), where: str = "on path") -> list[EvalView]:
    """The camera-0 images of ``frames`` of a real capture as views (``where``: "on path" for
    held-out frames, :data:`TRAINING` for frames the textures came from; geometry and seen
    pixels: those below the horizon)."""
    K, size, native = view_camera(dataset.rig, config.size)
    views = []
    for f in frames:
        pose = dataset.world_from_cam(int(f), 0)
        truth = dataset.image(int(f), 0)
        if size != native:
            truth = cv2.resize(truth, size, interpolation=cv2.INTER_AREA)
        ground = below_horizon(K, pose, size)
        views.append(EvalView(int(f), where, K, pose, size, truth, ground, ground, real=True))
    return views

