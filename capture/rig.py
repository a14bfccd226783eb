"""Calibrated cameras of a rig, and ``rig.json``.

Rig frame: x forward (the driving direction), y left, z up: the project's axes, into which
the importers bring their captures; ``cam_from_rig`` fixes each camera in it. Camera frames
follow OpenCV (x right, y down, z forward), pixel centres at integer coordinates.

Lens distortion (:mod:`capture.distortion`): a rig may hold raw, distorted
cameras. ``Rig.intrinsics`` are always the pinhole matrices of the undistorted
images that ``Dataset.image`` returns; the raw K and the lens are kept beside
them so that ``rig.json`` round-trips.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, as_matrix, check_rigid, read_json, write_json

from .distortion import Distortion, UndistortTables, cached_tables, pinhole_for

RIG_FORMAT = "bbcity-rig"
#: Version of ``rig.json`` and ``poses.json``.
FORMAT_VERSION = 1


#: A focal length lies within this factor of its image edge (pixels), either way.
FOCAL_RANGE = 1000.0
#: How much narrower than the raw image a lens's undistorted pinhole image may be (fisheye
#: k1 = 100 makes it 6×; k1 = 1e6, 126×: a reconstruction then sees nothing).
MAX_UNDISTORT_ZOOM = 20.0
#: The camera models rig.json knows: the pinhole model (a lens goes in "distortion").
CAMERA_MODELS = ("pinhole",)
#: How far outside its image a principal point may lie, in image widths (cx) or heights (cy).
PRINCIPAL_POINT_RANGE = 1.0


def is_int(value) -> bool:
    """An integer (Python or numpy), not a bool (JSON ``true`` would pass as 1)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class Rig:
    """Calibrated cameras of a rig.

    intrinsics: (c, 3, 3) float64 OpenCV pinhole matrices (pixel centres at integers) of the
        images downstream stages see (the undistorted ones where a camera has a lens distortion).
    sizes: c × (width, height) in pixels (raw and undistorted images alike).
    cam_from_rig: (c, 4, 4) float64 rigid transforms.
    raw_intrinsics: (c, 3, 3) float64 K of the raw, distorted images, or None when no camera
        is distorted (then the raw images are the pinhole images).
    distortions: c × (Distortion or None), or None when no camera is distorted.
    Build distorted rigs with :meth:`from_raw`.
    """

    intrinsics: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    cam_from_rig: np.ndarray
    raw_intrinsics: np.ndarray | None = None
    distortions: tuple[Distortion | None, ...] | None = None

    def __post_init__(self):
        if (self.raw_intrinsics is None) != (self.distortions is None):
            raise InputError("raw_intrinsics and distortions go together (use Rig.from_raw)")
        if self.distortions is not None and (len(self.distortions) != len(self.sizes)
                                             or len(self.raw_intrinsics) != len(self.sizes)):
            raise InputError(f"{len(self.sizes)} cameras but {len(self.distortions)} distortions "
                             f"and {len(self.raw_intrinsics)} raw intrinsics")

    @classmethod
    def from_raw(cls, raw_intrinsics: np.ndarray, sizes, cam_from_rig: np.ndarray,
                 distortions) -> "Rig":
        """A rig from its raw cameras: K (c, 3, 3) float64 and a Distortion or None each.

        The pinhole ``intrinsics`` of distorted cameras are those of their undistorted images
        (:func:`capture.distortion.pinhole_for`). Without any distortion this is the plain rig.
        """
        raw = np.asarray(raw_intrinsics, dtype=np.float64)
        sizes = tuple((int(w), int(h)) for w, h in sizes)
        distortions = tuple(distortions)
        if all(d is None for d in distortions):
            return cls(raw, sizes, np.asarray(cam_from_rig, dtype=np.float64))
        Ks = np.array([K if d is None else pinhole_for(K, d, s) for K, d, s in zip(raw, distortions, sizes)])
        return cls(Ks, sizes, np.asarray(cam_from_rig, dtype=np.float64), raw, distortions)

    @property
    def num_cameras(self) -> int:
        return len(self.sizes)

    def distortion(self, cam: int) -> Distortion | None:
        """Lens distortion of camera ``cam``'s raw images (None: pinhole)."""
        return None if self.distortions is None else self.distortions[cam]

    def raw_K(self, cam: int) -> np.ndarray:
        """(3, 3) float64 K of camera ``cam``'s raw images (its pinhole K when undistorted)."""
        return self.intrinsics[cam] if self.raw_intrinsics is None else self.raw_intrinsics[cam]

    def undistort_tables(self, cam: int) -> UndistortTables | None:
        """Remap tables of camera ``cam`` (computed once per process and camera); None when pinhole."""
        d = self.distortion(cam)
        return None if d is None else cached_tables(self.raw_K(cam), d, self.sizes[cam])

    def undistort(self, raw: np.ndarray, cam: int, nearest: bool = False) -> np.ndarray:
        """Camera ``cam``'s raw image (h, w, 3) uint8 → the undistorted one (bilinear), or with
        ``nearest`` any per-pixel array (h, w) (depth, ids) by nearest raw pixel. A pinhole
        camera's array is returned as it is (no copy)."""
        tables = self.undistort_tables(cam)
        if tables is None:
            return raw
        return tables.nearest_values(raw) if nearest else tables.image(raw)

    def world_from_cam(self, world_from_rig: np.ndarray, cam: int) -> np.ndarray:
        """(4, 4) float64 pose of camera ``cam`` for a rig pose (4, 4) float64."""
        return world_from_rig @ np.linalg.inv(self.cam_from_rig[cam])

    def to_json(self) -> dict:
        cams = []
        for i, ((w, h), T) in enumerate(zip(self.sizes, self.cam_from_rig)):
            K, d = self.raw_K(i), self.distortion(i)  # rig.json holds the raw camera
            cams.append({
                "name": f"cam{i}", "model": "pinhole", "width": int(w), "height": int(h),
                "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                "distortion": "none" if d is None else d.to_json(), "cam_from_rig": T.tolist(),
            })
        return {"format": RIG_FORMAT, "version": FORMAT_VERSION, "pixel_centre": "integer (OpenCV)",
                "reference_camera": 0, "cameras": cams}

    def save(self, path: os.PathLike | str) -> Path:
        return write_json(path, self.to_json())

    @classmethod
    def load(cls, path: os.PathLike | str) -> "Rig":
        """Read and validate ``rig.json``; errors name the file and the field."""
        path = Path(path)
        data = read_json(path)
        if not isinstance(data, dict) or data.get("format") != RIG_FORMAT:
            raise DataFormatError(path, f"not a rig file (expected \"format\": \"{RIG_FORMAT}\")")
        if not is_int(data.get("version")) or data["version"] != FORMAT_VERSION:  # true == 1 in Python
            raise DataFormatError(path, f"unsupported version {data.get('version')!r}")
        cams = data.get("cameras")
        if not isinstance(cams, list) or not cams:
            raise DataFormatError(path, "\"cameras\" must be a non-empty list")
        _check_reference_camera(path, data.get("reference_camera", 0), len(cams))
        Ks, sizes, Ts, distortions = [], [], [], []
        for i, cam in enumerate(cams):
            where = f"cameras[{i}]"
            if not isinstance(cam, dict):
                raise DataFormatError(path, f"{where} is not an object")
            missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy", "cam_from_rig") if k not in cam]
            if missing:
                raise DataFormatError(path, f"{where} lacks {', '.join(missing)}")
            model = cam.get("model", "pinhole")  # hand-written files may leave it out
            if not isinstance(model, str) or model not in CAMERA_MODELS:
                raise DataFormatError(path, f"{where}.model {model!r} is not a camera model rig.json knows "
                                            f"({', '.join(CAMERA_MODELS)}; a lens goes in {where}.distortion)")
            distortions.append(Distortion.from_json(cam.get("distortion", "none"), path, f"{where}.distortion"))
            for name in ("width", "height"):
                v = cam[name]
                if not (is_int(v) and 0 < v <= 65536):  # JSON true would pass as 1
                    raise DataFormatError(path, f"{where}.{name} must be a positive integer ≤ 65536 "
                                                f"(image width/height in pixels), got {v!r}")
            w, h = cam["width"], cam["height"]
            f = as_matrix([cam["fx"], cam["fy"], cam["cx"], cam["cy"]], (4,), path, f"{where} intrinsics")
            if f[0] <= 0 or f[1] <= 0:
                raise DataFormatError(path, f"{where} focal lengths must be positive")
            for name, value, edge in (("fx", f[0], w), ("fy", f[1], h)):
                if not edge / FOCAL_RANGE <= value <= edge * FOCAL_RANGE:  # a 0.06° to 179.9° field of view
                    raise DataFormatError(path, f"{where}.{name} {value:g} px is not a lens's for a {edge}-px "
                                                f"image (expected {edge / FOCAL_RANGE:g} to {edge * FOCAL_RANGE:g})")
            _check_principal_point(path, where, f[2], f[3], w, h)
            Ks.append(np.array([[f[0], 0, f[2]], [0, f[1], f[3]], [0, 0, 1]]))
            sizes.append((w, h))
            Ts.append(check_rigid(as_matrix(cam["cam_from_rig"], (4, 4), path, f"{where}.cam_from_rig"),
                                  path, f"{where}.cam_from_rig"))
        try:
            rig = cls.from_raw(np.array(Ks), tuple(sizes), np.array(Ts), distortions)
        except ValueError as e:  # a lens that leaves no pinhole image inside the raw one
            raise DataFormatError(path, f"cannot undistort the cameras ({e})") from None
        for i, K in enumerate(Ks):
            zoom = rig.intrinsics[i][0, 0] / K[0, 0]
            if zoom > MAX_UNDISTORT_ZOOM:  # fisheye k1 = 1e6: the stages would see a few raw pixels
                raise DataFormatError(path, f"cameras[{i}].distortion leaves an undistorted image {zoom:.0f}× "
                                            f"narrower than the raw one (at most {MAX_UNDISTORT_ZOOM:g}×): "
                                            "coefficients no lens has")
        return rig


def _check_reference_camera(path: Path, ref, num_cameras: int) -> None:
    """DataFormatError naming ``path`` unless ``reference_camera`` ``ref`` is the index of
    one of the rig's ``num_cameras`` cameras (an integer, not a bool or a string)."""
    if not (is_int(ref) and 0 <= ref < num_cameras):
        raise DataFormatError(path, f"reference_camera must be an integer camera index 0 to {num_cameras - 1}, "
                                    f"got {ref!r}")


def _check_principal_point(path: Path, where: str, cx: float, cy: float, w: int, h: int) -> None:
    """DataFormatError naming ``path`` and ``where`` (``cameras[i]``) when the principal point
    (cx, cy) lies more than :data:`PRINCIPAL_POINT_RANGE` image widths (heights) outside the
    ``w`` × ``h`` image (pixel centres 0 to w − 1): no lens's, a K in other units or swapped."""
    for name, value, edge in (("cx", cx, w), ("cy", cy, h)):
        lo, hi = -0.5 - PRINCIPAL_POINT_RANGE * edge, edge - 0.5 + PRINCIPAL_POINT_RANGE * edge
        if not lo <= value <= hi:
            raise DataFormatError(path, f"{where}.{name} {value:g} px lies far outside the {w}x{h} image "
                                        f"(expected {lo:g} to {hi:g})")


def pinhole(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) float64 K with square pixels and the principal point at the image centre."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
