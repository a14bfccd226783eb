"""The fit within the eigen-textures: what the model stores is fitted, not what it then loses.

A quad's stored texture in direction c is X_c = mean + Σ_k w_ck · V_k (:mod:`billboards.pca`),
so with the coefficients w fixed, every (direction, texel) colour is linear in the slots
Z = (mean, V_1 … V_r) of its quad: X = B·Z. Fitting the per-direction textures X and then
compressing them throws back much of what the fit gained (the corrections are a few grey
levels, the size of the compression's own tolerance); fitting Z instead solves

    min_Z  ‖A·B·Z − y‖²  +  λ (Z − Z₀)ᵀ D (Z − Z₀)

where A is :class:`billboards.fit.Problem`'s matrix, Z₀ the eigen-textures of the sampled
textures and D = diag(BᵀB) the weight each slot has in the directions it spans (λ in the
units of :attr:`billboards.fit.FitConfig.prior`; a floor keeps a slot no direction uses
regular). The coefficients and ranks stay those of the sampled textures.

Arrays: slots Z (count·(1+R)·t², 3) float64 flat over (quad − begin, slot j, texel); slot 0
is the mean, slot k the k-th eigen image (zero beyond a quad's rank). Colours only: alpha
stays as sampled.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse

from .fit import Problem
from .pca import EigenTextures

#: The prior weight of a slot that no direction uses (relative to one direction's full weight).
FLOOR = 1e-3


@dataclass(frozen=True, eq=False)
class Subspace:
    """The problem of a range of quads in their slots: ``matrix`` (r, M) = A·B, ``y`` (r, 3)
    measured colours in [0, 1], ``weight`` (M,) the prior's diag(BᵀB) (floored)."""

    matrix: sparse.csr_matrix
    y: np.ndarray
    weight: np.ndarray

    @property
    def size(self) -> int:
        return self.matrix.shape[1]

    def apply(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(self.matrix @ z, np.float64)

    def adjoint(self, e: np.ndarray) -> np.ndarray:
        return np.asarray(self.matrix.T @ e, np.float64)

    def diagonal(self) -> np.ndarray:
        """(M,) the diagonal of (AB)ᵀ(AB)."""
        return np.asarray(self.matrix.multiply(self.matrix).sum(axis=0), np.float64).ravel()

    def prior_weight(self) -> np.ndarray:
        return self.weight

    def rows(self, keep: np.ndarray) -> "Subspace":
        return replace(self, matrix=self.matrix[np.flatnonzero(keep)], y=self.y[keep])


def expansion(coefficients: np.ndarray, rank: np.ndarray, texels: int) -> sparse.csr_matrix:
    """B: the (count·d·t², count·(1+R)·t²) sparse map from slots to per-direction texels.
    coefficients (count, d, R) float, rank (count,) int.

    Built row by row in CSR order: the row of quad q, direction c and texel t holds its
    mean slot (1) and then its eigen slots k < rank[q] (coefficient k), in ascending columns."""
    count, d, R = coefficients.shape
    q = np.repeat(np.arange(count), d * texels)  # (rows,) each row's quad
    t = np.tile(np.arange(texels), count * d)  # ... and texel
    slot = np.arange(1 + R)
    cols = (q[:, None] * (1 + R) + slot) * texels + t[:, None]  # (rows, 1 + R) int64
    vals = np.empty(cols.shape)
    vals[:, 0] = 1.0
    vals[:, 1:] = np.repeat(coefficients.reshape(count * d, R), texels, axis=0)
    used = slot <= np.asarray(rank)[q][:, None]  # the mean always, eigen slot k where k < rank
    indptr = np.zeros(len(q) + 1, np.int64)
    np.cumsum(used.sum(axis=1), out=indptr[1:])
    return sparse.csr_matrix((vals[used], cols[used], indptr), shape=(count * d * texels, count * (1 + R) * texels))


def subspace(prob: Problem, eig: EigenTextures) -> Subspace:
    """``prob`` (a range of ``eig``'s quads, in the same order) in the slots of ``eig``."""
    B = expansion(eig.coefficients, eig.rank, prob.texels)
    AB = (prob.matrix @ B).tocsr()
    weight = np.maximum(np.asarray(B.multiply(B).sum(axis=0), np.float64).ravel(), FLOOR)
    return Subspace(AB, prob.y, weight)


def slots(eig: EigenTextures, texels: int) -> np.ndarray:
    """Z (count·(1+R)·t², 3) float64: the colour channels of ``eig``'s mean and eigen images."""
    count, R = len(eig.rank), eig.basis.shape[1]
    z = np.concatenate([eig.mean[:, None], eig.basis], axis=1).reshape(count, 1 + R, texels, 4)
    return z[..., :3].reshape(-1, 3).astype(np.float64)


def with_slots(eig: EigenTextures, z: np.ndarray) -> EigenTextures:
    """``eig`` with its colour channels from Z (:func:`slots`' layout); alpha, coefficients
    and ranks unchanged; eigen images beyond a quad's rank stay zero."""
    count, R = len(eig.rank), eig.basis.shape[1]
    n = eig.mean.shape[1]
    z = z.reshape(count, 1 + R, n // 4, 3).astype(np.float32)
    mean = eig.mean.reshape(count, n // 4, 4).copy()
    mean[..., :3] = z[:, 0]
    basis = eig.basis.reshape(count, R, n // 4, 4).copy()
    basis[..., :3] = z[:, 1:]
    basis[np.arange(R)[None, :] >= eig.rank[:, None]] = 0.0
    return replace(eig, mean=mean.reshape(count, n), basis=basis.reshape(count, R, n))


def expansion_reference(coefficients: np.ndarray, rank: np.ndarray, texels: int) -> np.ndarray:
    """:func:`expansion` the slow, obvious way, dense, one entry at a time."""
    count, d, R = coefficients.shape
    B = np.zeros((count * d * texels, count * (1 + R) * texels))
    for q in range(count):
        for c in range(d):
            for t in range(texels):
                B[(q * d + c) * texels + t, (q * (1 + R)) * texels + t] = 1.0
                for k in range(rank[q]):
                    B[(q * d + c) * texels + t, (q * (1 + R) + 1 + k) * texels + t] = coefficients[q, c, k]
    return B
