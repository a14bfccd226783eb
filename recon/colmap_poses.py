"""Rig poses from a COLMAP model: one the user already has (:func:`poses_from_colmap`,
text or binary; with rigs and frames, COLMAP ≥ 3.12, or one image per camera) or one
that SfM just built (:func:`poses_from_reconstruction`).

COLMAP conventions bridged here (see :mod:`capture.colmap`): COLMAP
cameras use OpenCV's axes but put the top-left pixel centre at (0.5, 0.5), so
``cx_colmap = cx + 0.5``; a COLMAP rig frame *is* its reference sensor's
camera frame, so ``world_from_rig = inv(rig_from_world) @ cam_from_rig[ref]``
with our calibrated ``cam_from_rig`` of the reference camera.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path, PurePosixPath

import numpy as np

from capture.colmap import from_rigid3d
from capture.dataset import Dataset
from capture.native import pycolmap
from capture.poses import posed, unknown_poses
from core import DataFormatError
from core.rigid import rigid_inverse

from .colmap_log import colmap_log_to_logging
from .poses import MissingFramesError
from .trajectory import rig_baseline_ratio

logger = logging.getLogger(__name__)

__all__ = [
    "DEPTH_QUANTILES", "frame_depths", "image_index", "poses_from_colmap", "poses_from_reconstruction",
    "read_reconstruction",
]

#: Quantiles of the depths of the sparse points each frame sees that :func:`frame_depths` returns:
#: near, median, far (the 2nd and 98th percentiles leave out stray triangulations).
DEPTH_QUANTILES = (0.02, 0.5, 0.98)
#: Fewest sparse points a frame must see for its depths to count (fewer: NaN).
MIN_DEPTH_POINTS = 20


_CAM_DIR = re.compile(r"^cam(\d+)$")


def image_index(name: str, frame_index: dict[str, int], num_cameras: int) -> tuple[int, int] | None:
    """(frame, camera) of a COLMAP image name, or None when it is not one of the dataset's images.

    Accepted: ``cam{c}/{frame}.{ext}``, the same under extra leading folders
    (``images/cam1/000003.png``), and a bare ``{frame}.{ext}`` when the rig has
    a single camera (the only unambiguous case).
    """
    parts = PurePosixPath(name.replace("\\", "/")).parts
    if not parts:
        return None
    f = frame_index.get(PurePosixPath(parts[-1]).stem)
    if f is None:
        return None
    if len(parts) >= 2:
        m = _CAM_DIR.match(parts[-2])
        if m and int(m.group(1)) < num_cameras:
            return f, int(m.group(1))
        return None
    return (f, 0) if num_cameras == 1 else None


def poses_from_reconstruction(rec: pycolmap.Reconstruction, dataset: Dataset,
                              source: os.PathLike | str = "<reconstruction>") -> tuple[np.ndarray, np.ndarray]:
    """Rig poses from a pycolmap.Reconstruction, matched to the dataset's frames by image name.

    For each dataset frame, the pose comes from its registered image of the
    model rig's reference sensor when there is one (``world_from_rig =
    inv(rig_from_world) @ cam_from_rig[ref]``), otherwise from the registered
    image with the lowest camera index (``inv(cam_from_world) @
    cam_from_rig[c]``). Both reduce to the same matrix when the model's rig
    calibration equals the dataset's. Images whose names match no dataset
    image are ignored (logged).

    Returns world_from_rig (n, 4, 4) float64, NaN for frames without a
    registered image, and world_from_cam (n, c, 4, 4) float64, NaN where that
    camera's image is not registered.
    """
    n, c = dataset.num_frames, dataset.rig.num_cameras
    frame_index = {name: i for i, name in enumerate(dataset.frame_names)}
    cam_from_rig = dataset.rig.cam_from_rig
    world_from_cam = np.full((n, c, 4, 4), np.nan)
    is_ref = np.zeros((n, c), dtype=bool)
    ignored: list[str] = []
    rigs = rec.rigs
    for image in rec.images.values():
        where = image_index(image.name, frame_index, c)
        if where is None:
            ignored.append(image.name)
            continue
        if not image.has_pose:
            continue
        f, cam = where
        world_from_cam[f, cam] = rigid_inverse(from_rigid3d(image.cam_from_world()))
        frame = rec.frames[image.frame_id]
        is_ref[f, cam] = rigs[frame.rig_id].ref_sensor_id == image.data_id.sensor_id
    if ignored:
        logger.warning("%s: %d images match no image of the dataset (e.g. %s); ignored",
                       source, len(ignored), ignored[0])

    have = posed(world_from_cam.reshape(n * c, 4, 4)).reshape(n, c)
    # preferred camera per frame: a reference-sensor image first, then the lowest index
    rank = np.where(have, np.where(is_ref, 0, 1 + np.arange(c)), c + 1)
    best = np.argmin(rank, axis=1)
    world_from_rig = unknown_poses(n)
    rows = np.flatnonzero(have.any(axis=1))
    world_from_rig[rows] = world_from_cam[rows, best[rows]] @ cam_from_rig[best[rows]]
    return world_from_rig, world_from_cam


def frame_depths(rec: pycolmap.Reconstruction, dataset: Dataset, min_points: int = MIN_DEPTH_POINTS) -> np.ndarray:
    """Depths of the sparse points each frame's reference camera (camera 0) sees, in the
    model's units: (n, 3) float64, the :data:`DEPTH_QUANTILES` (near, median, far) per frame
    in ``dataset.frame_names`` order, NaN where the image is not registered or sees fewer
    than ``min_points`` points in front of it. Depth is along the optical axis, so it does
    not change when the model is moved rigidly (aligned to given poses)."""
    n = dataset.num_frames
    out = np.full((n, len(DEPTH_QUANTILES)), np.nan)
    frame_index = {name: i for i, name in enumerate(dataset.frame_names)}
    point_ids = np.fromiter(rec.points3D.keys(), np.int64, count=rec.num_points3D())
    order = np.argsort(point_ids)
    point_ids = point_ids[order]
    xyz = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)[order]
    for image in rec.images.values():
        where = image_index(image.name, frame_index, dataset.rig.num_cameras)
        if where is None or where[1] != 0 or not image.has_pose:
            continue
        ids = np.fromiter((p.point3D_id for p in image.get_observation_points2D()), np.int64)
        rows = np.searchsorted(point_ids, ids)
        rows = rows[(rows < len(point_ids)) & (point_ids[np.minimum(rows, len(point_ids) - 1)] == ids)]
        if len(rows) < min_points:
            continue
        X = xyz[rows]
        T = from_rigid3d(image.cam_from_world())
        z = X @ T[2, :3] + T[2, 3]
        z = z[z > 0]
        if len(z) >= min_points:
            out[where[0]] = np.quantile(z, DEPTH_QUANTILES)
    return out


def read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    """A COLMAP model (text or binary) read by pycolmap; DataFormatError naming ``model_dir``."""
    if not model_dir.is_dir():
        raise DataFormatError(model_dir, "COLMAP model directory does not exist")
    names = {p.name for p in model_dir.iterdir()}
    if not ({"cameras.bin", "images.bin"} <= names or {"cameras.txt", "images.txt"} <= names):
        raise DataFormatError(model_dir, "not a COLMAP model (needs cameras and images as .bin or .txt)")
    try:
        with colmap_log_to_logging():
            rec = pycolmap.Reconstruction(model_dir)
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with C++ messages
        raise DataFormatError(model_dir, f"cannot read the COLMAP model ({e})") from None
    check_poses(rec, model_dir)
    return rec


#: COLMAP writes unit quaternions; one whose norm is this far from 1 is no rotation (pycolmap
#: turns the quaternion 0 0 0 0 into the identity without a word).
QUATERNION_TOLERANCE = 1e-3
#: A camera or rig this far from the model's origin (in its units) is a damaged file, as in KITTI's poses.
MAX_TRANSLATION = 1e7


def check_poses(rec: pycolmap.Reconstruction, model_dir: Path) -> None:
    """DataFormatError naming ``model_dir`` and the image or frame whose pose is no rigid
    transform: a quaternion whose norm is not 1, a translation that is not finite or beyond
    :data:`MAX_TRANSLATION`."""
    poses = [(f"image {im.image_id} ({im.name})", im.cam_from_world()) for im in rec.images.values() if im.has_pose]
    poses += [(f"frame {fr.frame_id}", fr.rig_from_world) for fr in rec.frames.values() if fr.has_pose()]
    for what, rigid in poses:
        q, t = np.asarray(rigid.rotation.quat, np.float64), np.asarray(rigid.translation, np.float64)
        norm = float(np.linalg.norm(q))
        if not (np.isfinite(norm) and abs(norm - 1.0) <= QUATERNION_TOLERANCE):
            raise DataFormatError(model_dir, f"{what}: its quaternion {q[[3, 0, 1, 2]].tolist()} (w, x, y, z) has "
                                             f"norm {norm:g}, not 1: no rotation")
        if not (np.all(np.isfinite(t)) and np.abs(t).max() <= MAX_TRANSLATION):
            raise DataFormatError(model_dir, f"{what}: translation {t.tolist()} is not within ±{MAX_TRANSLATION:g}")


def check_image_sizes(rec: pycolmap.Reconstruction, dataset: Dataset, model_dir: Path) -> None:
    """DataFormatError naming ``model_dir`` when an image matched to the dataset was posed with a
    camera of another size than the dataset's (a model made from other images: its poses and
    the dataset's pixels would not belong together)."""
    frame_index = {name: i for i, name in enumerate(dataset.frame_names)}
    for image in rec.images.values():
        where = image_index(image.name, frame_index, dataset.rig.num_cameras)
        if where is None:
            continue
        camera, (w, h) = rec.cameras[image.camera_id], (int(v) for v in dataset.rig.sizes[where[1]])
        if (camera.width, camera.height) != (w, h):
            raise DataFormatError(model_dir, f"image {image.name} was posed with a {camera.width}×{camera.height} "
                                             f"camera; the dataset's camera {where[1]} is {w}×{h}: a model of "
                                             "other images")


def poses_from_colmap(model_dir: os.PathLike | str, dataset: Dataset, allow_missing: bool = False,
                      metric_tolerance: float = 0.01) -> np.ndarray:
    """Rig poses from an existing COLMAP model (text or binary, with or without rigs).

    Image names are matched to ``cam{c}/{frame}.png`` (any extension; extra
    leading folders allowed; bare ``{frame}.png`` only for a one-camera rig).
    With rigs and frames (COLMAP ≥ 3.12) a frame's pose is its
    ``rig_from_world`` mapped to our rig frame through ``cam_from_rig`` of the
    model's reference camera; without, each frame's cam0 image gives the pose
    (another camera's image when cam0's is not registered).

    The model's units are kept. When two cameras of a frame are registered,
    the model's camera spacing is compared with the calibrated baseline and a
    warning is logged if they differ by more than ``metric_tolerance`` (the
    model is not in metres).

    Returns world_from_rig (n, 4, 4) float64 in ``dataset.frame_names`` order.
    Raises DataFormatError naming ``model_dir`` when it is missing or
    unreadable, and MissingFramesError (a DataFormatError) listing the frames
    without a registered image unless ``allow_missing`` (then they are NaN).
    """
    model_dir = Path(model_dir)
    rec = read_reconstruction(model_dir)
    check_image_sizes(rec, dataset, model_dir)
    world_from_rig, world_from_cam = poses_from_reconstruction(rec, dataset, model_dir)
    ratio = rig_baseline_ratio(world_from_cam, dataset.rig.cam_from_rig)
    if np.isfinite(ratio) and abs(ratio - 1.0) > metric_tolerance:
        logger.warning("%s: camera spacing is %.4g × the calibrated baseline; the model is not metric "
                       "(poses are returned in the model's units)", model_dir, ratio)
    missing = [dataset.frame_names[i] for i in np.flatnonzero(~posed(world_from_rig))]
    if missing and not allow_missing:
        raise MissingFramesError(model_dir, missing, dataset.num_frames,
                                 " (not registered in the model; allow_missing=True gives NaN poses)")
    logger.info("imported %d of %d frame poses from %s (%d images, %d rigs)",
                dataset.num_frames - len(missing), dataset.num_frames, model_dir,
                rec.num_images(), rec.num_rigs())
    return world_from_rig
