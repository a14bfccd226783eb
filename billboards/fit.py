"""The fit: sampled textures corrected until the model reproduces its training images.

Sampling reads each texel once from the best camera; nothing checks what the model then
draws. The fit closes that loop. For every training view the model's quads are placed
as the renderer places them for that eye (billboards turned toward it, layer blocks
fixed, ground blocks drawn larger by the overlap) and ray cast on the CPU (Open3D's
``RaycastingScene``, :mod:`billboards.fit_cast`); a ray that meets a texel the renderer would discard (blended alpha
< 0.5) goes on to the quad behind it. Each ray that meets a quad is one measurement::

    pixel colour = Σ_s w_s · Σ_k b_k · X[quad, corner_s, texel_k]

the renderer's own filtering: the bracket of sampled directions around the eye with the
renderer's weights w_s (:func:`billboards.decode.direction_corners`), and bilinear taps
b_k kept between the tile's outer texel centres (``billboard_quad.glsl``'s
``tile_point``). The colours X of every (quad, direction, texel) then solve

    min_X  Σ_pixels ‖A X − y‖²  +  λ ‖X − X₀‖²

where X₀ is the sampled texture: λ (``FitConfig.prior``, in units of one pixel's full
weight) keeps texels that few or no pixels measure (a quad seen edge-on, a direction no
training camera looks from) at what sampling gave them, so the system is never singular
and never yields NaN. The build solves this within the eigen-textures the model stores
(:mod:`billboards.fit_subspace`: X = B·Z, Z the mean and eigen images), so that
compression does not undo the fit. With visibility fixed the system falls apart into one
small problem per quad; a chunk of quads is solved at once by conjugate gradients on the
normal equations with a Jacobi preconditioner (:func:`solve`), the residual of every
iteration recorded, until the iterations or the time budget run out.
:func:`solve_reference` is the same least-squares problem solved densely, for tests.
A pixel far off what X₀ predicts saw something passing (:func:`transient_rows`) and is
left out.

Which texels are shown and which are seen through is decided before, by the same images
(:mod:`billboards.fit_alpha`); the quads' places are sampling's.

Arrays: a view's measurements are :func:`record_dtype` rows (one row per ray that met a quad);
textures are (B, d, t, t, 3) float in [0, 1], direction j = p·d_yaw + y.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from scipy import sparse

from core.arrays import column_sums, scale_columns, scale_rows
from core.errors import InputError

from .decode import direction_corners, view_direction_index
from .geometry import GROUND, GROUND_OVERLAP, kind_frames, quad_edges
from .slits import Slits, build_slits

def record_dtype(corners: int) -> np.dtype:
    """The structured dtype of measurements whose direction bracket has ``corners`` (2 or 4) entries."""
    return np.dtype([("quad", "<i4"), ("corner", "<i2", (corners,)), ("weight", "<f4", (corners,)),
                     ("texel", "<f4", (2,)), ("colour", "u1", (3,))])


@dataclass(frozen=True)
class FitConfig:
    seconds: float = 150.0        # wall-clock budget of the fit (s): the solves stop iterating when it is spent
    iterations: int = 6           # conjugate-gradient iterations per chunk of quads at most
    pixel_stride: int = 2         # every n-th pixel of every n-th row of each training image is a measurement
    max_rays_side: int = 800      # ... and at most this many along the image's longer side (a larger stride
                                  # for large photos: the fit's memory follows its measurements)
    prior: float = 0.1            # λ: pull of each texel toward its sampled colour, in pixels of full weight
    see_through: int = 3          # a ray goes on past this many see-through texels at most
    transients: float | None = 96.0   # a measurement off the sampled texture by more than this many grey
                                      # levels in some channel is something passing (a car), not the
                                      # surface, and is left out (None: every measurement counts)
    alpha: bool = True            # decide which texels are shown or seen through by the training images first
                                  # (billboards.fit_alpha)
    alpha_tolerance: float = 12.0  # grey levels (RMS per channel) by which one explanation of a texel's pixels
                                   # must beat the other to change its alpha
    alpha_min_views: int = 2      # a texel's alpha changes only on rays from at least this many views
    alpha_min_rays: int = 3       # ... and at least this many rays

    def stride(self, size: tuple[int, int]) -> int:
        """The pixel stride of a training view of ``size`` (w, h): ``pixel_stride``, larger where
        the image's longer side would give more than ``max_rays_side`` rays."""
        return max(self.pixel_stride, math.ceil(max(size) / self.max_rays_side))

    def __post_init__(self):
        if not (np.isfinite(self.seconds) and self.seconds >= 0):
            raise InputError(f"fit seconds must be a finite number ≥ 0, got {self.seconds!r}")
        for name in ("iterations", "pixel_stride", "max_rays_side", "see_through", "alpha_min_views",
                     "alpha_min_rays"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise InputError(f"fit {name} must be an integer, got {value!r}")
        if self.iterations < 0 or self.pixel_stride < 1 or self.see_through < 0 or self.max_rays_side < 1:
            raise InputError("fit iterations and see_through must be ≥ 0, pixel_stride and max_rays_side ≥ 1")
        if not (np.isfinite(self.prior) and self.prior > 0):
            raise InputError(f"fit prior must be a finite number > 0 (it keeps the solve regular), got {self.prior!r}")
        if not isinstance(self.alpha, (bool, np.bool_)):
            raise InputError(f"fit alpha must be true or false, got {self.alpha!r}")
        if self.alpha_min_views < 1 or self.alpha_min_rays < 1:
            raise InputError("fit alpha_min_views and alpha_min_rays must be ≥ 1")
        if not (np.isfinite(self.alpha_tolerance) and self.alpha_tolerance >= 0):
            raise InputError(f"fit alpha_tolerance must be a finite number ≥ 0, got {self.alpha_tolerance!r}")
        if self.transients is not None and not (np.isfinite(self.transients) and self.transients > 0):
            raise InputError(f"fit transients must be a finite number > 0 or None, got {self.transients!r}")


@dataclass(frozen=True, eq=False)
class Quads:
    """The model's quads as the renderer places them.

    centres (n, 3) float64 world; base_yaw (n,) float64 radians; kind (n,) uint8
    (:data:`~billboards.geometry.KINDS`); size: a billboard's edge (m); block_size: a layer block's edge
    (m), both halved ``split`` times per quad; tile: texels per side t; yaw_offsets (d_yaw,), pitches
    (d_pitch,) radians; pitched: billboards also tilt toward the eye's elevation; slits: the facade
    columns the renderer draws as one quad each (:func:`quads_of`); corner_dz (n, 4) float32 a ground
    block's corners above its centre (:func:`~billboards.geometry.surface_dz`; None: all flat)."""

    centres: np.ndarray
    base_yaw: np.ndarray
    kind: np.ndarray
    size: float
    block_size: float
    tile: int
    yaw_offsets: np.ndarray
    pitches: np.ndarray
    pitched: bool
    slits: Slits
    split: np.ndarray | None = None   # (n,) uint8 each quad's edge halved this many times (None: never)
    corner_dz: np.ndarray | None = None

    @property
    def corners(self) -> int:
        """Directions a view blends per quad: 2 with one sampled pitch, else 4."""
        return 2 if len(self.pitches) <= 1 else 4

    @property
    def num_directions(self) -> int:
        return len(self.yaw_offsets) * len(self.pitches)

    def sizes(self, ids: np.ndarray) -> np.ndarray:
        """(m,) float64 edge of quads ``ids`` that their t texels span (m)."""
        return quad_edges(self.kind[ids], None if self.split is None else self.split[ids], self.size, self.block_size)

    def edges(self, ids: np.ndarray) -> np.ndarray:
        """(m,) float64 edge of quads ``ids`` as drawn: a ground block with its overlap, where
        its border texels repeat."""
        return np.where(self.kind[ids] == GROUND, 1 + 2 * GROUND_OVERLAP, 1.0) * self.sizes(ids)

    def frames(self, ids: np.ndarray, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Right and up axes (m, 3) float64 of quads ``ids`` seen from ``eye`` (3,) float64 world."""
        v = np.asarray(eye, np.float64)[None, :] - self.centres[ids]
        h = np.hypot(v[:, 0], v[:, 1])
        yaw = np.where(h > 0, np.arctan2(v[:, 1], v[:, 0]), 0.0)
        pitch = np.arctan2(v[:, 2], h)
        _, right, up = kind_frames(self.kind[ids], self.base_yaw[ids], yaw, pitch, self.pitched)
        return right, up

    def brackets(self, ids: np.ndarray, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The directions blended for quads ``ids`` seen from ``eye`` and their weights:
        (m, c) int64 and (m, c) float32, c = :attr:`corners` (the renderer's view brackets)."""
        v = np.asarray(eye, np.float64)[None, :] - self.centres[ids]
        yi, pi = view_direction_index(v, self.base_yaw[ids], self.yaw_offsets, self.pitches)
        corners, weights = direction_corners(yi, pi, len(self.yaw_offsets), len(self.pitches))
        c = self.corners
        return corners[:, :c], weights[:, :c]


def quads_of(origin: np.ndarray, centres: np.ndarray, base_yaw: np.ndarray, kind: np.ndarray, size: float,
             block_size: float, tile: int, yaw_offsets: np.ndarray, pitches: np.ndarray,
             pitched: bool = False, split: np.ndarray | None = None, corner_dz: np.ndarray | None = None) -> Quads:
    """:class:`Quads` of a model's arrays: origin (3,) float64; centres (n, 3) float32 relative to
    it; base_yaw (n,) float32; kind (n,) uint8; the rest as in :class:`Quads`. The slits are made
    from the model's own float32 arrays, as the renderer makes them."""
    slits = build_slits(centres, kind, base_yaw, block_size, merge=len(pitches) == 1)
    return Quads(np.asarray(centres, np.float64) + np.asarray(origin, np.float64), np.asarray(base_yaw, np.float64),
                 np.asarray(kind, np.uint8), float(size), float(block_size), int(tile),
                 np.asarray(yaw_offsets, np.float64), np.asarray(pitches, np.float64), bool(pitched), slits,
                 None if split is None else np.asarray(split, np.uint8),
                 None if corner_dz is None or not np.any(corner_dz) else np.asarray(corner_dz, np.float32))


def column_taps(quads: Quads, quad: np.ndarray, texel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The renderer's bilinear filtering: ``texel`` (r, 2) continuous tile coordinates (x =
    column, y = row, 0..t) on quads ``quad`` (r,) → tap quads (r, 4) int64, tap texels (r, 4)
    int64 (row·t + column) and weights (r, 4) float32 summing to 1. The sample point is kept
    between the outer texel centres of what the renderer draws as one texture: the tile, or for
    a block of a slit the column's tiles one below the other (so across a block's top and
    bottom edge it filters with the block above or below, never beyond the column)."""
    t = quads.tile
    slits = quads.slits
    pos = slits.position[quad]
    col = slits.column[pos]
    start, count = slits.column_start[col], slits.column_count[col]
    texel = np.asarray(texel, np.float64)
    px = np.clip(texel[:, 0], 0.5, t - 0.5) - 0.5                                     # texel-centre units
    py = np.clip(texel[:, 1] + (pos - start) * t, 0.5, count * t - 0.5) - 0.5         # down the column
    x0 = np.minimum(np.floor(px).astype(np.int64), t - 1)
    y0 = np.minimum(np.floor(py).astype(np.int64), count * t - 1)
    fx, fy = px - x0, py - y0
    x1, y1 = np.minimum(x0 + 1, t - 1), np.minimum(y0 + 1, count * t - 1)
    xs = np.stack([x0, x1, x0, x1], axis=1)
    ys = np.stack([y0, y0, y1, y1], axis=1)
    tap_quad = slits.order[start[:, None] + ys // t]
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return tap_quad, (ys % t) * t + xs, weights.astype(np.float32)


def blended(quads: Quads, values: np.ndarray, quad: np.ndarray, corner: np.ndarray, weight: np.ndarray,
            texel: np.ndarray) -> np.ndarray:
    """What the renderer draws from ``values`` (n, d, t·t, ...) per-texel values (alpha or
    colour) at measurements: quad (r,) int, corner (r, c) int, weight (r, c) float, texel (r, 2)
    → (r, ...) float32, the bracket's directions blended and each filtered bilinearly
    (:func:`column_taps`)."""
    tap_quad, taps, tap_w = column_taps(quads, quad, texel)
    n, d, tt = values.shape[:3]
    # one gather of whole items from the values as rows (n·d·t², ...), where they are laid out so
    flat = values.reshape((n * d * tt,) + values.shape[3:]) if values.flags.c_contiguous else None
    out = 0.0
    for s in range(corner.shape[1]):
        if flat is None:
            v = np.asarray(values[tap_quad, corner[:, s:s + 1], taps], np.float32)    # (r, 4, ...)
        else:
            v = np.take(flat, (tap_quad * d + corner[:, s:s + 1]) * tt + taps, axis=0).astype(np.float32)
        w = weight[:, s:s + 1] * tap_w                                                 # (r, 4)
        # the taps' products added left to right, as (w·v).sum(axis=1) adds its four
        total = _tap(w, v, 0)
        for k in range(1, w.shape[1]):
            total += _tap(w, v, k)
        out = out + total
    return out


def _tap(w: np.ndarray, v: np.ndarray, k: int) -> np.ndarray:
    """w[:, k] times v[:, k] (r, ...): weights (r, 4), values (r, 4, ...)."""
    if v.ndim == 2:
        return w[:, k] * v[:, k]
    return scale_rows(v[:, k].reshape(len(v), math.prod(v.shape[2:])), w[:, k]).reshape(v[:, k].shape)


@dataclass(frozen=True, eq=False)
class Problem:
    """The least-squares problem of a chunk of ``count`` quads: unknowns X (N, 3),
    N = count·d_pitch·d_yaw·t², flat over (quad − begin, direction p·d_yaw + y, texel
    row·t + column); each measurement i predicts Σ_k a[i, k]·X[idx[i, k]]. idx (r, k) int64,
    a (r, k) float64, y (r, 3) float64 measured colours in [0, 1]."""

    idx: np.ndarray
    a: np.ndarray
    y: np.ndarray
    count: int
    d_pitch: int
    d_yaw: int
    texels: int

    @property
    def size(self) -> int:
        return self.count * self.d_pitch * self.d_yaw * self.texels

    @cached_property
    def matrix(self) -> sparse.csr_matrix:
        """A as a sparse (r, N) float64 matrix (a row's repeated taps add up)."""
        r, k = self.idx.shape
        return sparse.csr_matrix((self.a.ravel(), self.idx.ravel(), np.arange(0, r * k + 1, k)),
                                 shape=(r, self.size))

    def apply(self, x: np.ndarray) -> np.ndarray:
        """A·x: (N, 3) → (r, 3)."""
        return np.asarray(self.matrix @ x, np.float64)

    def adjoint(self, z: np.ndarray) -> np.ndarray:
        """Aᵀ·z: (r, 3) → (N, 3)."""
        return np.asarray(self.matrix.T @ z, np.float64)

    def rows(self, keep: np.ndarray) -> "Problem":
        """The problem of the measurements where ``keep`` (r,) bool is set."""
        return replace(self, idx=self.idx[keep], a=self.a[keep], y=self.y[keep])

    def prior_weight(self) -> np.ndarray:
        """(N,) each unknown's weight in the prior: one each."""
        return np.ones(self.size)

    def diagonal(self) -> np.ndarray:
        """(N,) the diagonal of AᵀA: each unknown's summed squared weights."""
        return np.bincount(self.idx.ravel(), weights=np.square(self.a).ravel(), minlength=self.size).astype(np.float64)


def problem(quads: Quads, records: np.ndarray, begin: int, count: int, outside: np.ndarray | None) -> Problem:
    """The problem of quads [begin, begin + count) from their ``records`` (:func:`record_dtype`
    rows of any views, every quad in range). A tap on a quad outside the range (the block
    above or below in a slit) is not an unknown of this problem: its colour in ``outside``
    (n, d, t·t, 4) uint8 RGBA (a memory map will do: the sampled textures) moves to the
    measured side (None: there must be no such tap)."""
    quad = records["quad"].astype(np.int64)
    if len(quad) and (quad.min() < begin or quad.max() >= begin + count):
        raise InputError(f"records of quads outside [{begin}, {begin + count})")
    d_pitch, d_yaw, T = len(quads.pitches), len(quads.yaw_offsets), quads.tile * quads.tile
    tap_quad, taps, tap_w = column_taps(quads, quad, records["texel"])                 # (r, 4)
    corner = records["corner"].astype(np.int64)                                        # (r, c)
    r, c = corner.shape
    a = records["weight"].astype(np.float64)[:, :, None] * tap_w[:, None, :]          # (r, c, 4)
    tq = np.broadcast_to(tap_quad[:, None, :], (r, c, 4))
    tt = np.broadcast_to(taps[:, None, :], (r, c, 4))
    cc = np.broadcast_to(corner[:, :, None], (r, c, 4))
    inside = (tq >= begin) & (tq < begin + count)
    y = records["colour"].astype(np.float64) / 255.0
    if not inside.all():
        far = ~inside
        if outside is None:
            raise InputError(f"records of quads [{begin}, {begin + count}) tap quads outside it")
        known = np.asarray(outside[tq[far], cc[far], tt[far]], np.float64)[:, :3] / 255.0
        np.subtract.at(y, np.nonzero(far)[0], a[far][:, None] * known)
        a = np.where(inside, a, 0.0)
    idx = np.where(inside, ((tq - begin) * (d_pitch * d_yaw) + cc) * T + tt, 0)
    return Problem(idx.reshape(r, c * 4), a.reshape(r, c * 4), y, count, d_pitch, d_yaw, T)


def transient_rows(prob, x0: np.ndarray, threshold: float) -> np.ndarray:
    """(r,) bool: the measurements of ``prob`` (a :class:`Problem` or its subspace) whose colour
    is off what the unknowns ``x0`` (N, 3) predict by more than ``threshold`` grey levels in some channel. The sampled textures
    already left out what most cameras did not see there, so such a pixel saw something
    in front of the surface for a moment (a passing car), which the fit must not paint in."""
    return (np.abs(prob.apply(x0) - prob.y) > threshold / 255.0).any(axis=1)


def solve(prob: Problem, x0: np.ndarray, prior: float, iterations: int,
          deadline: float | None = None, clip: bool = True) -> tuple[np.ndarray, list[float], list[float]]:
    """min ‖A·x − y‖² + prior·(x − x0)ᵀP(x − x0) by conjugate gradients on the normal equations
    of the correction d = x − x0, (AᵀA + prior·P)·d = Aᵀ(y − A·x0), Jacobi-preconditioned,
    from d = 0; P = diag(``prob.prior_weight()``) (ones for a :class:`Problem`; a
    :class:`billboards.fit_subspace.Subspace` weighs its slots by the directions they span).

    x0 (N, 3) float; prior > 0; at most ``iterations``, none begun after ``deadline``
    (``time.time()``). Returns x (N, 3) float64 (clipped to [0, 1] with ``clip``), the
    squared data residual ‖A·x − y‖² (summed over channels) before the first iteration and
    after each, and the seconds spent by each of those moments. Unknowns that no
    measurement touches stay exactly at x0.
    """
    if not prior > 0:
        raise InputError(f"prior must be > 0, got {prior!r}")
    t0 = time.perf_counter()
    x = np.array(x0, np.float64)
    e = prob.apply(x) - prob.y                                  # data residual A·x − y, kept up to date
    history = [float(np.square(e).sum())]
    seconds = [time.perf_counter() - t0]
    weight = prior * prob.prior_weight()                        # (N,) the prior's diagonal
    diagonal = prob.diagonal() + weight
    precondition = 1.0 / diagonal
    r = -prob.adjoint(e)                                        # the right-hand side, as d = 0
    z = scale_rows(r, precondition)
    p = z.copy()
    rz = column_sums(r * z)
    for _ in range(iterations):
        if deadline is not None and time.time() > deadline:
            break
        if not np.any(rz > 1e-24):
            break                                               # converged (or nothing measured)
        Ap = prob.apply(p)
        Mp = prob.adjoint(Ap) + scale_rows(p, weight)
        pMp = column_sums(p * Mp)
        step = np.where(pMp > 0, rz / np.where(pMp > 0, pMp, 1.0), 0.0)
        x += scale_columns(p, step)
        e += scale_columns(Ap, step)
        r -= scale_columns(Mp, step)
        z = scale_rows(r, precondition)
        rz_new = column_sums(r * z)
        p = z + scale_columns(p, np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0))
        rz = rz_new
        history.append(float(np.square(e).sum()))
        seconds.append(time.perf_counter() - t0)
    if clip:
        np.clip(x, 0.0, 1.0, out=x)
    return x, history, seconds


def solve_reference(prob: Problem, x0: np.ndarray, prior: float) -> np.ndarray:
    """:func:`solve` the slow, obvious way: A as a dense matrix built one measurement and tap
    at a time, the regularised normal equations solved directly in float64 (unclipped).
    For small problems only."""
    A = np.zeros((len(prob.y), prob.size))
    for i in range(len(prob.y)):
        for k in range(prob.idx.shape[1]):
            A[i, prob.idx[i, k]] += prob.a[i, k]
    M = A.T @ A + prior * np.eye(prob.size)
    x0 = np.asarray(x0, np.float64)
    return x0 + np.linalg.solve(M, A.T @ (prob.y - A @ x0))
