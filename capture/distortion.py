"""Lens distortion: OpenCV's radial-tangential and fisheye models.

A camera's raw image is distorted; everything downstream of
:meth:`capture.dataset.Dataset.image` sees an undistorted pinhole image of the same
size. This module holds the lens models and the undistortion maps.

Normalised coordinates are those of the camera frame divided by z: a pinhole
camera maps them to pixels with K. ``distort`` takes undistorted normalised
coordinates (where the ray really points) to distorted ones (``K_raw⁻¹`` of the
raw pixel); ``undistort`` inverts it.

Models (OpenCV's, coefficient order as its functions take them):

* ``radtan`` (``cv2.undistort``, ``cv2.projectPoints``): k1, k2, p1, p2, k3 —
  r² = x² + y², radial = 1 + k1 r² + k2 r⁴ + k3 r⁶,
  x_d = x·radial + 2 p1 x y + p2 (r² + 2x²), y_d = y·radial + p1 (r² + 2y²) + 2 p2 x y.
* ``fisheye`` (``cv2.fisheye``, equidistant / Kannala–Brandt): k1, k2, k3, k4 —
  θ = atan(r), θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), x_d = (θ_d / r)·x.

The undistorted image's pinhole K (:func:`pinhole_for`) keeps the raw principal
point and the raw fx : fy aspect and takes the smallest focal for which every
pixel of the undistorted image samples inside the raw image: no invalid
border, for both models (OpenCV's ``alpha = 0`` / fisheye ``balance = 0`` in
spirit, but solved exactly over the whole image border, so it holds for strong
fisheye lenses where OpenCV's edge-midpoint estimate does not).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError

MODELS = ("radtan", "fisheye")
#: Coefficient names of each model, in OpenCV's order (also their rig.json keys).
COEFFICIENTS = {"radtan": ("k1", "k2", "p1", "p2", "k3"), "fisheye": ("k1", "k2", "k3", "k4")}
#: Coefficients that rig.json may leave out (taken as 0).
OPTIONAL = {"radtan": ("k3",), "fisheye": ()}

#: Named lenses (the names the synthetic rig's ``RigConfig.distortion`` takes). radtan: a mild
#: barrel lens whose radial function stays monotonic far past the default camera's corners
#: (r ≈ 3.2); fisheye: a typical Kannala–Brandt calibration of an equidistant lens.
PRESETS = {
    "radtan": {"k1": -0.03, "k2": 0.0015, "p1": 2e-4, "p2": -1e-4, "k3": 0.0},
    "fisheye": {"k1": 0.02, "k2": -0.006, "k3": 0.001, "k4": -1e-4},
}

#: Newton iterations of :func:`undistort` at most; points not converged by then are NaN.
UNDISTORT_ITERATIONS = 50
#: Residual (normalised units) below which :func:`undistort` counts a point as converged.
UNDISTORT_TOLERANCE = 1e-13


@dataclass(frozen=True)
class Distortion:
    """One camera's lens distortion: ``model`` in MODELS, ``coeffs`` in OpenCV order
    (radtan: k1, k2, p1, p2, k3; fisheye: k1, k2, k3, k4), finite floats."""

    model: str
    coeffs: tuple[float, ...]
    # radius of validity (cached): beyond it the radial function is no longer monotonic
    _limit: float = field(default=0.0, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.model not in MODELS:
            raise InputError(f"unknown distortion model {self.model!r} (expected one of {', '.join(MODELS)})")
        names = COEFFICIENTS[self.model]
        coeffs = tuple(self.coeffs)
        if len(coeffs) != len(names):
            raise InputError(f"{self.model} takes {len(names)} coefficients ({', '.join(names)}), got {len(coeffs)}")
        for name, c in zip(names, coeffs):
            if isinstance(c, bool) or not isinstance(c, (int, float, np.floating, np.integer)) or not math.isfinite(c):
                raise InputError(f"{self.model} coefficient {name} must be a finite number, got {c!r}")
        object.__setattr__(self, "coeffs", tuple(float(c) for c in coeffs))
        object.__setattr__(self, "_limit", _valid_limit(self.model, self.coeffs))
        if self._limit < 0.1:  # folds back right at the centre: no usable image
            raise InputError(f"the {self.model} lens is not monotonic even near the image centre (no usable image)")

    @classmethod
    def preset(cls, name: str) -> "Distortion":
        """A named lens of :data:`PRESETS`."""
        if name not in PRESETS:
            raise InputError(f"unknown distortion preset {name!r} (expected one of {', '.join(PRESETS)})")
        return cls(name, tuple(PRESETS[name][k] for k in COEFFICIENTS[name]))

    @property
    def opencv(self) -> np.ndarray:
        """(5,) float64 radtan or (4,) float64 fisheye coefficients, as cv2 takes them."""
        return np.array(self.coeffs, dtype=np.float64)

    @property
    def valid_radius(self) -> float:
        """Undistorted normalised radius up to which the model is monotonic (inf: everywhere);
        radtan in r, fisheye in tan θ (θ < 90°)."""
        return self._limit

    def to_json(self) -> dict:
        """The rig.json object: {"model": ..., "k1": ..., ...} (radtan always writes k3)."""
        return {"model": self.model, **dict(zip(COEFFICIENTS[self.model], self.coeffs))}

    @classmethod
    def from_json(cls, value, path: os.PathLike | str, where: str) -> "Distortion | None":
        """Parse a rig.json ``distortion`` entry: "none" → None, or a model object.

        Errors raise :class:`DataFormatError` naming ``path`` and ``where`` (e.g. "cameras[1].distortion").
        """
        path = Path(path)
        if value == "none":
            return None
        if not isinstance(value, dict):
            raise DataFormatError(path, f"{where} must be \"none\" or an object with a \"model\", got {value!r}")
        model = value.get("model")
        if model not in MODELS:
            raise DataFormatError(path, f"{where}.model {model!r} is not one of {', '.join(MODELS)}")
        names = COEFFICIENTS[model]
        unknown = sorted(set(value) - set(names) - {"model"})
        if unknown:
            raise DataFormatError(path, f"{where} has unknown keys {', '.join(unknown)} for model {model} "
                                        f"(takes {', '.join(names)})")
        missing = [k for k in names if k not in value and k not in OPTIONAL[model]]
        if missing:
            raise DataFormatError(path, f"{where} lacks {', '.join(missing)} (model {model})")
        coeffs = []
        for k in names:
            c = value.get(k, 0.0)
            if isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c):
                raise DataFormatError(path, f"{where}.{k} must be a finite number, got {c!r}")
            coeffs.append(float(c))
        try:
            return cls(model, tuple(coeffs))
        except ValueError as e:
            raise DataFormatError(path, f"{where}: {e}") from None


def _radial_derivative(model: str, c: tuple[float, ...], s: np.ndarray) -> np.ndarray:
    """d(distorted radius)/d(undistorted radius) along a ray, ignoring tangential terms.
    radtan: s = r; fisheye: s = θ (then d θ_d / d θ)."""
    if model == "radtan":
        k1, k2, _, _, k3 = c
        r2 = s * s
        return 1 + 3 * k1 * r2 + 5 * k2 * r2 ** 2 + 7 * k3 * r2 ** 3
    k1, k2, k3, k4 = c
    t2 = s * s
    return 1 + 3 * k1 * t2 + 5 * k2 * t2 ** 2 + 7 * k3 * t2 ** 3 + 9 * k4 * t2 ** 4


def _valid_limit(model: str, c: tuple[float, ...]) -> float:
    """First radius where the radial function stops increasing (inf if it never does in range)."""
    if model == "radtan":
        s = np.linspace(0.0, 50.0, 200001)  # r up to 50 (88.9° off axis), steps of 2.5e-4
    else:
        s = np.linspace(0.0, np.pi / 2, 200001)[:-1]  # θ below 90°
    bad = np.flatnonzero(_radial_derivative(model, c, s) <= 0)
    if not len(bad):
        return float("inf")
    limit = s[max(bad[0] - 1, 0)]
    return float(limit if model == "radtan" else np.tan(limit))


# --------------------------------------------------------------------------- point maps


def _check_points(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise InputError(f"points must be (n, 2), got {xy.shape}")
    return xy


def distort(xy: np.ndarray, distortion: Distortion) -> np.ndarray:
    """Distorted normalised coordinates (n, 2) float64 of undistorted ones ``xy`` (n, 2) float64.

    Vectorised twin of :func:`distort_reference`; agrees with ``cv2.projectPoints`` /
    ``cv2.fisheye.distortPoints``. Points beyond ``distortion.valid_radius`` are mapped
    all the same (the model is only invertible inside it).
    """
    xy = _check_points(xy)
    x, y = xy[:, 0], xy[:, 1]
    c = distortion.coeffs
    if distortion.model == "radtan":
        k1, k2, p1, p2, k3 = c
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return np.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                         y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], axis=-1)
    k1, k2, k3, k4 = c
    r = np.hypot(x, y)
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 1e-12, theta_d / r, 1.0)  # θ_d / r → 1 at the centre
    return xy * scale[:, None]


def distort_reference(xy: np.ndarray, distortion: Distortion) -> np.ndarray:
    """Slow, obvious twin of :func:`distort`: one point at a time in plain floats (for tests)."""
    out = []
    for x, y in _check_points(xy).tolist():
        if distortion.model == "radtan":
            k1, k2, p1, p2, k3 = distortion.coeffs
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
            out.append((x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y))
        else:
            k1, k2, k3, k4 = distortion.coeffs
            r = math.hypot(x, y)
            if r == 0:
                out.append((x, y))
                continue
            t = math.atan(r)
            td = t * (1 + k1 * t ** 2 + k2 * t ** 4 + k3 * t ** 6 + k4 * t ** 8)
            out.append((x * td / r, y * td / r))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def undistort(xy: np.ndarray, distortion: Distortion) -> np.ndarray:
    """Undistorted normalised coordinates (n, 2) float64 of distorted ones ``xy`` (n, 2) float64.

    Newton's method in float64 (radtan: on the 2-D map with its Jacobian; fisheye: on
    θ_d(θ)), up to UNDISTORT_ITERATIONS steps; ``distort(undistort(p))`` equals ``p`` to
    about 1e-15. NaN where no undistorted point inside ``distortion.valid_radius`` maps to
    ``xy`` (outside a strong lens's image circle, or where the model folds back).
    """
    xy = _check_points(xy)
    if distortion.model == "radtan":
        return _undistort_radtan(xy, distortion)
    return _undistort_fisheye(xy, distortion)


def _undistort_radtan(xd: np.ndarray, d: Distortion) -> np.ndarray:
    k1, k2, p1, p2, k3 = d.coeffs
    p = xd.copy()  # distortion is mild near the centre: start at the distorted point
    active = np.arange(len(p))
    for _ in range(UNDISTORT_ITERATIONS):
        if not len(active):
            break
        x, y = p[active, 0], p[active, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        g = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r²
        fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd[active, 0]
        fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - xd[active, 1]
        done = np.maximum(np.abs(fx), np.abs(fy)) <= 1e-15 * (1 + np.abs(xd[active, 0]) + np.abs(xd[active, 1]))
        keep = ~done  # NaN residuals stay, and fail the final check
        active, x, y, r2, radial, g, fx, fy = (a[keep] for a in (active, x, y, r2, radial, g, fx, fy))
        a = radial + 2 * g * x * x + 2 * p1 * y + 6 * p2 * x
        b = 2 * g * x * y + 2 * p1 * x + 2 * p2 * y  # ∂x_d/∂y = ∂y_d/∂x
        e = radial + 2 * g * y * y + 6 * p1 * y + 2 * p2 * x
        det = a * e - b * b
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            p[active, 0] = x - (e * fx - b * fy) / det
            p[active, 1] = y - (a * fy - b * fx) / det
    return _keep_converged(p, xd, d)


def _undistort_fisheye(xd: np.ndarray, d: Distortion) -> np.ndarray:
    k1, k2, k3, k4 = d.coeffs
    theta_d = np.hypot(xd[:, 0], xd[:, 1])
    theta = theta_d.copy()
    for _ in range(UNDISTORT_ITERATIONS):
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        with np.errstate(divide="ignore", invalid="ignore"):
            step = f / df
        theta = np.clip(theta - step, 0.0, np.pi / 2)
        if not np.any(np.abs(step) > 1e-16 * (1 + theta)):
            break
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(theta_d > 1e-12, np.tan(theta) / theta_d, 1.0)
    return _keep_converged(xd * scale[:, None], xd, d)


def _keep_converged(p: np.ndarray, xd: np.ndarray, d: Distortion) -> np.ndarray:
    """NaN where ``p`` is not a true preimage of ``xd`` inside the model's valid radius."""
    with np.errstate(invalid="ignore", over="ignore"):
        r = np.hypot(p[:, 0], p[:, 1])
        residual = np.abs(distort(np.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0), d) - xd).max(axis=1)
        ok = np.isfinite(r) & (r <= d.valid_radius) & (residual <= UNDISTORT_TOLERANCE * (1 + np.hypot(xd[:, 0], xd[:, 1])))
    p[~ok] = np.nan
    return p


# --------------------------------------------------------------------------- images


def _border_pixels(size: tuple[int, int]) -> np.ndarray:
    """(m, 2) float64 pixel centres on the border of a width × height image."""
    w, h = size
    u, v = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    return np.concatenate([np.stack([u, np.zeros(w)], -1), np.stack([u, np.full(w, h - 1.0)], -1),
                           np.stack([np.zeros(h), v], -1), np.stack([np.full(h, w - 1.0), v], -1)])


def pinhole_for(K_raw: np.ndarray, distortion: Distortion, size: tuple[int, int]) -> np.ndarray:
    """(3, 3) float64 K of the undistorted image (same ``size`` (width, height) as the raw one).

    Keeps the raw principal point and fx : fy, and scales the focal lengths by the smallest
    factor for which every border pixel of the undistorted image maps inside the raw image
    (pixel centres in [0, w−1] × [0, h−1]): no invalid border (bisection, 60 halvings).
    """
    K_raw = np.asarray(K_raw, dtype=np.float64)
    w, h = size
    q = _border_pixels(size)
    c = K_raw[[0, 1], [2, 2]]
    f = K_raw[[0, 1], [0, 1]]

    def inside(scale: float) -> bool:
        xu = (q - c) / (f * scale)
        if np.any(np.hypot(xu[:, 0], xu[:, 1]) > distortion.valid_radius):
            return False
        raw = distort(xu, distortion) * f + c
        return bool(np.all((raw >= -1e-9).all(axis=1) & (raw[:, 0] <= w - 1 + 1e-9) & (raw[:, 1] <= h - 1 + 1e-9)))

    lo, hi = -12.0, 12.0  # log2 of the scale
    if not inside(2.0 ** hi):
        raise InputError("no pinhole camera fits inside the raw image (principal point outside it?)")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside(2.0 ** mid) else (mid, hi)
    s = 2.0 ** hi
    return np.array([[f[0] * s, 0.0, c[0]], [0.0, f[1] * s, c[1]], [0.0, 0.0, 1.0]])


def undistort_maps(K_raw: np.ndarray, distortion: Distortion, size: tuple[int, int]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The undistorted camera and its remap tables.

    K_raw: (3, 3) float64 of the raw (distorted) image; size: (width, height) of both images.
    Returns K_pinhole (3, 3) float64 (:func:`pinhole_for`) and map_x, map_y (h, w) float32:
    the raw pixel that each undistorted pixel samples (``cv2.remap(raw, map_x, map_y, ...)``),
    from ``cv2.initUndistortRectifyMap`` / ``cv2.fisheye.initUndistortRectifyMap``.
    """
    K_raw = np.asarray(K_raw, dtype=np.float64)
    K = pinhole_for(K_raw, distortion, size)
    size = (int(size[0]), int(size[1]))
    if distortion.model == "radtan":
        mx, my = cv2.initUndistortRectifyMap(K_raw, distortion.opencv, None, K, size, cv2.CV_32FC1)
    else:
        mx, my = cv2.fisheye.initUndistortRectifyMap(K_raw, distortion.opencv, np.eye(3), K, size, cv2.CV_32FC1)
    return K, mx, my


def undistort_maps_reference(K_raw: np.ndarray, distortion: Distortion, size: tuple[int, int]
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twin of :func:`undistort_maps` from :func:`distort` (float64 maps), for tests."""
    K_raw = np.asarray(K_raw, dtype=np.float64)
    K = pinhole_for(K_raw, distortion, size)
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xu = np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1]], -1)
    raw = distort(xu, distortion) * K_raw[[0, 1], [0, 1]] + K_raw[[0, 1], [2, 2]]
    return K, raw[:, 0].reshape(h, w), raw[:, 1].reshape(h, w)


@dataclass(frozen=True, eq=False)
class UndistortTables:
    """K (3, 3) float64 pinhole of the undistorted image; map_x, map_y (h, w) float32 raw pixel
    sampled per undistorted pixel; nearest (h, w) int64 flat index of the nearest raw pixel."""

    K: np.ndarray
    map_x: np.ndarray
    map_y: np.ndarray
    nearest: np.ndarray

    def image(self, raw: np.ndarray) -> np.ndarray:
        """Undistort an image (h, w[, 3]) uint8 (bilinear; edges replicated)."""
        return cv2.remap(raw, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def nearest_values(self, raw: np.ndarray) -> np.ndarray:
        """Undistort a per-pixel array (h, w) of any dtype by nearest raw pixel (depth, ids)."""
        return raw.reshape(-1)[self.nearest]


_TABLES: dict[tuple, UndistortTables] = {}
_TABLES_MAX = 16  # cameras kept per process (about 5 MB each at 416×736)


def cached_tables(K_raw: np.ndarray, distortion: Distortion, size: tuple[int, int]) -> UndistortTables:
    """:func:`undistort_maps` computed once per process and camera (keyed by raw K, lens and size)."""
    K_raw = np.ascontiguousarray(K_raw, dtype=np.float64)
    size = (int(size[0]), int(size[1]))
    key = (K_raw.tobytes(), distortion, size)
    tables = _TABLES.get(key)
    if tables is None:
        K, mx, my = undistort_maps(K_raw, distortion, size)
        w, h = size
        ix = np.clip(np.rint(mx), 0, w - 1).astype(np.int64)
        iy = np.clip(np.rint(my), 0, h - 1).astype(np.int64)
        for a in (K, mx, my):
            a.setflags(write=False)
        nearest = iy * w + ix
        nearest.setflags(write=False)
        if len(_TABLES) >= _TABLES_MAX:
            _TABLES.clear()
        tables = _TABLES[key] = UndistortTables(K, mx, my, nearest)
    return tables
