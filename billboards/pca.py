"""Eigen-textures: batched PCA of each billboard's view-dependent texture stack.

A billboard has d view samples of a t×t RGBA texture, flattened to a stack
X (d, n) with n = t·t·4 values in [0, 1]. It is stored as a mean image, r
orthonormal eigen images and d×r coefficients:

    X_i ≈ mean + Σ_k w_ik · V_k        (i < d view, k < r eigen image)

The fast path (:func:`eigen_textures`) works on chunks of billboards at once:
centre, form the small d×d Gram matrices G = A·Aᵀ with one stacked
``np.matmul``, decompose them with one stacked ``np.linalg.eigh`` (always in
float64), lift the eigenvectors to eigen images V_k = Aᵀu_k / ‖Aᵀu_k‖ and
project for the coefficients w_ik = A_i · V_k. Peak memory is a few chunk-sized
arrays, whatever the number of billboards. :func:`eigen_textures_reference` is
the slow, obvious version (one float64 SVD per billboard) the tests compare
against.

Rank per billboard (:func:`choose_rank`): the eigenvalues λ of the centred
Gram are the energy each eigen image explains. A stack whose texture does not
change with direction gets r = 0 (mean only); otherwise r is the smallest rank
that reaches the cumulative contribution ratio and/or keeps the RMS
reconstruction error within a bound in 8-bit units, capped by ``max_rank`` and
by the numerical rank (eigenvalues that are round-off give garbage images).

Missing values are NaN in the input: each is replaced by its texel's mean over
the billboard's valid views (0 where no view is valid) before the PCA, so a
billboard with one valid view comes out as that view with r = 0. No NaN or inf
ever reaches the output.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from core.errors import InputError
from core.metrics import PSNR_MAX_DB

logger = logging.getLogger(__name__)

PRECISIONS = ("float64", "float32")


@dataclass(frozen=True)
class PcaTolerances:
    """Every numerical tolerance of the eigen-texture code, in one place."""

    zero_rms: float = 1e-6  # centred RMS ≤ this × data scale → no view dependence, r = 0 (8-bit step: 4e-3)
    rank_rtol64: float = 1e-10  # eigenvalues ≤ this × λ_max are round-off (float64 Gram: errors ~1e-14 λ_max)
    rank_rtol32: float = 1e-5  # the same for a float32 Gram (entries off by ~√n·6e-8 ≈ 4e-6 relative)
    max_abs_value: float = 1e6  # inputs beyond this magnitude are rejected (textures are in [0, 1])
    psnr_max_db: float = PSNR_MAX_DB  # psnr of identical images (finite, so that reports stay valid JSON)


#: The tolerances used by this module.
TOL = PcaTolerances()


@dataclass(frozen=True)
class PcaConfig:
    ratio: float | None = 0.95  # cumulative contribution ratio a rank must reach; None = rule off
    max_error: float | None = 7.0  # RMS reconstruction error bound in 8-bit units (0–255 scale); None = rule off
    max_rank: int = 16  # never more eigen images than this
    fixed_rank: int | None = None  # each billboard gets min(fixed_rank, its numerical rank); overrides the rules
    chunk: int = 256  # billboards per batched Gram/eigh (memory: ~chunk·d·n·8 bytes per work array)
    precision: str = "float64"  # "float64" or "float32": the big matmuls (centring, Gram, lifting); eigh is float64

    def __post_init__(self):
        if self.ratio is not None and not 0.0 < self.ratio <= 1.0:
            raise InputError(f"PcaConfig.ratio must lie in (0, 1] or be None, got {self.ratio}")
        if self.max_error is not None and not (math.isfinite(self.max_error) and self.max_error >= 0.0):
            raise InputError(f"PcaConfig.max_error must be finite and ≥ 0 or None, got {self.max_error}")
        if self.max_rank < 0:
            raise InputError(f"PcaConfig.max_rank must be ≥ 0, got {self.max_rank}")
        if self.fixed_rank is not None and not 0 <= self.fixed_rank <= self.max_rank:
            raise InputError(f"PcaConfig.fixed_rank must lie in [0, max_rank={self.max_rank}], "
                             f"got {self.fixed_rank} (raise max_rank too)")
        if self.chunk < 1:
            raise InputError(f"PcaConfig.chunk must be ≥ 1, got {self.chunk}")
        if self.precision not in PRECISIONS:
            raise InputError(f"PcaConfig.precision must be one of {PRECISIONS}, got {self.precision!r}")


@dataclass(frozen=True, eq=False)
class EigenTextures:
    """Compressed view-dependent textures of B billboards (d views, n values each).

    mean: (B, n) float32 mean image.
    basis: (B, R, n) float32 eigen images (rows; orthonormal as the PCA makes them, not
        once fitted), zero rows beyond a billboard's rank; R = the largest rank in the batch (may be 0).
    coefficients: (B, d, R) float32 w_ik, zero beyond a billboard's rank.
    rank: (B,) int32 eigen images each billboard uses.
    """

    mean: np.ndarray
    basis: np.ndarray
    coefficients: np.ndarray
    rank: np.ndarray

    @property
    def num_views(self) -> int:
        return self.coefficients.shape[1]

    def slice(self, begin: int, end: int) -> "EigenTextures":
        """Billboards [begin, end) (R kept)."""
        return EigenTextures(self.mean[begin:end], self.basis[begin:end], self.coefficients[begin:end],
                             self.rank[begin:end])

    def reconstruct(self) -> np.ndarray:
        """(B, d, n) float32: mean + Σ_k w_ik V_k for every view."""
        return self.mean[:, None, :] + np.matmul(self.coefficients, self.basis)

    def rms_error(self, samples: np.ndarray) -> np.ndarray:
        """(B,) float64 RMS of reconstruction − samples over each billboard's valid values (0–1 scale).

        samples: (B, d, n) as given to :func:`eigen_textures`; NaN values are
        left out, and a billboard without any valid value scores 0.
        """
        samples = np.asarray(samples)
        if samples.shape != (len(self.rank), self.num_views, self.mean.shape[1]):
            raise InputError(f"samples of shape {samples.shape} do not match the eigen-textures "
                             f"({len(self.rank)}, {self.num_views}, {self.mean.shape[1]})")
        diff = self.reconstruct().astype(np.float64) - samples
        valid = ~np.isnan(diff)
        count = valid.sum(axis=(1, 2))
        sq = np.where(valid, diff * diff, 0.0).sum(axis=(1, 2))
        return np.sqrt(sq / np.maximum(count, 1))


def choose_rank(eigenvalues: np.ndarray, num_values: int, config: PcaConfig = PcaConfig(),
                scale: np.ndarray | float | None = None) -> np.ndarray:
    """Eigen images to keep per billboard.

    eigenvalues: (B, d) float64 eigenvalues of each centred Gram matrix, in
        descending order (the energy each eigen image explains; tiny negative
        round-off is treated as 0).
    num_values: d·n, the number of values in one billboard's stack.
    scale: (B,) or scalar magnitude of the data (eigen_textures passes the
        largest |mean value|, at least 1) against which "no variance" is
        judged; None = 1.
    Returns (B,) int32 ranks.

    r = 0 where the total energy is at most (TOL.zero_rms · scale)² · d·n.
    Otherwise the ratio rule gives the smallest r with Σ_{k<r} λ_k ≥ ratio · Σ λ,
    the error rule the smallest r with √(Σ_{k≥r} λ_k / (d·n)) · 255 ≤ max_error;
    with both on, the smaller (either criterion suffices); with neither, the
    numerical rank. ``fixed_rank`` replaces the rules. The result never exceeds
    ``max_rank`` nor the numerical rank (eigenvalues > rtol · λ_max, rtol by the
    Gram's precision).
    """
    lam = np.clip(np.asarray(eigenvalues, dtype=np.float64), 0.0, None)
    if lam.ndim != 2:
        raise InputError(f"eigenvalues must be (B, d), got shape {lam.shape}")
    count, d = lam.shape
    if count == 0:
        return np.zeros(0, np.int32)
    scale = np.broadcast_to(np.ones(1) if scale is None else np.asarray(scale, np.float64), (count,))
    # cumulative energy with a leading 0: head[:, r] = Σ_{k<r} λ_k, tail[:, r] = Σ_{k≥r} λ_k
    head = np.concatenate([np.zeros((count, 1)), np.cumsum(lam, axis=1)], axis=1)
    tail = np.concatenate([np.cumsum(lam[:, ::-1], axis=1)[:, ::-1], np.zeros((count, 1))], axis=1)
    total = head[:, -1]
    zero = total <= (TOL.zero_rms * scale) ** 2 * num_values
    rtol = TOL.rank_rtol32 if config.precision == "float32" else TOL.rank_rtol64
    numerical = np.where(zero, 0, (lam > rtol * lam.max(axis=1, keepdims=True)).sum(axis=1))
    if config.fixed_rank is not None:
        rank = np.full(count, config.fixed_rank)
    else:
        rules = []
        if config.ratio is not None:  # the first r that reaches the ratio (r = d always does)
            rules.append(np.argmax(head >= config.ratio * total[:, None], axis=1))
        if config.max_error is not None:  # tail[:, d] = 0 always satisfies the bound
            rules.append(np.argmax(np.sqrt(tail / num_values) * 255.0 <= config.max_error, axis=1))
        rank = np.minimum.reduce(rules) if rules else numerical
    return np.minimum(np.minimum(rank, numerical), config.max_rank).astype(np.int32)


def eigen_textures(samples: np.ndarray, config: PcaConfig = PcaConfig(),
                   progress: bool | None = False) -> EigenTextures:
    """Batched PCA of B billboards' view stacks.

    samples: (B, d, n) float32 or float64, values in [0, 1]; NaN marks a missing
        texel or view. inf or |value| > TOL.max_abs_value raises ValueError.
    progress: tqdm bar over chunks (None = only on a terminal).
    Returns :class:`EigenTextures`; every array is finite.
    """
    samples = _check_samples(samples)
    count, d, n = samples.shape
    parts = []
    chunks = range(0, count, config.chunk)
    for start in tqdm(chunks, desc="pca", unit="chunk", disable=None if progress is None else not progress):
        parts.append(_eigen_chunk(samples[start:start + config.chunk], config, start))
    result = _assemble(parts, count, d, n)
    if count:
        logger.debug("eigen-textures of %d billboards: mean rank %.2f, %d with r = 0, max %d", count,
                     result.rank.mean(), int((result.rank == 0).sum()), int(result.rank.max()))
    return result


def eigen_textures_reference(samples: np.ndarray, config: PcaConfig = PcaConfig()) -> EigenTextures:
    """Slow, obvious eigen-textures: one float64 SVD per billboard, same rank rule.

    Same arguments and result as :func:`eigen_textures` (``chunk`` and
    ``precision`` are ignored: everything is float64). For tests.
    """
    samples = _check_samples(samples)
    config = replace(config, precision="float64")
    count, d, n = samples.shape
    means, bases, coeffs, ranks = [], [], [], []
    for b in range(count):
        x = samples[b].astype(np.float64)
        missing = np.isnan(x)
        if missing.any():
            for j in np.flatnonzero(missing.any(axis=0)):
                valid = ~missing[:, j]
                x[~valid, j] = x[valid, j].mean() if valid.any() else 0.0
        mean = x.mean(axis=0)
        a = x - mean
        _, s, vt = np.linalg.svd(a, full_matrices=False)
        lam = np.zeros(d)
        lam[:len(s)] = s ** 2
        r = int(choose_rank(lam[None], d * n, config, max(1.0, np.abs(mean).max(initial=0.0)))[0])
        coeff = a @ vt[:r].T
        flip = np.where(np.take_along_axis(coeff, np.abs(coeff).argmax(axis=0)[None], axis=0) < 0, -1.0, 1.0)
        means.append(mean)
        bases.append(vt[:r] * flip.T)
        coeffs.append(coeff * flip)
        ranks.append(r)
    width = max(ranks, default=0)
    basis_out = np.zeros((count, width, n), np.float32)
    coeff_out = np.zeros((count, d, width), np.float32)
    for b, r in enumerate(ranks):
        basis_out[b, :r] = bases[b]
        coeff_out[b, :, :r] = coeffs[b]
    return EigenTextures(np.array(means, np.float32).reshape(count, n), basis_out, coeff_out,
                         np.array(ranks, np.int32))


# ---------------------------------------------------------------------------------------------------


def _check_samples(samples: np.ndarray) -> np.ndarray:
    samples = np.asarray(samples)
    if samples.ndim != 3:
        raise InputError(f"samples must be (B, d, n), got shape {samples.shape}")
    if samples.dtype not in (np.float32, np.float64):
        raise InputError(f"samples must be float32 or float64, got {samples.dtype}")
    if samples.shape[1] < 1 and samples.shape[0]:
        raise InputError("samples need at least one view (d ≥ 1)")
    return samples


def _check_range(x: np.ndarray, first: int) -> None:
    """Raise ValueError for inf or values beyond TOL.max_abs_value in a chunk (first = its offset)."""
    bad = np.isinf(x) | (np.abs(np.nan_to_num(x)) > TOL.max_abs_value)
    if bad.any():
        b = first + int(np.argwhere(bad)[0, 0])
        raise InputError(f"samples of billboard {b} hold inf or values beyond ±{TOL.max_abs_value:g} "
                         "(textures are in [0, 1]; NaN marks missing values)")


def _fill_missing(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Replace NaN by the texel's mean over the valid views (0 if none).

    x: (B, d, n) float32/float64 finite or NaN. Returns the filled copy (same
    dtype) and the mean (B, n) float64 over all views of the filled stack.
    """
    valid = ~np.isnan(x)
    num = valid.sum(axis=1)
    mean = np.where(valid, x, 0).sum(axis=1, dtype=np.float64) / np.maximum(num, 1)
    filled = np.where(valid, x, mean[:, None, :].astype(x.dtype))
    return filled, mean


def _fix_signs(vectors: np.ndarray) -> np.ndarray:
    """Flip columns of (B, d, R) in place so that each column's largest-magnitude entry is positive.

    Applied to the Gram eigenvectors u_k (or the coefficients w_·k = σ_k u_k):
    the view that an eigen image serves most gets a positive coefficient.
    """
    if vectors.size:
        peak = np.take_along_axis(vectors, np.abs(vectors).argmax(axis=1)[:, None, :], axis=1)
        vectors *= np.where(peak < 0, -1.0, 1.0).astype(vectors.dtype)
    return vectors


def _eigen_chunk(x: np.ndarray, config: PcaConfig, first: int = 0) -> tuple[np.ndarray, ...]:
    """PCA of one chunk (b, d, n) that starts at billboard ``first``.

    Returns mean (b, n), basis (b, r, n), coefficients (b, d, r), all float32,
    and rank (b,) int32, with r the chunk's largest rank.
    """
    b, d, n = x.shape
    work = np.float64 if config.precision == "float64" else np.float32
    with np.errstate(over="ignore", invalid="ignore"):
        mean = x.sum(axis=1, dtype=np.float64) / d
    if not np.isfinite(mean).all():  # NaN (missing), inf or overflow somewhere: the careful path
        _check_range(x, first)
        x, mean = _fill_missing(x)
    a = np.subtract(x, mean[:, None, :].astype(work), dtype=work)  # centred, a new (b, d, n) array
    with np.errstate(over="ignore", invalid="ignore"):  # out-of-range inputs are caught just below
        gram = np.matmul(a, a.transpose(0, 2, 1)).astype(np.float64)
    scale = np.maximum(1.0, np.abs(mean).max(axis=1, initial=0.0))
    # |value| ≤ |mean| + √G_ii: one cheap test instead of a pass over the chunk
    bound = scale + np.sqrt(np.abs(np.einsum("bii->bi", gram)).max(axis=1, initial=0.0))
    if not (np.isfinite(gram).all() and (bound <= TOL.max_abs_value).all()):
        _check_range(x, first)
    lam, u = np.linalg.eigh(gram)  # ascending; only the lower triangle is read
    lam, u = lam[:, ::-1], u[:, :, ::-1]
    rank = choose_rank(lam, d * n, config, scale)
    width = int(rank.max(initial=0))
    if width == 0:
        return mean.astype(np.float32), np.zeros((b, 0, n), np.float32), np.zeros((b, d, 0), np.float32), rank
    ut = _fix_signs(u[:, :, :width].copy()).transpose(0, 2, 1).astype(work)  # (b, r, d)
    basis = np.matmul(ut, a)  # (b, r, n): Aᵀu_k, norm √λ_k
    norm = np.sqrt(np.einsum("brn,brn->br", basis, basis, dtype=np.float64))
    keep = np.arange(width)[None, :] < rank[:, None]
    inv = np.where(keep & (norm > 0), 1.0 / np.where(norm > 0, norm, 1.0), 0.0)
    basis *= inv[:, :, None].astype(work)
    stored = basis.astype(np.float32, copy=False)
    if stored is not basis:
        basis[...] = stored  # round in place: project onto the eigen images as they are stored
    coefficients = np.matmul(a, basis.transpose(0, 2, 1))
    return mean.astype(np.float32), stored, coefficients.astype(np.float32, copy=False), rank


def _assemble(parts: list[tuple[np.ndarray, ...]], count: int, d: int, n: int) -> EigenTextures:
    width = max((p[1].shape[1] for p in parts), default=0)
    mean = np.zeros((count, n), np.float32)
    basis = np.zeros((count, width, n), np.float32)
    coefficients = np.zeros((count, d, width), np.float32)
    rank = np.zeros(count, np.int32)
    if len(parts) == 1:
        return EigenTextures(*parts[0])
    start = 0
    for m, v, w, r in parts:
        stop = start + len(m)
        mean[start:stop] = m
        basis[start:stop, :v.shape[1]] = v
        coefficients[start:stop, :, :w.shape[2]] = w
        rank[start:stop] = r
        start = stop
    return EigenTextures(mean, basis, coefficients, rank)
