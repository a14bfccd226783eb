"""Eigen-textures: the batched PCA against the per-billboard SVD reference, rank rules, stiff cases."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from billboards.pca import TOL, EigenTextures, PcaConfig, choose_rank, eigen_textures, eigen_textures_reference
from core.metrics import psnr

PRECISIONS = ["float64", "float32"]
#: (reconstruction atol, orthonormality atol) per Gram precision, values on the 0–1 scale
ATOL = {"float64": (2e-6, 1e-5), "float32": (2e-5, 1e-3)}
ALL = dict(ratio=None, max_error=None)  # no rule: every numerically significant eigen image (≤ max_rank)


def low_rank(rng: np.random.Generator, count: int, d: int, n: int, amplitudes=(0.1, 0.04, 0.015, 0.005),
             dtype=np.float32) -> np.ndarray:
    """(count, d, n) stacks in [0.05, 0.95]: a mean image plus len(amplitudes) view-dependent components.

    The components are orthogonal with the given RMS amplitudes, scaled down
    together where needed so that no value leaves the range (no clipping, so
    the centred rank is exactly len(amplitudes), as far as d allows).
    """
    k = len(amplitudes)
    mean = 0.5 + 0.2 * rng.uniform(-1, 1, (count, 1, n))
    comp = np.linalg.qr(rng.standard_normal((count, n, k)))[0].transpose(0, 2, 1) * math.sqrt(n)
    weights = np.linalg.qr(rng.standard_normal((count, d, k)))[0] * math.sqrt(d) if d >= k else \
        rng.standard_normal((count, d, k))
    part = (weights * np.asarray(amplitudes)) @ comp
    part *= np.minimum(1.0, 0.25 / np.abs(part).max(axis=(1, 2), keepdims=True))
    return (mean + part).astype(dtype)


def assert_valid(et: EigenTextures, count: int, d: int, n: int) -> None:
    """Shapes, dtypes, finiteness and zero padding beyond each billboard's rank."""
    width = et.basis.shape[1]
    assert et.mean.shape == (count, n) and et.mean.dtype == np.float32
    assert et.basis.shape == (count, width, n) and et.basis.dtype == np.float32
    assert et.coefficients.shape == (count, d, width) and et.coefficients.dtype == np.float32
    assert et.rank.shape == (count,) and et.rank.dtype == np.int32
    assert width == (int(et.rank.max()) if count else 0)
    for a in (et.mean, et.basis, et.coefficients):
        assert np.isfinite(a).all()
    unused = np.arange(width)[None, :] >= et.rank[:, None]
    assert not et.basis[unused].any()
    assert not et.coefficients.transpose(0, 2, 1)[unused].any()
    assert np.isfinite(et.reconstruct()).all()


def orthonormality_error(et: EigenTextures) -> float:
    gram = np.matmul(et.basis.astype(np.float64), et.basis.transpose(0, 2, 1))
    return max((np.abs(gram[b, :r, :r] - np.eye(r)).max(initial=0.0) for b, r in enumerate(et.rank)),
               default=0.0)


def svd_eigenvalues(x: np.ndarray) -> np.ndarray:
    """(B, d) descending eigenvalues of each centred stack's Gram matrix, by float64 SVD."""
    a = x.astype(np.float64) - x.astype(np.float64).mean(axis=1, keepdims=True)
    s = np.linalg.svd(a, compute_uv=False)
    lam = np.zeros(x.shape[:2])
    lam[:, :s.shape[1]] = s ** 2
    return lam


# --- fast against reference --------------------------------------------------------------------------


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("shape", [(6, 32, 256), (5, 8, 64), (3, 5, 1024), (4, 32, 16), (2, 3, 4)])
@pytest.mark.parametrize("rule", [dict(), ALL, dict(ratio=0.99, max_error=None), dict(ratio=None, max_error=1.0)])
def test_matches_reference(shape, precision, rule):
    count, d, n = shape
    x = low_rank(np.random.default_rng(sum(shape)), count, d, n)
    config = PcaConfig(precision=precision, **rule)
    fast, ref = eigen_textures(x, config), eigen_textures_reference(x, config)
    assert_valid(fast, count, d, n)
    assert_valid(ref, count, d, n)
    atol, ortho = ATOL[precision]
    np.testing.assert_array_equal(fast.rank, ref.rank)
    np.testing.assert_allclose(fast.mean, ref.mean, rtol=0, atol=1e-7)
    np.testing.assert_allclose(fast.reconstruct(), ref.reconstruct(), rtol=0, atol=atol)
    assert orthonormality_error(fast) <= ortho
    # distinct eigenvalues: the same eigen images and coefficients (same sign convention, checked up to sign)
    for b, r in enumerate(fast.rank):
        dots = np.abs(np.einsum("kn,kn->k", fast.basis[b, :r].astype(np.float64), ref.basis[b, :r]))
        np.testing.assert_allclose(dots, 1.0, rtol=0, atol=10 * ortho)
        np.testing.assert_allclose(np.abs(fast.coefficients[b]), np.abs(ref.coefficients[b]), rtol=0, atol=10 * atol)
    # coefficients are the projections of the centred views on the stored eigen images
    a = x.astype(np.float64) - fast.mean[:, None, :]
    np.testing.assert_allclose(fast.coefficients, a @ fast.basis.transpose(0, 2, 1), rtol=0, atol=10 * atol)


@pytest.mark.parametrize("precision", PRECISIONS)
def test_float64_input_and_signs(precision):
    x = low_rank(np.random.default_rng(1), 4, 16, 256, dtype=np.float64)
    et = eigen_textures(x, PcaConfig(precision=precision, **ALL))
    np.testing.assert_allclose(et.reconstruct(), x, rtol=0, atol=ATOL[precision][0])
    # sign convention: the largest-magnitude coefficient of every eigen image is positive
    for b, r in enumerate(et.rank):
        w = et.coefficients[b, :, :r]
        assert (w[np.abs(w).argmax(axis=0), np.arange(r)] > 0).all()


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("chunk", [1, 3, 256])
def test_chunking_gives_the_same_result(chunk, precision):
    rng = np.random.default_rng(2)
    x = np.concatenate([low_rank(rng, 5, 12, 64), low_rank(rng, 2, 12, 64, amplitudes=(0.1,)),
                        np.full((1, 12, 64), 0.25, np.float32)])
    whole = eigen_textures(x, PcaConfig(precision=precision, chunk=256))
    parts = eigen_textures(x, PcaConfig(precision=precision, chunk=chunk))
    assert_valid(parts, 8, 12, 64)
    np.testing.assert_array_equal(parts.rank, whole.rank)
    for a, b in [(parts.mean, whole.mean), (parts.basis, whole.basis), (parts.coefficients, whole.coefficients)]:
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


# --- rank rules --------------------------------------------------------------------------------------


@pytest.mark.parametrize("max_error", [0.5, 1.0, 3.0, 8.0])
def test_error_rule_respects_the_bound_with_the_smallest_rank(max_error):
    x = low_rank(np.random.default_rng(3), 6, 24, 256, amplitudes=(0.08, 0.04, 0.02, 0.01, 0.005, 0.0025))
    config = PcaConfig(ratio=None, max_error=max_error)
    et = eigen_textures(x, config)
    assert (et.rms_error(x) * 255 <= max_error * (1 + 1e-4)).all()
    for b, r in enumerate(et.rank):  # one eigen image fewer breaks the bound
        if r > 0:
            fewer = eigen_textures(x[b:b + 1], PcaConfig(fixed_rank=int(r) - 1))
            assert fewer.rms_error(x[b:b + 1])[0] * 255 > max_error


@pytest.mark.parametrize("ratio", [0.5, 0.9, 0.95, 0.999])
def test_ratio_rule_reaches_the_ratio_with_the_smallest_rank(ratio):
    x = low_rank(np.random.default_rng(4), 6, 24, 256, amplitudes=(0.08, 0.05, 0.03, 0.02, 0.01))
    et = eigen_textures(x, PcaConfig(ratio=ratio, max_error=None))
    lam = svd_eigenvalues(x)
    captured = np.take_along_axis(np.cumsum(lam, axis=1), et.rank[:, None] - 1, axis=1)[:, 0]
    before = np.take_along_axis(np.cumsum(lam, axis=1), np.maximum(et.rank[:, None] - 2, 0), axis=1)[:, 0]
    assert (et.rank >= 1).all()
    assert (captured >= ratio * lam.sum(axis=1) * (1 - 1e-9)).all()
    assert (np.where(et.rank > 1, before, 0.0) < ratio * lam.sum(axis=1)).all()


def test_both_rules_take_the_smaller_rank():
    x = low_rank(np.random.default_rng(5), 6, 24, 256, amplitudes=(0.08, 0.04, 0.02, 0.01, 0.005, 0.0025))
    r_ratio = eigen_textures(x, PcaConfig(ratio=0.999, max_error=None)).rank
    r_error = eigen_textures(x, PcaConfig(ratio=None, max_error=2.0)).rank
    both = eigen_textures(x, PcaConfig(ratio=0.999, max_error=2.0)).rank
    np.testing.assert_array_equal(both, np.minimum(r_ratio, r_error))
    assert (r_ratio != r_error).any()


@pytest.mark.parametrize("precision", PRECISIONS)
def test_fixed_rank_and_max_rank(precision):
    x = low_rank(np.random.default_rng(6), 4, 16, 128, amplitudes=(0.1, 0.05, 0.02))  # numerical rank 3
    assert (eigen_textures(x, PcaConfig(precision=precision, fixed_rank=2)).rank == 2).all()
    assert (eigen_textures(x, PcaConfig(precision=precision, fixed_rank=0)).rank == 0).all()
    assert (eigen_textures(x, PcaConfig(precision=precision, fixed_rank=5)).rank == 3).all()  # numerical rank caps
    assert (eigen_textures(x, PcaConfig(precision=precision, max_rank=1, **ALL)).rank == 1).all()
    assert (eigen_textures(x, PcaConfig(precision=precision, max_rank=0, **ALL)).rank == 0).all()
    full = eigen_textures(x, PcaConfig(precision=precision, **ALL))
    assert (full.rank == 3).all()
    np.testing.assert_allclose(full.reconstruct(), x, rtol=0, atol=ATOL[precision][0])


def test_choose_rank_on_known_eigenvalues():
    lam = np.array([[4.0, 3.0, 2.0, 1.0, 0.0]])  # total 10; residual energies 10, 6, 3, 1, 0
    def rank(num_values=100, **kw):
        return int(choose_rank(lam, num_values, PcaConfig(**kw))[0])
    assert rank(ratio=0.65, max_error=None) == 2  # 4 + 3 ≥ 6.5
    assert rank(ratio=0.4, max_error=None) == 1
    assert rank(ratio=1.0, max_error=None) == 4  # never the zero eigenvalue
    # error bound: √(residual / num_values)·255 ≤ e; with num_values = 255² the error is √residual
    assert rank(255 ** 2, ratio=None, max_error=2.5) == 1  # √6 ≈ 2.45
    assert rank(255 ** 2, ratio=None, max_error=1.0) == 3  # √1
    assert rank(255 ** 2, ratio=None, max_error=3.2) == 0  # √10 ≈ 3.16: the mean is enough
    assert rank(255 ** 2, ratio=0.95, max_error=2.5) == 1  # the smaller of 4 and 1
    assert rank(ratio=None, max_error=None) == 4
    assert rank(ratio=None, max_error=None, max_rank=2) == 2
    assert rank(fixed_rank=3) == 3
    assert choose_rank(np.zeros((0, 5)), 100).shape == (0,)


def test_choose_rank_numerical_rank_and_zero_variance():
    rank = lambda lam, **kw: choose_rank(np.array([lam]), 1000, PcaConfig(ratio=None, max_error=None, **kw))[0]
    assert rank([1.0, 1e-12, -1e-15]) == 1  # round-off eigenvalues never count, negative ones neither
    assert rank([1.0, 1e-7]) == 2
    assert rank([1.0, 1e-7], precision="float32") == 1  # a float32 Gram cannot resolve that
    assert rank([1.0, 1e-7], fixed_rank=2) == 2
    assert rank([1.0, 1e-12], fixed_rank=2) == 1
    assert rank([0.0, 0.0]) == 0
    tiny = 0.5 * TOL.zero_rms ** 2 * 1000  # below the zero-variance energy
    assert rank([tiny, tiny / 10]) == 0
    assert choose_rank(np.array([[tiny * 4, 0.0]]), 1000, PcaConfig(**ALL), scale=1.0)[0] == 1
    assert choose_rank(np.array([[tiny * 4, 0.0]]), 1000, PcaConfig(**ALL), scale=10.0)[0] == 0  # relative to scale


def test_config_validation():
    for bad in [dict(ratio=0.0), dict(ratio=1.5), dict(max_error=-1.0), dict(max_error=math.inf), dict(max_rank=-1),
                dict(fixed_rank=-1), dict(fixed_rank=17), dict(chunk=0), dict(precision="float16")]:
        with pytest.raises(ValueError):
            PcaConfig(**bad)
    PcaConfig(fixed_rank=20, max_rank=20)


# --- stiff cases -------------------------------------------------------------------------------------


@pytest.mark.parametrize("precision", PRECISIONS)
def test_constant_textures_have_rank_zero_and_the_exact_mean(precision):
    rng = np.random.default_rng(7)
    texture = rng.random((3, 1, 256), dtype=np.float32)  # varies over texels, not over views
    x = np.concatenate([np.repeat(texture, 32, axis=1), np.full((1, 32, 256), 1 / 3, np.float32),
                        np.zeros((1, 32, 256), np.float32), np.ones((1, 32, 256), np.float32)])
    for config in [PcaConfig(precision=precision), PcaConfig(precision=precision, **ALL),
                   PcaConfig(precision=precision, fixed_rank=4)]:
        et = eigen_textures(x, config)
        assert_valid(et, 6, 32, 256)
        assert (et.rank == 0).all() and et.basis.shape[1] == 0
        np.testing.assert_array_equal(et.mean, x[:, 0])
        np.testing.assert_array_equal(et.reconstruct(), x)
        np.testing.assert_array_equal(et.rms_error(x), 0.0)
    ref = eigen_textures_reference(x, PcaConfig(**ALL))
    assert (ref.rank == 0).all()


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("d", [7, 32])  # d = 7: the float64 mean of equal values is not exact
def test_one_valid_view(precision, d):
    rng = np.random.default_rng(8)
    x = np.full((3, d, 64), np.nan, np.float32)
    x[0, 3] = rng.random(64)
    x[1, 0] = 0.1
    x[2, d - 1] = rng.random(64)
    x[2, d - 1, :5] = np.nan  # texels no view saw: mean 0
    et = eigen_textures(x, PcaConfig(precision=precision, **ALL))
    assert_valid(et, 3, d, 64)
    assert (et.rank == 0).all()
    np.testing.assert_allclose(et.mean[0], x[0, 3], rtol=1e-7, atol=0)
    np.testing.assert_allclose(et.mean[1], 0.1, rtol=1e-7, atol=0)
    np.testing.assert_array_equal(et.mean[2, :5], 0.0)
    np.testing.assert_allclose(et.mean[2, 5:], x[2, d - 1, 5:], rtol=1e-7, atol=0)
    assert (et.rms_error(x) < 1e-7).all()
    assert (eigen_textures_reference(x, PcaConfig(**ALL)).rank == 0).all()


@pytest.mark.parametrize("precision", PRECISIONS)
def test_duplicated_views(precision):
    rng = np.random.default_rng(9)
    x = np.repeat(rng.random((4, 1, 256), dtype=np.float32), 16, axis=1)
    x[np.arange(4), [0, 5, 15, 8]] = rng.random((4, 256), dtype=np.float32)  # one view differs
    x[3, 8] = x[3, 0] + np.float32(1e-3)  # ... here only slightly
    assert (eigen_textures(x, PcaConfig(precision=precision)).rank <= 1).all()
    et = eigen_textures(x, PcaConfig(precision=precision, **ALL))
    assert_valid(et, 4, 16, 256)
    np.testing.assert_array_equal(et.rank, 1)
    np.testing.assert_allclose(et.reconstruct(), x, rtol=0, atol=ATOL[precision][0])
    assert orthonormality_error(et) <= ATOL[precision][1]


@pytest.mark.parametrize("precision", PRECISIONS)
def test_rank_deficient_stack_from_two_components(precision):
    x = low_rank(np.random.default_rng(10), 5, 32, 256, amplitudes=(0.1, 0.01))
    assert (eigen_textures(x, PcaConfig(precision=precision)).rank <= 2).all()
    for config in [PcaConfig(precision=precision, **ALL), PcaConfig(precision=precision, ratio=None, max_error=1e-3)]:
        et = eigen_textures(x, config)
        assert_valid(et, 5, 32, 256)
        np.testing.assert_array_equal(et.rank, 2)
        np.testing.assert_allclose(et.reconstruct(), x, rtol=0, atol=ATOL[precision][0])
        assert orthonormality_error(et) <= ATOL[precision][1]


@pytest.mark.parametrize("precision", PRECISIONS)
def test_missing_texels_and_views(precision):
    rng = np.random.default_rng(11)
    full = low_rank(rng, 4, 16, 256)
    x = full.copy()
    x[rng.random(x.shape) < 0.3] = np.nan  # 30 % missing texels
    x[0, 4] = np.nan  # a whole view missing
    x[1, :, :10] = np.nan  # texels no view saw
    x[3] = np.nan  # a billboard no view saw
    et = eigen_textures(x, PcaConfig(precision=precision))
    assert_valid(et, 4, 16, 256)
    with warnings.catch_warnings():  # nanmean of the all-NaN texels warns
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = np.nan_to_num(np.nanmean(x.astype(np.float64), axis=1), nan=0.0)
    np.testing.assert_allclose(et.mean, expected, rtol=0, atol=1e-6)
    assert et.rank[3] == 0 and not et.mean[3].any()
    assert np.isfinite(et.rms_error(x)).all()
    ref = eigen_textures_reference(x, PcaConfig())
    np.testing.assert_array_equal(et.rank, ref.rank)
    np.testing.assert_allclose(et.reconstruct(), ref.reconstruct(), rtol=0, atol=ATOL[precision][0])


@pytest.mark.parametrize("precision", PRECISIONS)
def test_values_at_and_near_the_ends_of_the_range(precision):
    rng = np.random.default_rng(12)
    x = np.zeros((4, 16, 256), np.float32)
    x[0] = rng.random((16, 256)) < 0.5  # binary texels, exactly 0 and 1, switching with the view
    x[1] = np.where(rng.random((16, 256)) < 0.5, np.float32(254.9 / 255), np.float32(1.0))  # saturated
    x[2] = np.where(rng.random((16, 256)) < 0.5, np.float32(0.1 / 255), np.float32(0.0))  # black
    x[3] = np.float32(1.0)
    x[3, 3, 17] = np.float32(254 / 255)  # one texel of one view differs by one 8-bit level
    et = eigen_textures(x, PcaConfig(precision=precision))
    ref = eigen_textures_reference(x, PcaConfig())
    assert_valid(et, 4, 16, 256)
    np.testing.assert_array_equal(et.rank, ref.rank)
    np.testing.assert_allclose(et.reconstruct(), ref.reconstruct(), rtol=0, atol=ATOL[precision][0])
    assert (et.rms_error(x)[1:] * 255 <= 2.0 * (1 + 1e-4)).all()
    assert et.rank[2] == 0  # variation far below an 8-bit level: the mean suffices
    assert et.rank[3] == 0  # one level in one texel: RMS 0.016 levels
    exact = eigen_textures(x, PcaConfig(precision=precision, **ALL))
    assert exact.rank[3] == 1
    np.testing.assert_allclose(exact.reconstruct()[3], x[3], rtol=0, atol=ATOL[precision][0])


@pytest.mark.parametrize("precision", PRECISIONS)
def test_tiny_number_of_views(precision):
    rng = np.random.default_rng(13)
    one = rng.random((3, 1, 64), dtype=np.float32)
    et = eigen_textures(one, PcaConfig(precision=precision, **ALL))
    assert_valid(et, 3, 1, 64)
    assert (et.rank == 0).all()
    np.testing.assert_array_equal(et.mean, one[:, 0])
    two = rng.random((3, 2, 64), dtype=np.float32)
    two[2, 1] = two[2, 0]
    et = eigen_textures(two, PcaConfig(precision=precision, **ALL))
    assert_valid(et, 3, 2, 64)
    np.testing.assert_array_equal(et.rank, [1, 1, 0])
    np.testing.assert_allclose(et.reconstruct(), two, rtol=0, atol=ATOL[precision][0])


@pytest.mark.parametrize("precision", PRECISIONS)
def test_empty_batch(precision):
    for config in [PcaConfig(precision=precision), PcaConfig(precision=precision, chunk=1)]:
        et = eigen_textures(np.zeros((0, 32, 256), np.float32), config)
        assert_valid(et, 0, 32, 256)
        assert et.reconstruct().shape == (0, 32, 256)
        assert et.rms_error(np.zeros((0, 32, 256))).shape == (0,)
    assert_valid(eigen_textures_reference(np.zeros((0, 32, 256)), PcaConfig()), 0, 32, 256)


@pytest.mark.parametrize("precision", PRECISIONS)
def test_large_values_do_not_overflow(precision):
    x = low_rank(np.random.default_rng(14), 3, 16, 256) * np.float32(0.9 * TOL.max_abs_value)
    et = eigen_textures(x, PcaConfig(precision=precision, **ALL))
    assert_valid(et, 3, 16, 256)
    np.testing.assert_allclose(et.reconstruct(), x, rtol=0, atol=ATOL[precision][0] * TOL.max_abs_value)


@pytest.mark.parametrize("precision", PRECISIONS)
def test_invalid_samples_raise(precision):
    config = PcaConfig(precision=precision)
    x = np.full((3, 8, 16), 0.5, np.float32)
    for value in [np.inf, -np.inf, 2 * TOL.max_abs_value, np.finfo(np.float32).max]:
        bad = x.copy()
        bad[1, 2, 3] = value
        with pytest.raises(ValueError, match="billboard 1"):
            eigen_textures(bad, config)
        with pytest.raises(ValueError, match="billboard 2"):
            eigen_textures(np.concatenate([x[:2], bad[1:2]]), PcaConfig(precision=precision, chunk=1))
    for bad in [np.zeros((8, 16), np.float32), np.zeros((3, 8, 16), np.uint8), np.zeros((3, 8, 16), np.float16),
                np.zeros((3, 0, 16), np.float32)]:
        with pytest.raises(ValueError):
            eigen_textures(bad, config)


def test_rms_error_leaves_out_missing_values():
    x = low_rank(np.random.default_rng(15), 3, 8, 64)
    et = eigen_textures(x, PcaConfig(fixed_rank=1))
    err = et.rms_error(x)
    x_missing = x.copy()
    x_missing[2] = np.nan
    np.testing.assert_allclose(et.rms_error(x_missing), [err[0], err[1], 0.0], rtol=1e-12)
    diff = et.reconstruct().astype(np.float64) - x
    np.testing.assert_allclose(err, np.sqrt(np.mean(diff ** 2, axis=(1, 2))), rtol=1e-12)
    with pytest.raises(ValueError):
        et.rms_error(x[:2])


# --- psnr ----------------------------------------------------------------------------------------


def test_psnr_known_values():
    a = np.zeros((4, 4, 3))
    assert psnr(a, a + 0.1) == pytest.approx(20.0)
    assert psnr(a, a + 0.01) == pytest.approx(40.0)
    assert psnr(a * 255, a * 255 + 1.0, peak=255.0) == pytest.approx(20 * math.log10(255.0))  # 48.13 dB
    assert psnr(a, a) == TOL.psnr_max_db  # identical: capped, finite
    assert psnr(a, a + 1e-9) == TOL.psnr_max_db
    assert math.isnan(psnr(np.zeros(0), np.zeros(0)))
    mask = np.zeros((4, 4), bool)
    assert math.isnan(psnr(a, a + 0.1, mask=mask))
    mask[0] = True
    b = a + 0.5
    b[0] = 0.1
    assert psnr(a, b, mask=mask) == pytest.approx(20.0)  # an (h, w) mask for (h, w, 3) images
    assert psnr(a, b, mask=mask[:, :, None]) == pytest.approx(20.0)
    b = a + 0.1
    b[1, 1, 1] = np.nan  # missing values are left out
    assert psnr(a, b) == pytest.approx(20.0)
