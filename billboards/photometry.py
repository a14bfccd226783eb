"""Photometric calibration: per-image exposure × white-balance gains from overlaps.

Real captures change exposure and white balance from image to image. A billboard's
directions are sampled from different images, so an uncorrected exposure change
becomes view dependence that the eigen-textures spend rank on. This module
estimates one multiplicative gain per image and colour channel, g_ic, and the
build divides each image by its gains before sampling textures
(:attr:`billboards.views.Views.gains`).

Model, in log space, per channel c::

    log I_ijc ≈ log g_ic + log ρ_jc          (image i, tie point j, albedo ρ)

Tie points are a seeded subsample of the fused cloud. Each is projected into every
image whose frustum holds it and that sees it unoccluded (its depth against the
cloud splatted into that image, :func:`billboards.voxels.zbuffer`); its colour is
read bilinearly from the slightly blurred image (sub-pixel misregistration between
views matters less). Samples near saturation or black, in any channel, are left out,
so are tie points seen in fewer than ``min_observations`` images and images with
fewer than ``min_image_observations`` samples.

The least-squares problem is solved with iteratively reweighted least squares
(Huber weights on each observation's RMS log residual over the channels, then a
redescending Cauchy loss; one weight for all channels so that moving objects and
specular pixels are discounted together, and a grey capture keeps equal channels). The gauge: within each connected
component of the image–tie point graph (the two sides of a street seen from two
passes share no point), the mean log gain is 0. Images with no usable observation
keep gain 1 and are reported.

Two solvers: :func:`solve_reference` (dense ``lstsq`` over all unknowns; small
problems only) and :func:`solve_fast` (the tie-point unknowns eliminated, the reduced
image system solved matrix-free by preconditioned conjugate gradients: memory and
time linear in the observations). Tests check they agree.
"""

from __future__ import annotations

import logging
import math
import time
from concurrent.futures import Executor
from dataclasses import dataclass, replace

import cv2
import numpy as np

from core.arrays import row_norms, unique_rows
from core.errors import InputError
from core.tasks import executor_workers, ordered_results

from .voxels import transform_points, voxel_points, zbuffer

logger = logging.getLogger(__name__)

SOLVERS = ("fast", "reference")
LOSSES = ("huber", "cauchy")
HUBER_ROUNDS = 2  # reweighting rounds with Huber weights before a Cauchy loss takes over
REFERENCE_MAX_ENTRIES = 50_000_000  # the dense reference solver's design matrix at most (400 MB of float64)


@dataclass(frozen=True)
class PhotometryConfig:
    enabled: bool = True              # False: images are used as captured (every gain 1)
    samples: int = 20000              # cloud points drawn (seeded) as tie points
    min_observations: int = 2         # images a tie point must be usable in
    min_image_observations: int = 20  # an image with fewer usable samples keeps gain 1 (reported)
    robust_threshold: float = 0.05    # scale δ of the robust loss on an observation's RMS log residual (≈ 5 %)
    loss: str = "cauchy"              # "huber", or "cauchy" (redescending: moving objects and reflections lose
                                      # all pull; on the street 4× less gain error than Huber)
    iterations: int = 10              # reweighting rounds at most (stops earlier when the gains settle)
    dark: int = 5                     # samples with a channel ≤ this (8-bit) are left out: noise and black clip
    saturated: int = 250              # samples with a channel ≥ this are left out: clipped highlights
    blur_sigma: float = 1.0           # Gaussian blur (pixels) before sampling; 0: none
    max_distance: float = 60.0        # tie points farther than this from a camera (m) are not sampled in it
    zbuffer_scale: int = 2            # occlusion z-buffer pixel = this many image pixels per side
    abs_tolerance: float = 0.05       # depth slack of the visibility test (m) ...
    rel_tolerance: float = 0.01       # ... plus this fraction of the depth
    cell: float = 2.0                 # grid cell (m) grouping the cloud for per-image frustum culling
    zbuffer_points: int = 4_000_000   # the visibility z-buffers splat at most this many cloud points (every n-th):
                                      # splatting is the cost, and a 2 cm cloud is denser than the z-buffer
    solver: str = "fast"              # "fast" (reduced system, PCG) or "reference" (dense lstsq, small problems)
    seed: int = 0                     # tie-point subsample

    def __post_init__(self):
        if self.samples < 1 or self.iterations < 1 or self.zbuffer_scale < 1 or self.zbuffer_points < 1:
            raise InputError("PhotometryConfig: samples, iterations, zbuffer_scale and zbuffer_points must be ≥ 1")
        if self.min_observations < 2:
            raise InputError(f"PhotometryConfig.min_observations must be ≥ 2 (a point seen once ties nothing), "
                             f"got {self.min_observations}")
        if self.min_image_observations < 1:
            raise InputError(f"PhotometryConfig.min_image_observations must be ≥ 1, got {self.min_image_observations}")
        if not (math.isfinite(self.robust_threshold) and self.robust_threshold > 0):
            raise InputError(f"PhotometryConfig.robust_threshold must be finite and > 0, got {self.robust_threshold}")
        if not 0 <= self.dark < self.saturated <= 256:
            raise InputError(f"PhotometryConfig: need 0 ≤ dark < saturated ≤ 256, got {self.dark}, {self.saturated}")
        if self.blur_sigma < 0 or self.max_distance <= 0 or self.cell <= 0:
            raise InputError("PhotometryConfig: blur_sigma must be ≥ 0, max_distance and cell > 0")
        if self.abs_tolerance < 0 or self.rel_tolerance < 0:
            raise InputError("PhotometryConfig: depth tolerances must be ≥ 0")
        if self.loss not in LOSSES:
            raise InputError(f"PhotometryConfig.loss must be one of {LOSSES}, got {self.loss!r}")
        if self.solver not in SOLVERS:
            raise InputError(f"PhotometryConfig.solver must be one of {SOLVERS}, got {self.solver!r}")


@dataclass(frozen=True, eq=False)
class Observations:
    """Tie-point samples: image (n,) int64 view index; point (n,) int64 tie point index;
    rgb (n, 3) float64 colour in 8-bit units (bilinear, blurred); num_images, num_points."""

    image: np.ndarray
    point: np.ndarray
    rgb: np.ndarray
    num_images: int
    num_points: int

    def __len__(self) -> int:
        return len(self.image)


@dataclass(frozen=True, eq=False)
class Solution:
    """log_gains (V, 3) float64 (0 where not estimated); estimated (V,) bool; component (V,)
    int64 connected component of each estimated image (−1: none); weights (n,) float64 final
    IRLS weight of each observation given to the solver (0: pruned); iterations; residual_rms
    (log units, over the kept observations, weighted)."""

    log_gains: np.ndarray
    estimated: np.ndarray
    component: np.ndarray
    weights: np.ndarray
    iterations: int
    residual_rms: float
    grayscale: bool

    @property
    def gains(self) -> np.ndarray:
        """(V, 3) float64 multiplicative gains (1 where not estimated)."""
        return np.exp(self.log_gains)

    @property
    def num_components(self) -> int:
        return int(self.component.max() + 1) if len(self.component) and self.component.max() >= 0 else 0


@dataclass(frozen=True, eq=False)
class PhotometryResult:
    """gains (V, 3) float64 per view and RGB channel (divide an image by its gains);
    the solution and observations it came from; seconds spent."""

    gains: np.ndarray
    solution: Solution | None
    observations: int
    tie_points: int
    seconds: float

    def report(self) -> dict:
        """A JSON-ready summary for build_report.json."""
        g = self.gains
        est = self.solution.estimated if self.solution is not None else np.zeros(len(g), bool)
        summary = {}
        for c, name in enumerate("rgb"):
            v = g[est, c] if est.any() else g[:, c]
            summary[name] = {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max())} if len(v) \
                else None
        sol = self.solution
        return {"enabled": True, "seconds": self.seconds, "observations": self.observations,
                "tie_points": self.tie_points, "images": len(g), "estimated_images": int(est.sum()),
                "not_estimated": np.flatnonzero(~est).tolist(),
                "components": sol.num_components if sol else 0,
                "iterations": sol.iterations if sol else 0,
                "residual_rms_log": sol.residual_rms if sol else None,
                "grayscale": bool(sol.grayscale) if sol else None,
                "gain_summary": summary, "gains": np.round(g, 5).tolist()}


# --------------------------------------------------------------------------- applying

def apply_gains(image: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Divide an image by its gains. image (h, w, 3) uint8, gain (3,) float → (h, w, 3) uint8
    (rounded, clipped to [0, 255]); unit gains return the image itself."""
    gain = np.asarray(gain, dtype=np.float64)
    if np.all(gain == 1.0):
        return image
    scaled = image.astype(np.float32) * (1.0 / gain).astype(np.float32)
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- observations

def _cloud_cells(points: np.ndarray, cell: float):
    """The cloud grouped in a coarse grid (:class:`~billboards.voxels.VoxelPoints`), for frustum culling."""
    origin = points.min(axis=0)
    key = np.floor((points - origin) / cell).astype(np.int64)
    cells, leaf = unique_rows(key, return_inverse=True)
    centres = origin + (cells + 0.5) * cell
    return voxel_points(points, leaf.ravel(), centres, origin, cell)


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """image (h, w, c) float at pixel positions u, v (n,) float64 (pixel centres at integers,
    inside [0, w−1] × [0, h−1]) → (n, c) float64."""
    h, w = image.shape[:2]
    x0 = np.clip(np.floor(u).astype(np.int64), 0, w - 2 if w > 1 else 0)
    y0 = np.clip(np.floor(v).astype(np.int64), 0, h - 2 if h > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (u - x0)[:, None], (v - y0)[:, None]
    img = image.astype(np.float64, copy=False)
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)


def collect_observations(views, points: np.ndarray, config: PhotometryConfig = PhotometryConfig(),
                         progress: bool | None = None, executor: Executor | None = None) -> Observations:
    """Sample tie points of the cloud in every view that sees them.

    views: :class:`~billboards.views.Views` (read as captured, whatever their gains); points (N, 3)
    float64 world. The tie points are ``config.samples`` points drawn without replacement
    (seeded). A sample is kept when the point lies in front of the camera, within
    ``max_distance``, inside the image (one pixel from its border), is not hidden behind
    the splatted cloud, and no channel of the pixels around it is dark or saturated.
    executor: the views are read in runs of consecutive views, in parallel (None: here); the
    observations are the same either way.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0 or len(views) == 0:
        return Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), len(views), 0)
    rng = np.random.default_rng(config.seed)
    ties = points[np.sort(rng.choice(len(points), min(config.samples, len(points)), replace=False))]
    stride = -(-len(points) // config.zbuffer_points)
    cells = _cloud_cells(points[::stride], config.cell)
    if getattr(views, "gains", None) is not None:
        views = replace(views, gains=None)  # the gains are estimated on the images as captured
    # a run per worker: each task carries the cloud's cells (tens of MB) to its worker
    runs = np.array_split(np.arange(len(views)), max(1, min(len(views), executor_workers(executor))))
    tasks = [(views, run, ties, cells, config) for run in runs if len(run)]
    found = [o for part in ordered_results(_observe_views, tasks, executor, desc="photometry", progress=progress)
             for o in part]
    if not found:
        return Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), len(views), len(ties))
    return Observations(np.concatenate([np.full(len(i), v, np.int64) for v, i, _ in found]),
                        np.concatenate([i for _, i, _ in found]), np.concatenate([c for _, _, c in found]),
                        len(views), len(ties))


def _observe_views(task) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """:func:`collect_observations` of a run of views: (view, tie point ids (k,) int64, colours
    (k, 3) float64) of each view that keeps any."""
    views, run, ties, cells, config = task
    out = []
    for i in run:
        i = int(i)
        K, pose, size = views.K[i], views.world_from_cam[i], views.sizes[i]
        w, h = (int(s) for s in size)
        R, C = pose[:3, :3], pose[:3, 3]
        cam = transform_points(ties - C, R.T)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * cam[:, 0] / z + K[0, 2]
            v = K[1, 1] * cam[:, 1] / z + K[1, 2]
        ok = (z > 0.1) & (row_norms(cam) < config.max_distance)
        ok &= (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
        sel = np.flatnonzero(ok)
        if len(sel) == 0:
            continue
        # Seen: the cloud's surface at the point's z-buffer pixel is the point's own (a hole in the
        # z-buffer could hide an occluder), and nothing around it lies in front (depth edges blend colours).
        pts = cells.in_view(K, pose, size, config.max_distance)
        filled, nearest = zbuffer(pts, cells.origin, K, pose, size, config.zbuffer_scale)
        s = config.zbuffer_scale
        zr = np.minimum(((v[sel] + 0.5) / s).astype(np.int64), filled.shape[0] - 1)
        zc = np.minimum(((u[sel] + 0.5) / s).astype(np.int64), filled.shape[1] - 1)
        zs = z[sel]
        tol = config.abs_tolerance + config.rel_tolerance * zs
        sel = sel[(np.abs(filled[zr, zc] - zs) <= tol) & (nearest[zr, zc] >= zs - tol)]
        if len(sel) == 0:
            continue
        image = views.image(i)
        # Dark or saturated in any channel of the 3×3 pixels around: left out (clipping breaks the model).
        kernel = np.ones((3, 3), np.uint8)
        hi = cv2.dilate(image.max(axis=2), kernel)
        lo = cv2.erode(image.min(axis=2), kernel)
        iu, iv = np.rint(u[sel]).astype(np.int64), np.rint(v[sel]).astype(np.int64)
        sel = sel[(hi[iv, iu] < config.saturated) & (lo[iv, iu] > config.dark)]
        if len(sel) == 0:
            continue
        img = image.astype(np.float32)
        if config.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), config.blur_sigma, borderType=cv2.BORDER_REPLICATE)
        out.append((i, sel.astype(np.int64), _bilinear(img, u[sel], v[sel])))
    return out


# --------------------------------------------------------------------------- solving

def prune(image: np.ndarray, point: np.ndarray, num_images: int, num_points: int, min_observations: int,
          min_image_observations: int) -> np.ndarray:
    """(n,) bool observations kept: those of points seen in ≥ ``min_observations`` kept images
    and of images with ≥ ``min_image_observations`` kept samples (repeated until stable)."""
    keep = np.ones(len(image), bool)
    while True:
        per_point = np.bincount(point[keep], minlength=num_points)
        per_image = np.bincount(image[keep], minlength=num_images)
        new = keep & (per_point[point] >= min_observations) & (per_image[image] >= min_image_observations)
        if new.sum() == keep.sum():
            return new
        keep = new


def components(image: np.ndarray, point: np.ndarray, num_images: int, num_points: int) -> np.ndarray:
    """(num_images,) int64 connected component of each image in the bipartite image–point
    graph of the observations (numbered 0… by smallest image; −1: image without observation)."""
    label = np.arange(num_images, dtype=np.int64)
    while True:
        at_point = np.full(num_points, num_images, np.int64)
        np.minimum.at(at_point, point, label[image])
        new = label.copy()
        np.minimum.at(new, image, at_point[point])
        new = new[new]  # pointer jumping: labels point at smaller labels
        if np.array_equal(new, label):
            break
        label = new
    seen = np.bincount(image, minlength=num_images) > 0
    out = np.full(num_images, -1, np.int64)
    _, out[seen] = np.unique(label[seen], return_inverse=True)
    return out


def _gauge(a: np.ndarray, comp: np.ndarray, ncomp: int) -> np.ndarray:
    """Subtract each component's mean from ``a`` (V, k); entries with comp −1 are left at 0."""
    on = comp >= 0
    count = np.bincount(comp[on], minlength=ncomp).astype(np.float64)
    out = np.zeros_like(a)
    for c in range(a.shape[1]):
        mean = np.bincount(comp[on], a[on, c], minlength=ncomp) / np.maximum(count, 1)
        out[on, c] = a[on, c] - mean[comp[on]]
    return out


def solve_reference(image: np.ndarray, point: np.ndarray, y: np.ndarray, w: np.ndarray, num_images: int,
                    num_points: int, comp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares min Σ w (y − a_i − b_j)² as one dense ``lstsq``.

    image, point (n,) int64; y (n, k) float64; w (n,) float64 > 0; comp (V,) int64 component
    per image (−1: no observation). The gauge (mean a = 0 per component) enters as one extra
    row per component: it only fixes the null space, so the fit is the same.
    Returns a (V, k), b (P, k) float64 (0 for unknowns without observation). Memory
    n·(V + P) doubles: tests and small problems only.
    """
    n, k = y.shape
    if n * (num_images + num_points) > REFERENCE_MAX_ENTRIES:
        raise InputError(f"{n} observations of {num_images} images and {num_points} points are too many for the "
                         f"dense reference solver (use solver='fast')")
    ncomp = int(comp.max() + 1) if len(comp) and comp.max() >= 0 else 0
    A = np.zeros((n + ncomp, num_images + num_points))
    sw = np.sqrt(w)
    rows = np.arange(n)
    A[rows, image] = sw
    A[rows, num_images + point] = sw
    on = np.flatnonzero(comp >= 0)
    A[n + comp[on], on] = 1.0
    rhs = np.zeros((n + ncomp, k))
    rhs[:n] = sw[:, None] * y
    x = np.linalg.lstsq(A, rhs, rcond=None)[0]
    # Unknowns without observations get the minimum-norm 0 from lstsq already.
    return x[:num_images], x[num_images:]


def solve_fast(image: np.ndarray, point: np.ndarray, y: np.ndarray, w: np.ndarray, num_images: int,
               num_points: int, comp: np.ndarray, x0: np.ndarray | None = None, rtol: float = 1e-12,
               max_iter: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The same solution as :func:`solve_reference`, with the tie points eliminated.

    Normal equations [D_a B; Bᵀ D_b] [a; b] = [r_a; r_b] with D_a, D_b the weight sums per
    image and point and B_ij the weight of observation (i, j). Eliminating b gives the
    image system S a = r_a − B D_b⁻¹ r_b, S = D_a − B D_b⁻¹ Bᵀ (a weighted graph Laplacian:
    singular along each component's constant vector, which the gauge removes). It is solved
    by conjugate gradients, Jacobi-preconditioned, projected onto the gauge, with every
    product by B or Bᵀ a ``bincount`` over the observations; then b = D_b⁻¹ (r_b − Bᵀ a).
    x0: (V, k) start (warm start across reweighting rounds). Returns a (V, k), b (P, k).
    """
    n, k = y.shape
    ncomp = int(comp.max() + 1) if len(comp) and comp.max() >= 0 else 0
    Da = np.bincount(image, w, minlength=num_images)
    Db = np.bincount(point, w, minlength=num_points)
    inv_Db = np.where(Db > 0, 1.0 / np.where(Db > 0, Db, 1.0), 0.0)

    def B(x):        # (P, k) → (V, k)
        return np.stack([np.bincount(image, w * x[point, c], minlength=num_images) for c in range(x.shape[1])], 1)

    def Bt(a):       # (V, k) → (P, k)
        return np.stack([np.bincount(point, w * a[image, c], minlength=num_points) for c in range(a.shape[1])], 1)

    def S(a):
        return Da[:, None] * a - B(inv_Db[:, None] * Bt(a))

    ra = np.stack([np.bincount(image, w * y[:, c], minlength=num_images) for c in range(k)], 1)
    rb = np.stack([np.bincount(point, w * y[:, c], minlength=num_points) for c in range(k)], 1)
    rhs = _gauge(ra - B(inv_Db[:, None] * rb), comp, ncomp)
    diag = Da - np.bincount(image, w * w * inv_Db[point], minlength=num_images)
    # A Laplacian's diagonal is positive wherever the image ties to another; guard the rest.
    inv_diag = np.where(diag > 1e-300, 1.0 / np.where(diag > 1e-300, diag, 1.0), 0.0)[:, None]
    a = np.zeros((num_images, k)) if x0 is None else _gauge(np.asarray(x0, np.float64), comp, ncomp)
    r = rhs - S(a)
    z = _gauge(inv_diag * r, comp, ncomp)
    p = z.copy()
    rz = np.einsum("vk,vk->k", r, z)
    scale = np.maximum(np.linalg.norm(rhs, axis=0), 1e-300)
    for _ in range(max_iter or 10 * num_images + 100):
        if np.all(np.linalg.norm(r, axis=0) <= rtol * scale):
            break
        Sp = S(p)
        pSp = np.einsum("vk,vk->k", p, Sp)
        alpha = np.where(pSp > 0, rz / np.where(pSp > 0, pSp, 1.0), 0.0)
        a += alpha * p
        r -= alpha * Sp
        z = _gauge(inv_diag * r, comp, ncomp)
        rz_new = np.einsum("vk,vk->k", r, z)
        beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
        p = z + beta * p
        rz = rz_new
    a = _gauge(a, comp, ncomp)
    b = inv_Db[:, None] * (rb - Bt(a))
    return a, b


def _robust_weights(rho: np.ndarray, config: PhotometryConfig, iteration: int) -> np.ndarray:
    """IRLS weights (n,) float64 for the round after ``iteration`` (1-based) of observations with
    RMS log residuals ``rho`` (n,) float64: Huber, min(1, δ/ρ); with the Cauchy loss, from the
    third round on (once Huber, convex, has found the basin), 1 / (1 + (ρ/δ)²)."""
    x = rho / config.robust_threshold
    if config.loss == "cauchy" and iteration >= HUBER_ROUNDS:
        return 1.0 / (1.0 + x * x)
    return np.minimum(1.0, 1.0 / np.maximum(x, 1e-300))


def solve_gains(obs: Observations, config: PhotometryConfig = PhotometryConfig(),
                solver: str | None = None) -> Solution:
    """Robust per-channel log gains from tie-point observations (iteratively reweighted).

    Observations are pruned (:func:`prune`); each reweighting round solves the weighted
    least squares with ``solver`` ("fast" or "reference"; default the config's) and weighs
    an observation by its RMS log residual ρ over the channels against δ =
    ``robust_threshold``: Huber, then (``loss="cauchy"``) Cauchy (:func:`_robust_weights`).
    When every sample has equal channels (a grey capture) one channel
    is solved and copied, so the gains are exactly equal across channels.
    """
    solver = solver or config.solver
    if solver not in SOLVERS:
        raise InputError(f"solver must be one of {SOLVERS}, got {solver!r}")
    V, P = obs.num_images, obs.num_points
    keep = prune(obs.image, obs.point, V, P, config.min_observations, config.min_image_observations)
    image, point = obs.image[keep], obs.point[keep]
    rgb = obs.rgb[keep]
    grayscale = bool(len(rgb) and np.all(rgb[:, 1:] == rgb[:, :1]))
    y = np.log(np.maximum(rgb[:, :1] if grayscale else rgb, 1e-3))
    comp = components(image, point, V, P)
    w = np.ones(len(image))
    a = np.zeros((V, y.shape[1]))
    iterations = 0
    res_rms = 0.0
    if len(image):
        for iterations in range(1, config.iterations + 1):
            if solver == "reference":
                a_new, b = solve_reference(image, point, y, w, V, P, comp)
            else:
                a_new, b = solve_fast(image, point, y, w, V, P, comp, x0=a)
            change = np.abs(a_new - a).max()
            a = a_new
            rho = np.sqrt(np.mean((y - a[image] - b[point]) ** 2, axis=1))
            res_rms = float(np.sqrt(np.sum(w * rho ** 2) / np.sum(w)))
            w = _robust_weights(rho, config, iterations)
            if iterations > 1 and change < 1e-7:
                break
    weights = np.zeros(len(obs.image))
    weights[keep] = w
    log_gains = np.repeat(a, 3, axis=1) if grayscale else a
    return Solution(log_gains, comp >= 0, comp, weights, iterations, res_rms, grayscale)


def estimate_gains(views, points: np.ndarray, config: PhotometryConfig = PhotometryConfig(),
                   progress: bool | None = None, executor: Executor | None = None) -> PhotometryResult:
    """Per-view RGB gains (V, 3) float64 of ``views`` from the cloud ``points`` (N, 3) float64.

    With ``config.enabled`` False every gain is 1. Views that no usable tie point links to
    another view keep gain 1 (``report()["not_estimated"]``). executor: reads the views in
    parallel (None: here).
    """
    t0 = time.perf_counter()
    if not config.enabled:
        return PhotometryResult(np.ones((len(views), 3)), None, 0, 0, 0.0)
    obs = collect_observations(views, points, config, progress, executor)
    sol = solve_gains(obs, config)
    result = PhotometryResult(sol.gains, sol, int((sol.weights > 0).sum()), int(obs.num_points),
                              time.perf_counter() - t0)
    missing = int((~sol.estimated).sum())
    if missing:
        logger.info("photometry: %d of %d images share no usable tie points with others; their gains stay 1",
                    missing, len(views))
    logger.info("photometry: %d observations of %d tie points, %d component(s), gains %s (%.1f s)",
                result.observations, obs.num_points, sol.num_components,
                ", ".join(f"{n} {v['min']:.3f}–{v['max']:.3f}" for n, v in result.report()["gain_summary"].items()
                          if v is not None) or "none", result.seconds)
    return result
