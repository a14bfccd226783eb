"""nerfstudio's ``transforms.json`` and its images → a dataset (``bbcity import nerfstudio``).

The format (docs.nerf.studio, "Data conventions"; the Instant-NGP layout): intrinsics
``fl_x fl_y cx cy w h`` and a ``camera_model`` at the top level or in each frame (the top
level wins, as nerfstudio reads it), lens coefficients ``k1 k2 k3 k4 p1 p2`` (all from the
top level when any is there, else per frame; missing ones are 0), and ``frames``, each a
``file_path`` relative to the file's folder and a ``transform_matrix``: camera-to-world,
4×4 (or its top 3×4), with OpenGL/Blender camera axes (x right, y up, z back).

- Pixels: nerfstudio puts pixel (0, 0)'s centre at (0.5, 0.5) (COLMAP's convention), the
  project at (0, 0) (OpenCV's): cx and cy are :data:`PIXEL_OFFSET` less here.
- Lenses: ``PINHOLE``, ``SIMPLE_PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL`` and ``OPENCV`` (or no
  camera_model: nerfstudio's perspective camera) with k1 k2 p1 p2 k3 are the radtan lens
  (a pinhole when all are 0); ``OPENCV_FISHEYE`` with k1..k4 the fisheye lens. k4 on a
  perspective lens, p1/p2 on a fisheye and every other model (equirectangular, FISHEYE624 …)
  are refused. Images are copied as they are and undistorted when read.
- One camera: every frame must share the intrinsics and the image size (a dataset holds one
  rig); a file of several cameras is refused, naming the first frame that differs.
- Frames are sorted by file_path (as nerfstudio sorts them) and named by file stem
  (:func:`.common.frame_names`); each becomes a one-camera frame with its pose.
- Rig frame: origin at the camera, x its viewing direction made level, z the world's up (the
  mean up seen from the camera over all frames), y left — the COLMAP importer's level rig.
- World: nerfstudio's is z-up by convention (``ns-process-data`` orients it so), any origin
  and scale. ``world="auto"`` keeps it exactly as it is when the cameras' estimated up
  (:func:`recon.trajectory.up_direction`: minus their mean image-down axis) lies within
  :data:`UP_TOLERANCE_DEG` of +z, and turns it like the COLMAP importer otherwise (up → +z,
  origin at the first camera, x its level view); ``"keep"`` never turns it, ``"level"``
  always does. The turn is stored in dataset.json ("source" "world_from_nerfstudio"). The
  scale is kept: metres only when the file is metric (``--metric``; recorded as "metric").
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.distortion import Distortion
from capture.rig import Rig
from core.errors import InputError
from core.fileio import DataFormatError, read_json
from core.rigid import rigid_inverse

from ..trajectory import level_from_world, up_direction
from .common import check_image, clean_rigid, frame_names, write_imported_dataset

logger = logging.getLogger(__name__)

#: nerfstudio's pixel coordinate of the first pixel's centre along each axis (ours: 0).
PIXEL_OFFSET = 0.5
#: (4, 4) float64: an OpenGL camera frame (x right, y up, z back) ↔ an OpenCV one (x right,
#: y down, z forward); its own inverse.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
#: The camera models nerfstudio writes for a perspective lens (k1 k2 p1 p2 k3: radtan) and a fisheye.
PERSPECTIVE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
#: world="auto" keeps a world whose estimated up lies within this angle of +z, degrees: a
#: capture's cameras pitched up or down tilt the estimate by their pitch (a street rig's 8°).
UP_TOLERANCE_DEG = 15.0
#: Frames whose intrinsics differ by more than this (relative) are different cameras.
CAMERA_AGREEMENT = 1e-6
WORLDS = ("auto", "keep", "level")


@dataclass(frozen=True)
class NerfstudioImportConfig:
    metric: bool = False  # the poses are in metres (a metric capture); recorded in dataset.json
    world: str = "auto"  # auto: keep a z-up world, else turn it z-up; keep: never turn; level: always (module doc)

    def __post_init__(self):
        if not isinstance(self.metric, bool):
            raise InputError(f"metric must be True or False, got {self.metric!r}")
        if self.world not in WORLDS:
            raise InputError(f"world must be one of {', '.join(WORLDS)}, got {self.world!r}")


@dataclass(frozen=True)
class _Camera:
    """A frame's camera as the file gives it: model name, the six intrinsics and the six lens
    coefficients in DISTORTION_KEYS order."""

    model: str
    intrinsics: tuple[float, ...]
    coeffs: tuple[float, ...]

    def same(self, other: "_Camera") -> bool:
        a, b = np.array(self.intrinsics + self.coeffs), np.array(other.intrinsics + other.coeffs)
        return self.model == other.model and bool(np.all(np.abs(a - b) <= CAMERA_AGREEMENT * np.maximum(1.0, abs(a))))


def _number(value, path: Path, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataFormatError(path, f"{where} must be a finite number, got {value!r}")
    return float(value)


def _frame_camera(meta: dict, frame: dict, path: Path, where: str) -> _Camera:
    """The camera of one frame: each key from the top level, else the frame (see the module doc)."""
    values = []
    for key in INTRINSIC_KEYS:
        source = meta if key in meta else frame
        if key not in source:
            raise DataFormatError(path, f"{where} has no {key!r} (nor has the top level)")
        values.append(_number(source[key], path, key if source is meta else f"{where}.{key}"))
    fx, fy, _, _, w, h = values
    if fx <= 0 or fy <= 0:
        raise DataFormatError(path, f"{where}: fl_x and fl_y must be positive, got {fx:g} and {fy:g}")
    if w != int(w) or h != int(h) or not (0 < w <= 65536 and 0 < h <= 65536):
        raise DataFormatError(path, f"{where}: w and h must be positive integer pixel sizes, got {w:g} and {h:g}")
    lens = meta if any(k in meta for k in DISTORTION_KEYS) else frame
    coeffs = tuple(_number(lens.get(k, 0.0), path, k if lens is meta else f"{where}.{k}") for k in DISTORTION_KEYS)
    model = meta.get("camera_model", frame.get("camera_model", "OPENCV"))
    if not isinstance(model, str):
        raise DataFormatError(path, f"camera_model must be a string, got {model!r}")
    return _Camera(model, tuple(values), coeffs)


def raw_camera(camera: _Camera, path: Path) -> tuple[np.ndarray, tuple[int, int], Distortion | None]:
    """K (3, 3) float64 (OpenCV pixel centres), (width, height) and lens of a file's camera."""
    fx, fy, cx, cy, w, h = camera.intrinsics
    k = dict(zip(DISTORTION_KEYS, camera.coeffs))
    if camera.model in PERSPECTIVE_MODELS:
        if k["k4"]:
            raise DataFormatError(path, f"a {camera.model} camera with k4 (an eighth-order radial term) cannot be "
                                        "imported: the radtan lens has k1 k2 k3 p1 p2")
        model, names = "radtan", ("k1", "k2", "p1", "p2", "k3")
    elif camera.model in FISHEYE_MODELS:
        if k["p1"] or k["p2"]:
            raise DataFormatError(path, f"an {camera.model} camera has no tangential terms p1 p2")
        model, names = "fisheye", ("k1", "k2", "k3", "k4")
    else:
        raise DataFormatError(path, f"camera_model {camera.model!r} cannot be imported (known: "
                                    f"{', '.join(PERSPECTIVE_MODELS + FISHEYE_MODELS)})")
    K = np.array([[fx, 0.0, cx - PIXEL_OFFSET], [0.0, fy, cy - PIXEL_OFFSET], [0.0, 0.0, 1.0]])
    distortion = None
    if any(k[n] for n in names):
        try:
            distortion = Distortion(model, tuple(k[n] for n in names))
        except ValueError as e:
            raise DataFormatError(path, f"{camera.model} lens: {e}") from None
    return K, (int(w), int(h)), distortion


def _pose(frame: dict, path: Path, where: str) -> np.ndarray:
    """(4, 4) float64 world_from_cam with OpenCV camera axes from a frame's transform_matrix."""
    value = frame.get("transform_matrix")
    if value is None:
        raise DataFormatError(path, f"{where} has no transform_matrix")
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataFormatError(path, f"{where}.transform_matrix is not a matrix of numbers") from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise DataFormatError(path, f"{where}.transform_matrix must be 4×4 (or 3×4), got shape {T.shape}")
    if np.all(np.isfinite(T)) and np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise DataFormatError(path, f"{where}.transform_matrix's last row must be 0 0 0 1")
    return clean_rigid(T, path, f"{where}.transform_matrix") @ GL_FROM_CV


def read_transforms(path: Path) -> tuple[list[str], np.ndarray, _Camera]:
    """A transforms.json → file paths (sorted), world_from_cam (n, 4, 4) float64 (OpenCV axes,
    the file's world) and the one camera they share. Errors name the file and the frame."""
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise DataFormatError(path, "not a nerfstudio transforms file (expected an object with \"frames\")")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataFormatError(path, "\"frames\" must be a non-empty list")
    rows = []
    for i, frame in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(frame, dict):
            raise DataFormatError(path, f"{where} is not an object")
        name = frame.get("file_path")
        if not isinstance(name, str) or not name.strip():
            raise DataFormatError(path, f"{where} has no file_path")
        rows.append((name, _pose(frame, path, where), _frame_camera(meta, frame, path, where)))
    rows.sort(key=lambda r: r[0])
    names = [r[0] for r in rows]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise DataFormatError(path, f"two frames name the image {twice!r}")
    camera = rows[0][2]
    for name, _, other in rows[1:]:
        if not other.same(camera):
            raise DataFormatError(path, f"the frame of {name} has another camera than that of {names[0]} "
                                        f"({other.model} {other.intrinsics} vs {camera.model} {camera.intrinsics}); "
                                        "a dataset holds one camera: write one file per camera")
    return names, np.array([r[1] for r in rows]), camera


def level_rig(world_from_cam: np.ndarray) -> np.ndarray:
    """(4, 4) float64 cam_from_rig of a camera in a z-up world: the rig frame at the camera,
    z the world's up as the camera sees it on average, x its view made level (module doc).

    world_from_cam: (n, 4, 4) float64, OpenCV camera axes."""
    up = np.einsum("nji,j->ni", world_from_cam[:, :3, :3], [0.0, 0.0, 1.0]).mean(axis=0)  # world z in the camera
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, -1.0, 0.0])  # up and down cancel out: the image's up
    rig_from_cam = level_from_world(up, np.array([0.0, 0.0, 1.0]), np.zeros(3))
    return rigid_inverse(rig_from_cam)


def z_up_world(world_from_cam: np.ndarray, world: str) -> tuple[np.ndarray, float]:
    """(4, 4) float64 new_world_from_file_world for the ``world`` rule (module doc) and the
    angle between the cameras' estimated up and +z, degrees."""
    try:
        up = up_direction(world_from_cam, world_from_cam[:, :3, 3])
    except ValueError:  # the cameras' down axes cancel out: no estimate
        up = np.array([0.0, 0.0, 1.0])
    tilt = float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
    if world == "keep" or (world == "auto" and tilt <= UP_TOLERANCE_DEG):
        return np.eye(4), tilt
    return level_from_world(up, world_from_cam[0, :3, 2], world_from_cam[0, :3, 3]), tilt


def import_nerfstudio(transforms: os.PathLike | str, out_dir: os.PathLike | str,
                      config: NerfstudioImportConfig = NerfstudioImportConfig(), progress=None) -> Path:
    """Import a nerfstudio ``transforms.json`` (or the folder holding one) and its images into
    the dataset directory ``out_dir`` (new)."""
    path, out = Path(transforms), Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    if path.is_dir():
        path = path / "transforms.json"
    names, world_from_cam, camera = read_transforms(path)
    K, size, distortion = raw_camera(camera, path)
    images = [path.parent / n for n in names]
    for image in images:
        check_image(image, size, path.name, f"{path.name} gives w×h")
    level, tilt = z_up_world(world_from_cam, config.world)
    world_from_cam = level[None] @ world_from_cam
    cam_from_rig = level_rig(world_from_cam)
    try:
        rig = Rig.from_raw(K[None], [size], cam_from_rig[None], [distortion])
    except ValueError as e:  # a lens that leaves no pinhole image inside the raw one
        raise DataFormatError(path, f"cannot undistort the camera ({e})") from None
    kept = bool(np.array_equal(level, np.eye(4)))
    source = {"kind": "nerfstudio", "path": str(path.resolve()), "camera_model": camera.model, "poses": "given",
              "metric": config.metric,
              "units": "metres" if config.metric else "the transforms file's (metres only if it is metric)",
              "world": "kept" if kept else "turned z-up", "up_tilt_deg": tilt,
              "world_from_nerfstudio": level.tolist()}
    logger.info("%s: %d frames of %dx%d pixels (%s); its world %s (cameras' up %.1f° from +z)", path, len(names),
                size[0], size[1], camera.model, "kept" if kept else "turned z-up", tilt)
    return write_imported_dataset(out, rig, world_from_cam @ cam_from_rig[None],
                                  [[p] for p in images], source, names=frame_names(names), progress=progress)
