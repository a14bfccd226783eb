"""Trajectory geometry: alignment of one trajectory to another, its errors, and the world's up.

Poses are ``world_from_rig`` (n, 4, 4) float64 (rig frame: x forward, y left, z up; see
:mod:`capture.rig`), NaN matrices for frames without a pose (:mod:`capture.poses`).

* :func:`align_trajectory` (Umeyama, SE(3) or Sim(3)) and :func:`align_components` (each
  SfM component placed on reference poses, e.g. GPS);
* :func:`trajectory_rmse` (position and rotation errors after alignment);
* :func:`rig_baseline_ratio` (reconstructed over calibrated camera spacing: 1 when metric);
* :func:`up_direction` and :func:`level_from_world` (a z-up world from cameras held level).

Pure numpy: no COLMAP here.
"""

from __future__ import annotations

import numpy as np

from capture.poses import posed, unknown_poses
from core.errors import InputError
from core.rigid import rigid_inverse

__all__ = [
    "align_components", "align_trajectory", "level_from_world", "rig_baseline_ratio", "trajectory_rmse",
    "up_direction",
]

COLLINEAR_RATIO = 1e-4  # align_trajectory: positions are one line when singular values 2nd/1st fall below this


#: up_direction: the trajectory's main direction counts as level (its component along the
#: estimated up is removed) when it lies within this many degrees of horizontal.
LEVEL_TRAVEL_DEG = 30.0


def up_direction(world_from_cam: np.ndarray, positions: np.ndarray | None = None) -> np.ndarray:
    """(3,) float64 unit vector: the world's up, estimated from cameras held roughly level.

    world_from_cam: (m, 4, 4) float64 camera poses (OpenCV axes; NaN poses are ignored).
    positions: optional (k, 3) float64 rig positions along the capture.
    Up is minus the mean of the cameras' image-down (y) axes. A camera pitched up or down
    tilts that estimate about its own x axis; when the positions run along one main
    direction within LEVEL_TRAVEL_DEG of that horizontal (a street is nearly level), the
    estimate is made perpendicular to it, which removes the pitch of forward-looking
    cameras (sideways-looking ones pitch about the travel direction and cannot be corrected).
    """
    T = np.asarray(world_from_cam, dtype=np.float64)
    T = T[posed(T)]
    if len(T) == 0:
        raise InputError("no camera pose to estimate the up direction from")
    up = -T[:, :3, 1].mean(axis=0)
    if np.linalg.norm(up) < 1e-6:
        raise InputError("the cameras' down axes cancel out: no up direction")
    up /= np.linalg.norm(up)
    if positions is not None:
        P = np.asarray(positions, dtype=np.float64)
        P = P[np.isfinite(P).all(axis=1)]
        if len(P) >= 2:
            _, sv, Vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
            d = Vt[0]
            if sv[0] > 1e-9 and abs(d @ up) < np.sin(np.radians(LEVEL_TRAVEL_DEG)):
                up = up - (d @ up) * d
                up /= np.linalg.norm(up)
    return up


def level_from_world(up: np.ndarray, heading: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4, 4) float64 rigid transform to a z-up world: ``up`` (3,) becomes +z, the horizontal
    part of ``heading`` (3,) becomes +x (any horizontal direction when it is vertical) and
    ``origin`` (3,) the origin. All in the old world's coordinates."""
    z = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    x = np.asarray(heading, dtype=np.float64) - (np.asarray(heading) @ z) * z
    if np.linalg.norm(x) < 1e-6:  # heading straight up or down: any horizontal axis will do
        x = np.eye(3)[np.argmin(np.abs(z))]
        x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: the new axes in old coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.asarray(origin, dtype=np.float64)
    return T


def rig_baseline_ratio(world_from_cam: np.ndarray, cam_from_rig: np.ndarray) -> float:
    """Median over frames of (reconstructed / calibrated) distance between camera centres.

    world_from_cam: (n, c, 4, 4) float64 per frame and camera, NaN where unknown.
    cam_from_rig: (c, 4, 4) float64 calibration.
    Uses every frame with at least two cameras and every camera pair whose
    calibrated distance exceeds 1 mm. Returns NaN when no frame qualifies.
    A metric reconstruction gives 1.
    """
    centres = world_from_cam[:, :, :3, 3]  # (n, c, 3)
    calib = rigid_inverse(cam_from_rig)[:, :3, 3]  # (c, 3) camera centres in the rig
    c = cam_from_rig.shape[0]
    ratios = []
    for i in range(c):
        for j in range(i + 1, c):
            d_cal = np.linalg.norm(calib[i] - calib[j])
            if d_cal < 1e-3:
                continue
            d = np.linalg.norm(centres[:, i] - centres[:, j], axis=1)
            ratios.append(d[np.isfinite(d)] / d_cal)
    ratios = np.concatenate(ratios) if ratios else np.empty(0)
    return float(np.median(ratios)) if ratios.size else float("nan")


def _kabsch(H: np.ndarray) -> np.ndarray:
    """Rotation R (3, 3) maximising trace(R @ H) for H (3, 3) = Σ x_est ⊗ x_ref (proper, det +1)."""
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    return Vt.T @ D @ U.T


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about the unit vector ``axis`` (3,)."""
    K = _skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking unit vector u (3,) to unit vector v (3,)."""
    w = np.cross(u, v)
    s, c = np.linalg.norm(w), float(u @ v)
    if s > 1e-15:
        return _axis_angle(w / s, np.arctan2(s, c))
    if c > 0:
        return np.eye(3)
    a = np.cross(u, np.eye(3)[np.argmin(np.abs(u))])  # any axis perpendicular to u: half a turn
    a /= np.linalg.norm(a)
    return 2.0 * np.outer(a, a) - np.eye(3)


def _similarity(est: np.ndarray, ref: np.ndarray, with_scale: bool) -> tuple[np.ndarray, float, np.ndarray]:
    """R (3, 3), s, t (3,) minimising Σ|ref_p − (s R est_p + t)|² over valid poses (m, 4, 4) each.

    Umeyama on positions. Where positions leave the rotation free — all on one
    line (a straight drive: the roll about the line) or all at one point —
    the free part maximises the agreement of orientations, Σ trace(R_ref^T R R_est).
    """
    pe, pr = est[:, :3, 3], ref[:, :3, 3]
    me, mr = pe.mean(axis=0), pr.mean(axis=0)
    xe, xr = pe - me, pr - mr
    H = xe.T @ xr  # (3, 3): trace(R @ H) = Σ xr · R xe
    A = np.einsum("mij,mkj->ik", est[:, :3, :3], ref[:, :3, :3])  # trace(R @ A) = Σ trace(R_ref^T R R_est)
    U, sv, Vt = np.linalg.svd(H)
    scale_h = max(np.sqrt((xe ** 2).sum() * (xr ** 2).sum()), 1e-300)
    if sv[0] <= 1e-12 * scale_h:  # one point: orientations alone
        R = _kabsch(A)
    elif sv[1] <= COLLINEAR_RATIO * sv[0]:  # one line: align it, then roll about it by orientations
        d = Vt[0]
        R0 = _rotation_between(U[:, 0], d)
        B = R0 @ A
        R = _axis_angle(d, np.arctan2(np.trace(_skew(d) @ B), np.trace(B) - d @ B @ d)) @ R0
    else:
        R = _kabsch(H)
    s = 1.0
    if with_scale:
        s = float(np.einsum("mi,mi->", xr, xe @ R.T) / (xe ** 2).sum()) if (xe ** 2).sum() > 0 else float("nan")
    return R, s, mr - s * R @ me


def align_trajectory(estimated: np.ndarray, reference: np.ndarray,
                     with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Align an estimated trajectory to a reference (Umeyama on rig positions).

    estimated, reference: (n, 4, 4) float64 world_from_rig of the same frames;
    frames with any NaN in either are ignored. Rotation and translation (and
    with ``with_scale`` a scale) minimise the squared position error
    (Umeyama); orientations decide only what positions leave free: the roll
    about the line when all positions are on one line (a straight drive;
    perpendicular spread below about 1 % of the extent, see
    ``COLLINEAR_RATIO``), the whole rotation for a single position. Needs ≥ 1
    valid frame (≥ 2 for a scale).

    Returns aligned (n, 4, 4) float64 = the estimated poses moved into the
    reference frame (rotation R @ R_est, position s R p + t; NaN frames stay
    NaN), transform (4, 4) float64 reference_from_estimated with ``s R`` in
    its upper-left block, and the scale s (1.0 without ``with_scale``).
    """
    est = np.asarray(estimated, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise InputError(f"estimated {est.shape} and reference {ref.shape} must both be (n, 4, 4)")
    ok = posed(est) & posed(ref)
    if not ok.any():
        raise InputError("no frame has a pose in both trajectories")
    if with_scale and ok.sum() < 2:
        raise InputError("a scale needs at least two frames with poses in both trajectories")
    R, s, t = _similarity(est[ok], ref[ok], with_scale)
    transform = np.eye(4)
    transform[:3, :3] = s * R
    transform[:3, 3] = t
    aligned = unknown_poses(len(est))
    aligned[ok, :3, :3] = R @ est[ok, :3, :3]
    aligned[ok, :3, 3] = s * est[ok, :3, 3] @ R.T + t
    aligned[ok, 3] = [0.0, 0.0, 0.0, 1.0]
    return aligned, transform, s


def align_components(world_from_rig: np.ndarray, component: np.ndarray, reference: np.ndarray,
                     with_scale: bool = False) -> np.ndarray:
    """Place each component of an SfM trajectory onto reference poses (e.g. GPS/IMU).

    world_from_rig: (n, 4, 4) float64, each component in its own frame (NaN = no pose).
    component: (n,) int, component per frame (negative = none), e.g. ``SfmResult.component``.
    reference: (n, 4, 4) float64 poses in the target frame; NaN frames are not used.
    Each component is moved by the SE(3) (Sim(3) with ``with_scale``) that
    best fits its frames to the reference (:func:`align_trajectory`); a
    component with no reference frame stays NaN.
    Returns (n, 4, 4) float64 in the reference frame.
    """
    est = np.asarray(world_from_rig, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    comp = np.asarray(component)
    out = unknown_poses(len(est))
    for label in np.unique(comp[comp >= 0]):
        sel = (comp == label) & posed(est)
        usable = sel & posed(ref)
        if not usable.any() or (with_scale and usable.sum() < 2):
            continue
        # fit on frames with both poses, then move every frame of the component
        _, T, s = align_trajectory(np.where(usable[:, None, None], est, np.nan),
                                   np.where(usable[:, None, None], ref, np.nan), with_scale)
        R = T[:3, :3] / s
        out[sel, :3, :3] = R @ est[sel, :3, :3]
        out[sel, :3, 3] = est[sel, :3, 3] @ T[:3, :3].T + T[:3, 3]
        out[sel, 3] = [0.0, 0.0, 0.0, 1.0]
    return out


def _rotation_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(m,) float64 angle in degrees of A_i^T B_i for rotations A, B (m, 3, 3)."""
    tr = np.einsum("mij,mij->m", A, B)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def trajectory_rmse(estimated: np.ndarray, reference: np.ndarray, with_scale: bool = False,
                    groups: np.ndarray | None = None) -> dict:
    """Trajectory errors after aligning the estimate to the reference.

    estimated, reference: (n, 4, 4) float64 world_from_rig; NaN = no pose.
    with_scale: align with Sim(3) for the main errors (default SE(3): a metric
        estimate is judged with its own scale).
    groups: optional (n,) int, frames aligned separately per group value
        (e.g. ``SfmResult.component``); negative = no pose.

    Returns a dict: ``frames``, ``valid`` (frames with both poses),
    ``missing`` (frames of the reference with no estimate); position errors in
    metres ``rmse_m``, ``mean_m``, ``median_m``, ``max_m``; rotation errors
    in degrees ``rot_rmse_deg``, ``rot_max_deg``; ``scale`` — the Sim(3)
    scale (reference units per estimated unit; of the largest group) —,
    ``scale_error`` = scale − 1, ``sim3_rmse_m`` (RMSE after Sim(3));
    ``path_length_m`` of the reference over valid frames; per frame
    ``position_error_m`` and ``rotation_error_deg`` (n,) float64, NaN where
    a pose is missing. Statistics are NaN when no frame is valid.
    """
    est = np.asarray(estimated, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise InputError(f"estimated {est.shape} and reference {ref.shape} must both be (n, 4, 4)")
    n = len(est)
    g = np.zeros(n, dtype=np.int64) if groups is None else np.asarray(groups).astype(np.int64)
    if g.shape != (n,):
        raise InputError(f"groups must have shape ({n},), got {g.shape}")
    ok = posed(est) & posed(ref) & (g >= 0)
    pos_err = np.full(n, np.nan)
    rot_err = np.full(n, np.nan)
    sim3_err = np.full(n, np.nan)
    best_scale, best_size = float("nan"), 0
    for label in np.unique(g[ok]):
        sel = ok & (g == label)
        e, r = np.where(sel[:, None, None], est, np.nan), np.where(sel[:, None, None], ref, np.nan)
        aligned, _, _ = align_trajectory(e, r, with_scale=with_scale)
        pos_err[sel] = np.linalg.norm(aligned[sel, :3, 3] - ref[sel, :3, 3], axis=1)
        rot_err[sel] = _rotation_deg(aligned[sel, :3, :3], ref[sel, :3, :3])
        if sel.sum() >= 2:
            aligned_s, _, s = align_trajectory(e, r, with_scale=True)
            sim3_err[sel] = np.linalg.norm(aligned_s[sel, :3, 3] - ref[sel, :3, 3], axis=1)
            if sel.sum() > best_size:
                best_scale, best_size = s, int(sel.sum())
    v = pos_err[ok]
    steps = np.linalg.norm(np.diff(ref[ok, :3, 3], axis=0), axis=1) if ok.sum() > 1 else np.empty(0)

    def stat(fn, a):
        return float(fn(a)) if a.size else float("nan")

    return {
        "frames": n,
        "valid": int(ok.sum()),
        "missing": int((posed(ref) & ~ok).sum()),
        "rmse_m": stat(lambda a: np.sqrt(np.mean(a ** 2)), v),
        "mean_m": stat(np.mean, v),
        "median_m": stat(np.median, v),
        "max_m": stat(np.max, v),
        "rot_rmse_deg": stat(lambda a: np.sqrt(np.mean(a ** 2)), rot_err[ok]),
        "rot_max_deg": stat(np.max, rot_err[ok]),
        "scale": best_scale,
        "scale_error": best_scale - 1.0,
        "sim3_rmse_m": stat(lambda a: np.sqrt(np.mean(a ** 2)), sim3_err[np.isfinite(sim3_err)]),
        "path_length_m": float(steps.sum()),
        "position_error_m": pos_err,
        "rotation_error_deg": rot_err,
    }
