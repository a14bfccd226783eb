"""Rigid transforms: the exact inverse of 4×4 poses and the rotation nearest a matrix."""

from __future__ import annotations

import numpy as np


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) float64 inverses of rigid transforms (..., 4, 4): [Rᵀ | −Rᵀt], exact where
    ``np.linalg.inv`` would round."""
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) float64: the rotation closest to ``R`` (3, 3) in the Frobenius norm (SVD; det +1)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
