"""Motion stereo: depth from ONE camera, matching each frame with its neighbours.

A one-camera rig (a phone walked along a facade, a single camera looking out of
a car's side window) has no second camera; the camera's own motion between
frames is the baseline. For each reference frame:

1. **Partners** (:func:`select_partners`): the frames before and after it (up
   to ``max_frame_gap`` frames away in capture order) whose baseline, as a
   share of the reference frame's scene depth, lies in [``min_baseline_ratio``,
   ``max_baseline_ratio``], whose optical axis turned by at most
   ``max_view_angle_deg``, whose baseline lies within ``max_baseline_angle_deg``
   of the reference's x axis (sideways motion: forward motion puts the epipole
   inside the image, where rectification fails; vertical motion is not
   supported, as in :mod:`recon.rectify`) and that see at least ``min_overlap``
   of the reference image at that depth. On each side the acceptable frame
   whose baseline ratio is nearest ``target_baseline_ratio`` wins (ties: the
   nearer frame). The scene depth is the median depth of the sparse points the
   reference frame sees (SfM or a COLMAP model: a walk along a facade 3 m per
   photo and a car's camera 0.8 m per frame are judged alike, whatever the
   model's units), else ``scene_depth`` (metres). The first and last frames of a
   pass have one partner; a frame whose neighbours all fail (a stop, a turn) has
   none and gives no points.
2. **Rectification** from the relative pose (:func:`recon.rectify.rectify_views`,
   cv2.stereoRectify): per pair of frames, so the maps are not cached.
3. **Matching and fusion** exactly as the trinocular path does: every pair's
   disparity (:func:`recon.stereo.disparity`) is lifted to 3-D and splatted
   into the reference image (:func:`recon.trinocular.pair_depth_in_reference`),
   then cross-checked and fused (:func:`recon.trinocular.fuse_depths`) with the
   trinocular agreement tolerances.

Agreement (``min_agree``). With two partners both pairs must agree (2): the
two pairs see the scene from opposite sides of the reference, so a false match
rarely repeats, and this plays the part of the rig's three-pair check. With
one partner (first or last frame of a pass) nothing can cross-check it, so its
estimates are kept unchecked (1), guarded only by the matcher's left–right
check; their confidence is scaled by the share of the expected pairs present,
so that they weigh less where a voxel also has checked estimates.
``outer_pair`` (the default) adds the pair (before, after) itself (twice the
baseline, like the rig's (0, 2) pair), three pairs in all, of which 2 must
agree by default. On a 40 m street (416×736, frames 0.82 m apart, partners
±0.82 m) it took accuracy from 2.35 to 1.76 cm median (p90 9.5 → 6.5 cm) and
completeness within 20 cm from 94.8 to 95.6 %, for 1.4× the stereo time.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from core.errors import InputError

from .rectify import MAX_BASELINE_ANGLE_DEG, rectify_views
from .trinocular import FrameDepth, TrinocularConfig, fuse_depths, pair_depth_in_reference

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MotionStereoConfig:
    min_baseline_ratio: float = 0.0375  # shortest baseline to a partner, over the scene depth (shorter: imprecise)
    max_baseline_ratio: float = 0.75  # longest baseline over the scene depth (longer: occlusions, perspective)
    target_baseline_ratio: float = 0.1  # preferred baseline on each side over the scene depth (0.8 m at 8 m)
    max_view_angle_deg: float = 15.0  # largest angle between the two frames' optical axes, degrees
    max_baseline_angle_deg: float = MAX_BASELINE_ANGLE_DEG  # largest baseline angle from the x axis, degrees
    min_overlap: float = 0.5  # share of the reference image the partner must see at the scene depth
    scene_depth: float = 8.0  # scene depth of a frame with no sparse points, metres (a facade across a sidewalk)
    max_frame_gap: int = 8  # partners are searched this many frames before and after the reference
    outer_pair: bool = True  # also match the two partners with each other (three pairs, like the rig)
    min_agree: int | None = None  # estimates that must agree; None: 2 with two or more pairs, 1 with one

    def __post_init__(self):
        if not (0 < self.min_baseline_ratio <= self.max_baseline_ratio < np.inf):
            raise InputError(f"need 0 < min_baseline_ratio <= max_baseline_ratio, got {self.min_baseline_ratio}, "
                             f"{self.max_baseline_ratio}")
        if not (self.min_baseline_ratio <= self.target_baseline_ratio <= self.max_baseline_ratio):
            raise InputError(f"target_baseline_ratio {self.target_baseline_ratio} must lie in "
                             f"[{self.min_baseline_ratio}, {self.max_baseline_ratio}]")
        if not (0 <= self.max_view_angle_deg < 90):
            raise InputError(f"max_view_angle_deg must be in [0, 90), got {self.max_view_angle_deg}")
        if not (0 <= self.max_baseline_angle_deg <= MAX_BASELINE_ANGLE_DEG):
            raise InputError(f"max_baseline_angle_deg must be in [0, {MAX_BASELINE_ANGLE_DEG}] (rectification "
                             f"rejects steeper baselines), got {self.max_baseline_angle_deg}")
        if not (0 <= self.min_overlap <= 1):
            raise InputError(f"min_overlap must be in [0, 1], got {self.min_overlap}")
        if not (0 < self.scene_depth < np.inf):
            raise InputError(f"scene_depth must be a positive number of metres, got {self.scene_depth}")
        if self.max_frame_gap < 1:
            raise InputError(f"max_frame_gap must be at least 1, got {self.max_frame_gap}")
        if self.min_agree is not None and self.min_agree < 1:
            raise InputError(f"min_agree must be at least 1 or None, got {self.min_agree}")

    def agreement(self, num_pairs: int) -> int:
        """Estimates that must agree when a frame has ``num_pairs`` pairs (see the module doc)."""
        return self.min_agree if self.min_agree is not None else min(2, max(1, num_pairs))


def relative_pose(world_from_a: np.ndarray, world_from_b: np.ndarray) -> np.ndarray:
    """(4, 4) float64 b_from_a of two rigid poses (4, 4) float64.

    The translations are subtracted before rotating, so poses far from the
    origin (UTM coordinates) lose no precision.
    """
    Ra, ta = world_from_a[:3, :3], world_from_a[:3, 3]
    Rb, tb = world_from_b[:3, :3], world_from_b[:3, 3]
    out = np.eye(4)
    out[:3, :3] = Rb.T @ Ra
    out[:3, 3] = Rb.T @ (ta - tb)
    return out


def pair_geometry(b_from_a: np.ndarray) -> tuple[float, float, float]:
    """Baseline (metres), angle between the optical axes (degrees) and the baseline's
    angle from the x axis (degrees, in [0, 90], the larger of the two views' frames)
    of a relative pose b_from_a (4, 4) float64."""
    R, t = b_from_a[:3, :3], b_from_a[:3, 3]
    centre_b_in_a = -R.T @ t
    baseline = float(np.linalg.norm(t))
    # angles by atan2 of (sine, cosine): arccos loses precision near 0°
    view = float(np.degrees(np.arctan2(np.hypot(R[0, 2], R[1, 2]), R[2, 2])))  # a's z axis in b: R[:, 2]
    if baseline < 1e-12:
        return 0.0, view, 90.0
    angle = max(float(np.degrees(np.arctan2(np.hypot(c[1], c[2]), abs(c[0]))))
                for c in (centre_b_in_a, t))  # a's centre in b's frame is t
    return baseline, view, angle


def view_overlap(K_a: np.ndarray, K_b: np.ndarray, b_from_a: np.ndarray, size: tuple[int, int],
                 depth: float, grid: int = 16) -> float:
    """Share of view a's image that view b sees, for a fronto-parallel plane at ``depth``
    (metres) in front of a: a grid × grid lattice of a's pixels is lifted to that depth,
    projected into b (same size (w, h)) and counted inside and in front. K_a, K_b:
    (3, 3) float64; b_from_a: (4, 4) float64. Returns a float in [0, 1]."""
    w, h = size
    u, v = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    pa = np.linalg.solve(K_a, pix) * depth  # (3, m): z = depth
    pb = b_from_a[:3, :3] @ pa + b_from_a[:3, 3:4]
    z = pb[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = K_b @ pb
        ub, vb = q[0] / z, q[1] / z
        inside = (z > 1e-6) & (ub >= -0.5) & (ub <= w - 0.5) & (vb >= -0.5) & (vb <= h - 0.5)
    return float(inside.mean())


def _acceptable(world_from_cam: np.ndarray, K: np.ndarray, size: tuple[int, int], ref: int, j: int,
                depth: float, config: MotionStereoConfig) -> float | None:
    """Baseline over the scene ``depth`` of the pair (ref, j) when it passes every test of
    ``config``, else None."""
    T = relative_pose(world_from_cam[ref], world_from_cam[j])
    baseline, view, angle = pair_geometry(T)
    ratio = baseline / depth
    if not (config.min_baseline_ratio <= ratio <= config.max_baseline_ratio):
        return None
    if view > config.max_view_angle_deg or angle > config.max_baseline_angle_deg:
        return None
    if view_overlap(K[ref], K[j], T, size, depth) < config.min_overlap:
        return None
    return ratio


def select_partners(world_from_cam: np.ndarray, intrinsics: np.ndarray, size: tuple[int, int],
                    config: MotionStereoConfig = MotionStereoConfig(),
                    frames: Sequence[int] | None = None, depth: np.ndarray | None = None) -> np.ndarray:
    """Stereo partners of each frame of one camera's trajectory (see the module doc).

    world_from_cam: (n, 4, 4) float64 camera poses in capture order (non-finite =
    no pose: never a partner, never given one). intrinsics: (3, 3) or (n, 3, 3)
    float64. size: (w, h). frames: the reference frames to serve (default all).
    depth: (n,) float64 scene depth of each frame in the poses' units (the median
    depth of its sparse points); NaN or None: ``config.scene_depth``.
    Returns (n, 2) int64: the partner before and the partner after each frame,
    −1 where there is none (and for frames not asked for).
    """
    T = np.asarray(world_from_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"world_from_cam must be (n, 4, 4), got {T.shape}")
    n = len(T)
    K = np.asarray(intrinsics, dtype=np.float64)
    K = np.broadcast_to(K, (n, 3, 3)) if K.shape == (3, 3) else K
    if K.shape != (n, 3, 3):
        raise InputError(f"intrinsics must be (3, 3) or ({n}, 3, 3), got {np.shape(intrinsics)}")
    posed = np.all(np.isfinite(T.reshape(n, -1)), axis=1)
    scene = np.full(n, config.scene_depth) if depth is None else np.asarray(depth, dtype=np.float64)
    if scene.shape != (n,):
        raise InputError(f"depth must be ({n},), got {scene.shape}")
    scene = np.where(np.isfinite(scene) & (scene > 0), scene, config.scene_depth)
    out = np.full((n, 2), -1, dtype=np.int64)
    for i in (range(n) if frames is None else frames):
        if not posed[i]:
            continue
        for side, step in ((0, -1), (1, 1)):
            best, best_key = -1, None
            for k in range(1, config.max_frame_gap + 1):
                j = i + step * k
                if not (0 <= j < n and posed[j]):
                    continue
                r = _acceptable(T, K, size, i, j, scene[i], config)
                if r is None:
                    continue
                key = (round(abs(r - config.target_baseline_ratio), 9), k)  # ties go to the nearer frame
                if best_key is None or key < best_key:
                    best, best_key = j, key
            out[i, side] = best
    return out


def motion_depth(images: Sequence[np.ndarray], intrinsics: np.ndarray, world_from_cam: np.ndarray,
                 config: MotionStereoConfig = MotionStereoConfig(),
                 trinocular: TrinocularConfig = TrinocularConfig()) -> FrameDepth:
    """Depth of a reference frame from its partner frames (one camera, see the module doc).

    images: (h, w, 3) uint8 RGB, the reference first, then 0–2 partners.
    intrinsics: (c, 3, 3) float64 per image; world_from_cam: (c, 4, 4) float64 per image.
    trinocular: the matcher (``stereo``) and agreement tolerances; its min_agree is
    replaced by ``config.agreement``. Returns a :class:`recon.trinocular.FrameDepth`
    in the reference image; its pair_depth keys index ``images``. A frame without
    partners (or whose pairs all fail to rectify) has an all-NaN depth.
    """
    c = len(images)
    K = np.asarray(intrinsics, dtype=np.float64)
    W = np.asarray(world_from_cam, dtype=np.float64)
    if K.shape != (c, 3, 3) or W.shape != (c, 4, 4):
        raise InputError(f"{c} images need intrinsics ({c}, 3, 3) and world_from_cam ({c}, 4, 4), "
                         f"got {K.shape} and {W.shape}")
    h, w = images[0].shape[:2]
    for i, img in enumerate(images):
        if img.shape[:2] != (h, w):
            raise InputError(f"image {i} is {img.shape[1]}x{img.shape[0]}, the reference {w}x{h}")
    size = (w, h)
    cam_from_ref = np.stack([relative_pose(W[0], W[i]) for i in range(c)])
    wanted = [(0, i) for i in range(1, c)]
    if config.outer_pair and c >= 3:
        wanted.append((1, 2))
    pairs = {}
    for a, b in wanted:
        try:
            pairs.update(rectify_views(K, cam_from_ref, size, ((a, b),)))
        except ValueError as e:  # a partner chosen by other means (or a degenerate pose): skip the pair
            logger.warning("motion stereo: pair %d-%d skipped: %s", a, b, e)
    if not pairs:
        nan = np.full((h, w), np.nan, np.float32)
        return FrameDepth(depth=nan, confidence=np.zeros((h, w), np.float32),
                          num_agree=np.zeros((h, w), np.uint8), pair_depth={})
    keys = list(pairs)
    eye = np.eye(4)
    per_pair = {k: pair_depth_in_reference(images, pairs[k], K[0], eye, size, trinocular.stereo) for k in keys}
    fuse_conf = dataclasses.replace(trinocular, min_agree=config.agreement(len(keys)))
    depth, conf, num = fuse_depths(np.stack([per_pair[k] for k in keys]),
                                   [pairs[k].focal_baseline for k in keys], fuse_conf)
    expected = 3 if config.outer_pair else 2
    if len(keys) < expected:  # an end of a pass: unchecked estimates weigh less
        conf = conf * np.float32(len(keys) / expected)
    logger.debug("motion depth: %.1f%% fused, pairs %s", 100.0 * np.isfinite(depth).mean(),
                 {k: round(float(np.isfinite(v).mean()), 3) for k, v in per_pair.items()})
    return FrameDepth(depth=depth, confidence=conf, num_agree=num, pair_depth=per_pair)
