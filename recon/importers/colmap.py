"""A COLMAP sparse model and its images → a dataset (``bbcity import colmap``).

The model (text or binary, read with pycolmap) gives the cameras and a pose for every
registered image; the image folder holds the files its image names point to.

Cameras: each COLMAP camera becomes a rig.json camera. SIMPLE_PINHOLE and PINHOLE are
pinhole; SIMPLE_RADIAL, RADIAL, OPENCV (and FULL_OPENCV with k4 = k5 = k6 = 0) become
the radtan lens, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, OPENCV_FISHEYE, SIMPLE_FISHEYE
and FISHEYE the fisheye lens (missing coefficients 0): their images are copied as they
are and undistorted when read. Every other perspective model (FULL_OPENCV with rational
terms, FOV, the thin-prism models, DIVISION, EUCM …) has terms neither lens can express:
its images are undistorted here, to the pinhole camera that
``pycolmap.undistort_camera`` chooses (its size may differ from the raw one).

Frames: a model rig with more than one sensor (COLMAP ≥ 3.12 ``rigs.txt``/``frames.txt``)
gives one dataset frame per registered frame that has an image of every sensor, cameras
in the order reference sensor, then the others by camera id. Without such a rig, a model
of one camera gives one frame per registered image (sorted by name); several cameras whose
images are named ``cam{c}/NAME.ext`` (the layout of :func:`capture.colmap.write_colmap_text` and of
the dataset itself) are grouped into frames by NAME, the rig taken from the poses (it must
be rigid). Any other model of several cameras is refused: give it a rig.

World: COLMAP's world is turned so that z points up — up is estimated as minus the mean
image-down axis of all cameras (held roughly level, see ``recon.trajectory.up_direction``) —
with its origin at the first frame's rig. The rig frame has the project's axes: origin at
the reference camera, z up (the same estimate, in the rig), x the reference camera's
viewing direction made horizontal, y left. COLMAP's scale is kept: metres only when the
model is metric (a known rig or GPS made it so; ``--metric`` records that in dataset.json).
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from capture.colmap import COLMAP_PIXEL_OFFSET, from_rigid3d
from capture.distortion import Distortion
from capture.native import pycolmap
from capture.rig import Rig
from core.errors import InputError
from core.fileio import DataFormatError, write_bytes
from core.rigid import nearest_rotation, rigid_inverse

from ..colmap_poses import read_reconstruction
from ..trajectory import level_from_world, up_direction
from .common import check_image, frame_names, write_imported_dataset

logger = logging.getLogger(__name__)

#: Largest spread of a camera's pose relative to camera 0 over frames, when a rig is taken from
#: poses (no rig in the model): rotation in degrees, translation relative to the largest offset.
RIG_ROTATION_TOLERANCE_DEG = 0.5
RIG_TRANSLATION_TOLERANCE = 0.02

#: COLMAP models our lenses express: name → (lens, parameter names in COLMAP's order).
#: "f" is one focal for x and y; coefficients not listed are 0.
LENS_MODELS = {
    "SIMPLE_PINHOLE": (None, ("f", "cx", "cy")),
    "PINHOLE": (None, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": ("radtan", ("f", "cx", "cy", "k1")),
    "RADIAL": ("radtan", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": ("radtan", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "FULL_OPENCV": ("radtan", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    "SIMPLE_RADIAL_FISHEYE": ("fisheye", ("f", "cx", "cy", "k1")),
    "RADIAL_FISHEYE": ("fisheye", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV_FISHEYE": ("fisheye", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    "SIMPLE_FISHEYE": ("fisheye", ("f", "cx", "cy")),
    "FISHEYE": ("fisheye", ("fx", "fy", "cx", "cy")),
}
#: FULL_OPENCV's rational terms, which the radtan lens lacks: when any is non-zero, undistort.
RATIONAL_TERMS = ("k4", "k5", "k6")
#: Rows of the undistortion map computed at once (bounds memory on large photos).
UNDISTORT_ROWS = 256

_CAM_NAME = re.compile(r"^(?:.*/)?cam(\d+)/([^/]+)$")


@dataclass(frozen=True)
class ColmapImportConfig:
    metric: bool = False  # the model is in metres (made with a known rig or GPS); recorded in dataset.json

    def __post_init__(self):
        if not isinstance(self.metric, bool):
            raise InputError(f"metric must be True or False, got {self.metric!r}")


@dataclass
class _Camera:
    """One dataset camera: the raw K (3, 3) float64 (OpenCV pixel centres), size, lens, and
    for a camera undistorted here its pycolmap raw and pinhole cameras."""

    K: np.ndarray
    size: tuple[int, int]
    distortion: Distortion | None
    raw: pycolmap.Camera | None = None  # set when the images are undistorted here
    pinhole: pycolmap.Camera | None = None


# --------------------------------------------------------------------------- reading


def _check_text_models(model_dir: Path) -> None:
    """A text model's camera lines name known models (pycolmap's own error names neither)."""
    path = model_dir / "cameras.txt"
    if not path.is_file() or (model_dir / "cameras.bin").is_file():
        return
    known = set(pycolmap.CameraModelId.__members__) - {"INVALID"}
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < 4:
            raise DataFormatError(path, f"line {i}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS…")
        if fields[1] not in known:
            raise DataFormatError(path, f"line {i}: camera {fields[0]} has unknown camera model {fields[1]!r} "
                                        f"(COLMAP's models: {', '.join(sorted(known))})")


def read_model(model_dir: os.PathLike | str) -> pycolmap.Reconstruction:
    """Read a COLMAP model (text or binary); errors name the directory or cameras file."""
    model_dir = Path(model_dir)
    if model_dir.is_dir():
        _check_text_models(model_dir)
    return read_reconstruction(model_dir)


MAX_IMAGE_EDGE = 65536  # pixels along an image's side (rig.json's limit)


def camera_from_colmap(camera: pycolmap.Camera, where: Path) -> _Camera:
    """A dataset camera for a COLMAP camera (see the module doc for the models); ``where``
    (the cameras file) is named in errors."""
    name = camera.model.name
    w, h = int(camera.width), int(camera.height)
    what = f"camera {camera.camera_id} ({name})"
    for side, value in (("width", w), ("height", h)):
        if not 0 < value <= MAX_IMAGE_EDGE:  # pycolmap reads a negative width as an unsigned 2⁶⁴ − n
            shown = value - (1 << 64) if value >= 1 << 63 else value
            raise DataFormatError(where, f"{what} has {side} {shown}: not an image {side} (1 to {MAX_IMAGE_EDGE} px)")
    params = np.asarray(camera.params, dtype=np.float64)
    if not np.all(np.isfinite(params)):
        raise DataFormatError(where, f"{what} has non-finite parameters")
    lens = LENS_MODELS.get(name)
    if lens is not None:
        model, names = lens
        if len(params) != len(names):
            raise DataFormatError(where, f"{what} has {len(params)} parameters, expected {len(names)}")
        p = dict(zip(names, params))
        if model != "radtan" or not any(p.get(k, 0.0) for k in RATIONAL_TERMS):
            fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
            if fx <= 0 or fy <= 0:
                raise DataFormatError(where, f"{what} has a non-positive focal length")
            K = np.array([[fx, 0.0, p["cx"] - COLMAP_PIXEL_OFFSET], [0.0, fy, p["cy"] - COLMAP_PIXEL_OFFSET],
                          [0.0, 0.0, 1.0]])
            distortion = None
            if model is not None:
                keys = ("k1", "k2", "p1", "p2", "k3") if model == "radtan" else ("k1", "k2", "k3", "k4")
                try:
                    distortion = Distortion(model, tuple(float(p.get(k, 0.0)) for k in keys))
                except ValueError as e:
                    raise DataFormatError(where, f"{what}: {e}") from None
            return _Camera(K, (w, h), distortion)
    # terms our lenses cannot express: undistort the images to a pinhole camera here
    if not camera.is_perspective():
        raise DataFormatError(where, f"{what} is not a perspective camera; it cannot be imported")
    try:
        pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
    except Exception as e:  # pycolmap raises RuntimeError/ValueError with C++ messages
        raise DataFormatError(where, f"{what} cannot be undistorted to a pinhole camera ({e})") from None
    if pinhole.model.name != "PINHOLE":
        raise DataFormatError(where, f"{what} cannot be undistorted to a pinhole camera")
    fx, fy, cx, cy = np.asarray(pinhole.params, dtype=np.float64)
    K = np.array([[fx, 0.0, cx - COLMAP_PIXEL_OFFSET], [0.0, fy, cy - COLMAP_PIXEL_OFFSET], [0.0, 0.0, 1.0]])
    return _Camera(K, (int(pinhole.width), int(pinhole.height)), None, camera, pinhole)


def colmap_pinhole_maps(raw: pycolmap.Camera, pinhole: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap tables (h, w) float32 x and y: for each pixel of the ``pinhole`` image, where
    it lies in the ``raw`` image (OpenCV pixel centres); outside the raw lens: −1."""
    w, h = int(pinhole.width), int(pinhole.height)
    map_x = np.empty((h, w), dtype=np.float32)
    map_y = np.empty((h, w), dtype=np.float32)
    u = np.arange(w, dtype=np.float64) + COLMAP_PIXEL_OFFSET
    for start in range(0, h, UNDISTORT_ROWS):
        rows = np.arange(start, min(start + UNDISTORT_ROWS, h), dtype=np.float64) + COLMAP_PIXEL_OFFSET
        uu, vv = np.meshgrid(u, rows)
        xy = pinhole.cam_from_img(np.stack([uu.ravel(), vv.ravel()], axis=1))
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        img = np.asarray(raw.img_from_cam(rays), dtype=np.float64) - COLMAP_PIXEL_OFFSET
        img[~np.isfinite(img).all(axis=1)] = -1.0
        map_x[start:start + len(rows)] = img[:, 0].reshape(len(rows), w)
        map_y[start:start + len(rows)] = img[:, 1].reshape(len(rows), w)
    return map_x, map_y


# --------------------------------------------------------------------------- frames


@dataclass
class _Layout:
    """What the model says, in COLMAP's frames: camera ids (c,) in dataset order, cam_from_ref
    (c, 4, 4) float64 (camera 0 is the reference), ref_from_world (n, 4, 4) float64 per frame,
    image names (n × c) and frame names (n)."""

    camera_ids: list[int]
    cam_from_ref: np.ndarray
    ref_from_world: np.ndarray
    images: list[list[str]]
    names: list[str]
    how: str


def _rig_layout(rec: pycolmap.Reconstruction, rig_id: int, model_dir: Path) -> _Layout:
    rig = rec.rigs[rig_id]
    ref = rig.ref_sensor_id
    others = sorted(rig.non_ref_sensors, key=lambda s: s.id)
    sensors = [ref, *others]
    for s in sensors:
        if s.type != pycolmap.SensorType.CAMERA:
            raise DataFormatError(model_dir, f"rig {rig_id} holds a {s.type.name} sensor; only cameras are imported")
    cam_from_ref = [np.eye(4)]
    for s in others:
        T = rig.sensor_from_rig(s)
        if T is None:
            raise DataFormatError(model_dir, f"rig {rig_id}: camera {s.id} has no pose in the rig (sensor_from_rig)")
        cam_from_ref.append(from_rigid3d(T))
    rows, skipped = [], 0
    for frame in rec.frames.values():
        if frame.rig_id != rig_id:
            continue
        by_sensor = {d.sensor_id.id: d.id for d in frame.data_ids if d.sensor_id.type == pycolmap.SensorType.CAMERA}
        if not frame.has_pose() or any(s.id not in by_sensor for s in sensors):
            skipped += 1
            continue
        missing = [by_sensor[s.id] for s in sensors if by_sensor[s.id] not in rec.images]
        if missing:  # frames.txt names an image that images.txt lacks
            raise DataFormatError(model_dir, f"frame {frame.frame_id} of rig {rig_id} names image(s) "
                                             f"{', '.join(map(str, missing))}, which the model's images lack")
        names = [rec.images[by_sensor[s.id]].name for s in sensors]
        rows.append((names[0], from_rigid3d(frame.rig_from_world), names))
    if skipped:
        logger.warning("%s: %d frames of rig %d are left out (not registered, or without an image of every camera)",
                       model_dir, skipped, rig_id)
    rows.sort(key=lambda r: r[0])
    return _Layout([s.id for s in sensors], np.array(cam_from_ref), np.array([r[1] for r in rows]).reshape(-1, 4, 4),
                   [r[2] for r in rows], frame_names([r[0] for r in rows]), f"rig {rig_id}")


def _single_camera_layout(rec: pycolmap.Reconstruction, camera_id: int) -> _Layout:
    images = sorted((im for im in rec.images.values() if im.camera_id == camera_id and im.has_pose),
                    key=lambda im: im.name)
    names = [im.name for im in images]
    poses = np.array([from_rigid3d(im.cam_from_world()) for im in images]).reshape(-1, 4, 4)
    return _Layout([camera_id], np.eye(4)[None], poses, [[n] for n in names], frame_names(names), "one camera")


def rig_from_poses(cam_from_world: np.ndarray, path: Path) -> np.ndarray:
    """(c, 4, 4) float64 cam_from_cam0 of cameras seen together in n frames.

    cam_from_world: (n, c, 4, 4) float64. The mean relative pose of each camera (rotation
    projected back onto SO(3)); an error naming ``path`` when a camera moves relative to
    camera 0 by more than the RIG_*_TOLERANCE (the cameras are not a rig)."""
    rel = cam_from_world @ rigid_inverse(cam_from_world[:, :1])  # (n, c, 4, 4): cam_from_cam0
    out = np.tile(np.eye(4), (rel.shape[1], 1, 1))
    reach = max(float(np.linalg.norm(rel[:, :, :3, 3], axis=2).max()), 1e-9)
    for c in range(1, rel.shape[1]):
        R = nearest_rotation(rel[:, c, :3, :3].mean(axis=0))
        t = rel[:, c, :3, 3].mean(axis=0)
        cos = (np.einsum("nij,ij->n", rel[:, c, :3, :3], R) - 1.0) / 2.0
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max()
        shift = np.linalg.norm(rel[:, c, :3, 3] - t, axis=1).max() / reach
        if angle > RIG_ROTATION_TOLERANCE_DEG or shift > RIG_TRANSLATION_TOLERANCE:
            raise DataFormatError(path, f"camera cam{c} moves relative to cam0 from frame to frame ({angle:.2g}°, "
                                        f"{100 * shift:.2g} % of the rig); they are not a rig: give the model a rig")
        out[c, :3, :3], out[c, :3, 3] = R, t
    return out


def _named_layout(rec: pycolmap.Reconstruction, model_dir: Path) -> _Layout | None:
    """Cameras grouped by ``cam{c}/NAME`` image names, or None when the names do not follow it."""
    groups: dict[str, dict[int, pycolmap.Image]] = {}
    camera_of: dict[int, int] = {}
    for im in rec.images.values():
        m = _CAM_NAME.match(im.name.replace("\\", "/"))
        if m is None:
            return None
        c = int(m.group(1))
        if camera_of.setdefault(c, im.camera_id) != im.camera_id:
            return None  # one folder, several cameras
        groups.setdefault(PurePosixPath(m.group(2)).stem, {})[c] = im
    cams = sorted(camera_of)
    if cams != list(range(len(cams))) or len(set(camera_of.values())) != len(cams):
        return None
    complete = sorted(k for k, g in groups.items() if len(g) == len(cams) and all(im.has_pose for im in g.values()))
    if len(complete) < len(groups):
        logger.warning("%s: %d frames are left out (not every camera's image registered)", model_dir,
                       len(groups) - len(complete))
    if not complete:
        raise DataFormatError(model_dir, "no frame has a registered image of every camera")
    cam_from_world = np.array([[from_rigid3d(groups[k][c].cam_from_world()) for c in cams] for k in complete])
    cam_from_ref = rig_from_poses(cam_from_world, model_dir / "images")
    return _Layout([camera_of[c] for c in cams], cam_from_ref, cam_from_world[:, 0],
                   [[groups[k][c].name for c in cams] for k in complete], complete, "cam{c}/NAME images")


def model_layout(rec: pycolmap.Reconstruction, model_dir: Path) -> _Layout:
    """How the model's images form dataset frames (see the module doc)."""
    rigs = [rid for rid, rig in rec.rigs.items() if rig.num_sensors() > 1]
    if len(rigs) > 1:
        raise DataFormatError(model_dir, f"has {len(rigs)} rigs of several cameras; a dataset holds one rig")
    if rigs:
        outside = sum(1 for f in rec.frames.values() if f.rig_id != rigs[0])
        if outside:
            logger.warning("%s: %d frames outside rig %d are left out", model_dir, outside, rigs[0])
        layout = _rig_layout(rec, rigs[0], model_dir)
    else:
        camera_ids = sorted({im.camera_id for im in rec.images.values()})
        if len(camera_ids) == 1:
            layout = _single_camera_layout(rec, camera_ids[0])
        else:
            layout = _named_layout(rec, model_dir)
            if layout is None:
                raise DataFormatError(model_dir, f"has {len(camera_ids)} cameras but no rig: give the model a rig "
                                                 "(COLMAP ≥ 3.12 rigs.txt and frames.txt), name its images "
                                                 "cam{c}/NAME, or import one camera's model")
    if len(layout.names) == 0:
        raise DataFormatError(model_dir, "has no registered image to import")
    return layout


def level_layout(cam_from_ref: np.ndarray, ref_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The project's rig and z-up world for a model's rig.

    cam_from_ref: (c, 4, 4), ref_from_world: (n, 4, 4) float64 (COLMAP's frames).
    Returns cam_from_rig (c, 4, 4), world_from_rig (n, 4, 4) and level_from_colmap (4, 4)
    float64 (the new world from COLMAP's). See the module doc for the axes.
    """
    world_from_cam = rigid_inverse(cam_from_ref[None] @ ref_from_world[:, None])  # (n, c, 4, 4)
    world_from_ref = rigid_inverse(ref_from_world)
    up = up_direction(world_from_cam.reshape(-1, 4, 4), world_from_ref[:, :3, 3])
    # up and the reference camera's view in the rig (the camera is camera 0, the rig frame its own)
    up_ref = ref_from_world[:, :3, :3] @ up
    up_ref = up_ref.mean(axis=0) / np.linalg.norm(up_ref.mean(axis=0))
    ref_from_rig = rigid_inverse(level_from_world(up_ref, rigid_inverse(cam_from_ref[0])[:3, 2], np.zeros(3)))
    cam_from_rig = cam_from_ref @ ref_from_rig
    colmap_from_rig = world_from_ref @ ref_from_rig
    level = level_from_world(up, colmap_from_rig[0, :3, 0], colmap_from_rig[0, :3, 3])
    return cam_from_rig, level @ colmap_from_rig, level


# --------------------------------------------------------------------------- import


def _undistorted(source: Path, target: Path, maps: tuple[np.ndarray, np.ndarray]) -> Path:
    image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataFormatError(source, "image could not be read")
    if image.dtype != np.uint8:
        raise DataFormatError(source, f"image has {image.dtype} pixels, expected 8-bit")
    out = cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    ok, buf = cv2.imencode(".png", out)
    if not ok:
        raise OSError(f"{target}: PNG encoding failed")
    write_bytes(target, buf.tobytes())
    return target


def import_colmap(model_dir: os.PathLike | str, image_dir: os.PathLike | str, out_dir: os.PathLike | str,
                  config: ColmapImportConfig = ColmapImportConfig(), progress=None) -> Path:
    """Import a COLMAP model and its images into the dataset directory ``out_dir`` (new)."""
    model_dir, image_dir, out = Path(model_dir), Path(image_dir), Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    if not image_dir.is_dir():
        raise DataFormatError(image_dir, "image directory does not exist")
    rec = read_model(model_dir)
    cameras_file = model_dir / ("cameras.bin" if (model_dir / "cameras.bin").is_file() else "cameras.txt")
    layout = model_layout(rec, model_dir)
    cams = [camera_from_colmap(rec.cameras[i], cameras_file) for i in layout.camera_ids]
    cam_from_rig, world_from_rig, level = level_layout(layout.cam_from_ref, layout.ref_from_world)
    try:
        rig = Rig.from_raw(np.array([c.K for c in cams]), [c.size for c in cams], cam_from_rig,
                           [c.distortion for c in cams])
    except ValueError as e:  # a lens that leaves no pinhole image inside the raw one
        raise DataFormatError(cameras_file, f"cannot undistort the cameras ({e})") from None
    raw_sizes = [(int(rec.cameras[i].width), int(rec.cameras[i].height)) for i in layout.camera_ids]
    sources = [[image_dir / name for name in row] for row in layout.images]
    for row in sources:
        for path, size, cid in zip(row, raw_sizes, layout.camera_ids):
            check_image(path, size, "the COLMAP model", f"COLMAP camera {cid} is")
    undistorted = [c for c, cam in enumerate(cams) if cam.raw is not None]
    source = {"kind": "colmap", "model": str(model_dir.resolve()), "images": str(image_dir.resolve()),
              "frames_from": layout.how,
              "colmap_models": [rec.cameras[i].model.name for i in layout.camera_ids],
              "undistorted_here": [f"cam{c}" for c in undistorted],
              "units": "metres" if config.metric else "the COLMAP model's (metres only if the model is metric)",
              "world_from_colmap": level.tolist()}
    with tempfile.TemporaryDirectory(prefix="bbcity-colmap-") as tmp:
        if undistorted:
            # undistorted copies go through a temporary folder; write_imported_dataset copies PNGs as they are
            logger.info("undistorting the images of %s to pinhole cameras",
                        ", ".join(f"cam{c} ({cams[c].raw.model.name})" for c in undistorted))
            for c in undistorted:
                maps = colmap_pinhole_maps(cams[c].raw, cams[c].pinhole)
                for f, row in enumerate(sources):
                    row[c] = _undistorted(row[c], Path(tmp) / f"cam{c}" / f"{f:06d}.png", maps)
        logger.info("COLMAP model %s: %d frames × %d cameras (%s)", model_dir, len(layout.names), len(cams),
                    layout.how)
        return write_imported_dataset(out, rig, world_from_rig, sources, source, names=layout.names,
                                      progress=progress)
