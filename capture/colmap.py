"""COLMAP's conventions, and a camera rig with its known poses as a COLMAP text model.

The conventions below are bridged here once, for every reader and writer of COLMAP
models (the synthetic generator's ``colmap/``, recon's COLMAP poses and SfM, the COLMAP
importer): :data:`COLMAP_PIXEL_OFFSET`, :func:`colmap_camera_model`, and
:func:`to_rigid3d` / :func:`from_rigid3d` between (4, 4) float64 matrices and pycolmap's
``Rigid3d``. :func:`write_colmap_text` writes a rig's calibration and per-frame poses as a
COLMAP *rig* model (``cameras.txt``, ``rigs.txt``, ``frames.txt``, ``images.txt``,
``points3D.txt``) so that COLMAP tools — or our own ``recon`` stage through its COLMAP
import — can consume "known poses" exactly as they would a real reconstruction.

Conventions bridged here
------------------------
* **Principal point.** OpenCV puts the centre of the top-left pixel at (0, 0);
  COLMAP puts it at (0.5, 0.5). The same physical principal point therefore has
  ``cx_colmap = cx_opencv + 0.5`` and ``cy_colmap = cy_opencv + 0.5``. Focal
  lengths are unchanged.
* **Camera frame.** Both use x right, y down, z forward, so rotations need no
  axis flip.
* **Lens distortion.** A camera with a lens is written as its raw camera:
  radtan → ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2), or ``FULL_OPENCV``
  (k3 and k4 = k5 = k6 = 0, the same polynomial) when k3 ≠ 0; fisheye →
  ``OPENCV_FISHEYE`` (fx, fy, cx, cy, k1, k2, k3, k4). COLMAP's models use
  OpenCV's formulas.
* **Rig frame.** COLMAP's rig frame *is* the reference sensor's frame (camera 0
  here). For camera ``i`` we store ``sensor_from_rig = cam_i_from_cam0 =
  cam_from_rig[i] @ inv(cam_from_rig[0])`` and for frame ``k`` we store
  ``rig_from_world = cam0_from_world = cam_from_rig[0] @ inv(world_from_rig[k])``.
  COLMAP then derives each image's pose as
  ``cam_from_world = sensor_from_rig @ rig_from_world =
  cam_from_rig[i] @ inv(world_from_rig[k])``.

IDs are assigned deterministically: camera/sensor ``i`` → camera_id ``i + 1``;
rig_id 1; frame ``k`` → frame_id ``k + 1``; image (k, i) → image_id
``k * c + i + 1``. COLMAP's text writer prints doubles with 17 significant
digits, so float64 poses survive the round trip (city-scale translations of
1e6 m keep sub-nanometre resolution).
"""

from __future__ import annotations

import logging
from pathlib import Path, PurePosixPath

import numpy as np

from core.errors import InputError
from core.fileio import atomic_dir
from core.rigid import nearest_rotation, rigid_inverse

from .distortion import Distortion
from .native import pycolmap

logger = logging.getLogger(__name__)

__all__ = ["COLMAP_PIXEL_OFFSET", "colmap_camera_model", "from_rigid3d", "to_rigid3d", "write_colmap_text"]

#: Added to an OpenCV principal point (cx, cy) to get COLMAP's.
COLMAP_PIXEL_OFFSET = 0.5

_ROT_TOL = 1e-6  # max |R^T R - I| and |det R - 1| accepted as a rotation


# --------------------------------------------------------------------------- validation


def _check_rigid(name: str, T: np.ndarray) -> None:
    """Raise ValueError unless every T[j] (m, 4, 4) is finite and rigid."""
    if not np.all(np.isfinite(T)):
        raise InputError(f"{name} contains non-finite values")
    bottom = T[:, 3, :]
    bad = np.flatnonzero(np.abs(bottom - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1) > 1e-12)
    if bad.size:
        raise InputError(f"{name}[{bad[0]}] last row is {bottom[bad[0]].tolist()}, expected [0, 0, 0, 1]")
    R = T[:, :3, :3]
    ortho_err = np.abs(np.einsum("mji,mjk->mik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((ortho_err > _ROT_TOL) | (np.abs(det - 1.0) > _ROT_TOL))
    if bad.size:
        j = bad[0]
        raise InputError(
            f"{name}[{j}] rotation block is not a proper rotation "
            f"(max |R^T R - I| = {ortho_err[j]:.3g}, det = {det[j]:.6g}; tolerance {_ROT_TOL:g})"
        )


def _as_float64(name: str, a: np.ndarray, shape_tail: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(a)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(m, " + ", ".join(str(s) for s in shape_tail) + ")"
        raise InputError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _validate(intrinsics: np.ndarray, sizes: list[tuple[int, int]], cam_from_rig: np.ndarray,
              world_from_rig: np.ndarray, image_names: list[list[str]]
              ) -> tuple[np.ndarray, list[tuple[int, int]], np.ndarray, np.ndarray, list[list[str]]]:
    """The arguments of :func:`write_colmap_text` checked (ValueError naming the first bad one)
    and as float64 arrays, sizes as int pairs."""
    K = _as_float64("intrinsics", intrinsics, (3, 3))
    c = K.shape[0]
    if c < 1:
        raise InputError("intrinsics must describe at least one camera")
    if not np.all(np.isfinite(K)):
        raise InputError("intrinsics contains non-finite values")
    for i in range(c):
        k = K[i]
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise InputError(f"intrinsics[{i}] focal lengths must be > 0, got fx={k[0, 0]}, fy={k[1, 1]}")
        if k[0, 1] != 0 or k[1, 0] != 0:
            raise InputError(f"intrinsics[{i}] has skew/shear terms; PINHOLE supports none")
        if not np.array_equal(k[2], [0.0, 0.0, 1.0]):
            raise InputError(f"intrinsics[{i}] last row is {k[2].tolist()}, expected [0, 0, 1]")

    if len(sizes) != c:
        raise InputError(f"sizes has {len(sizes)} entries but intrinsics describes {c} cameras")
    sizes_out: list[tuple[int, int]] = []
    for i, wh in enumerate(sizes):
        try:
            w, h = wh
        except (TypeError, ValueError):
            raise InputError(f"sizes[{i}] must be a (width, height) pair, got {wh!r}") from None
        if int(w) != w or int(h) != h or int(w) <= 0 or int(h) <= 0:
            raise InputError(f"sizes[{i}] must be positive integers, got {wh!r}")
        sizes_out.append((int(w), int(h)))

    cfr = _as_float64("cam_from_rig", cam_from_rig, (4, 4))
    if cfr.shape[0] != c:
        raise InputError(f"cam_from_rig has {cfr.shape[0]} transforms but intrinsics describes {c} cameras")
    _check_rigid("cam_from_rig", cfr)

    wfr = _as_float64("world_from_rig", world_from_rig, (4, 4))
    n = wfr.shape[0]
    if n < 1:
        raise InputError("world_from_rig must hold at least one frame")
    _check_rigid("world_from_rig", wfr)

    if len(image_names) != n:
        raise InputError(f"image_names has {len(image_names)} frames but world_from_rig has {n}")
    seen: set[str] = set()
    names_out: list[list[str]] = []
    for k, row in enumerate(image_names):
        if isinstance(row, str) or len(row) != c:
            raise InputError(f"image_names[{k}] must be a list of {c} names, got {row!r}")
        out_row = []
        for i, name in enumerate(row):
            if not isinstance(name, str) or not name:
                raise InputError(f"image_names[{k}][{i}] must be a non-empty string, got {name!r}")
            if any(ch.isspace() for ch in name):
                # COLMAP's text format separates fields by spaces.
                raise InputError(f"image_names[{k}][{i}] = {name!r} contains whitespace")
            if "\\" in name or PurePosixPath(name).is_absolute() or ".." in PurePosixPath(name).parts:
                raise InputError(
                    f"image_names[{k}][{i}] = {name!r} must be a relative POSIX path inside images/"
                )
            if name in seen:
                raise InputError(f"image_names[{k}][{i}] = {name!r} is duplicated")
            seen.add(name)
            out_row.append(name)
        names_out.append(out_row)
    return K, sizes_out, cfr, wfr, names_out


# --------------------------------------------------------------------------- building


def to_rigid3d(T: np.ndarray) -> pycolmap.Rigid3d:
    """A (4, 4) float64 rigid transform as pycolmap's Rigid3d (rotation re-orthonormalised)."""
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.ascontiguousarray(nearest_rotation(T[:3, :3]))),
                            np.ascontiguousarray(T[:3, 3]))


def from_rigid3d(rigid: pycolmap.Rigid3d) -> np.ndarray:
    """pycolmap.Rigid3d → (4, 4) float64 (the inverse of :func:`to_rigid3d`)."""
    T = np.eye(4)
    T[:3, :4] = rigid.matrix()
    return T


def colmap_camera_model(K: np.ndarray, distortion: Distortion | None) -> tuple[str, list[float]]:
    """COLMAP model name and parameters of an OpenCV camera K (3, 3) float64 with a lens (or None)."""
    params = [K[0, 0], K[1, 1], K[0, 2] + COLMAP_PIXEL_OFFSET, K[1, 2] + COLMAP_PIXEL_OFFSET]
    if distortion is None:
        return "PINHOLE", [float(p) for p in params]
    if distortion.model == "fisheye":
        return "OPENCV_FISHEYE", [float(p) for p in params + list(distortion.coeffs)]
    k1, k2, p1, p2, k3 = distortion.coeffs
    if k3 == 0.0:
        return "OPENCV", [float(p) for p in params + [k1, k2, p1, p2]]
    return "FULL_OPENCV", [float(p) for p in params + [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]]


def _build_reconstruction(K: np.ndarray, sizes: list[tuple[int, int]], cam_from_rig: np.ndarray,
                          world_from_rig: np.ndarray, image_names: list[list[str]],
                          distortions: list[Distortion | None]) -> pycolmap.Reconstruction:
    """The pycolmap model :func:`write_colmap_text` writes (its validated arguments)."""
    c = K.shape[0]
    n = world_from_rig.shape[0]
    rec = pycolmap.Reconstruction()

    for i in range(c):
        w, h = sizes[i]
        model, params = colmap_camera_model(K[i], distortions[i])
        cam = pycolmap.Camera(camera_id=i + 1, model=model, width=w, height=h, params=params)
        rec.add_camera(cam)

    def sensor(i: int) -> pycolmap.sensor_t:
        return pycolmap.sensor_t(pycolmap.SensorType.CAMERA, i + 1)

    rig_id = 1
    rig = pycolmap.Rig(rig_id=rig_id)
    rig.add_ref_sensor(sensor(0))
    cam0_from_rig_inv = rigid_inverse(cam_from_rig[0])
    for i in range(1, c):
        cam_i_from_cam0 = cam_from_rig[i] @ cam0_from_rig_inv
        rig.add_sensor(sensor(i), to_rigid3d(cam_i_from_cam0))
    rec.add_rig(rig)

    rig_from_world = cam_from_rig[0] @ rigid_inverse(world_from_rig)  # (n, 4, 4): cam0_from_world
    for k in range(n):
        frame_id = k + 1
        frame = pycolmap.Frame(frame_id=frame_id, rig_id=rig_id)
        for i in range(c):
            frame.add_data_id(pycolmap.data_t(sensor(i), k * c + i + 1))
        frame.rig_from_world = to_rigid3d(rig_from_world[k])
        rec.add_frame(frame)
        for i in range(c):
            image = pycolmap.Image(name=image_names[k][i], camera_id=i + 1, image_id=k * c + i + 1)
            image.frame_id = frame_id
            rec.add_image(image)
        rec.register_frame(frame_id)
    return rec


# --------------------------------------------------------------------------- writing


def write_colmap_text(
    out_dir: Path,
    intrinsics: np.ndarray,
    sizes: list[tuple[int, int]],
    cam_from_rig: np.ndarray,
    world_from_rig: np.ndarray,
    image_names: list[list[str]],
    distortions: list[Distortion | None] | None = None,
) -> Path:
    """Write a rig's cameras and known poses as a COLMAP text model (via pycolmap).

    Builds a ``pycolmap.Reconstruction`` with one PINHOLE camera per rig
    camera (OPENCV, FULL_OPENCV or OPENCV_FISHEYE for a camera with a lens), one rig (camera 0 is the reference sensor), one registered frame
    per pose and one image per camera per frame; no 3D points. Writes
    ``cameras.txt``, ``rigs.txt``, ``frames.txt``, ``images.txt`` and
    ``points3D.txt`` into a temporary sibling directory and renames it over
    ``out_dir`` (an existing ``out_dir`` is moved aside, replaced, then
    deleted), so a reader never sees a half-written model. The same inputs
    give the same bytes.

    intrinsics: (c, 3, 3) float64 OpenCV pinhole K per camera (pixel centres at
        integer coordinates). Written with cx, cy shifted by +0.5 into COLMAP's
        convention (top-left pixel centre at (0.5, 0.5)). No skew allowed.
    sizes: c × (width, height), positive ints.
    cam_from_rig: (c, 4, 4) float64 rigid transforms (OpenCV camera frame
        x right, y down, z forward).
    world_from_rig: (n, 4, 4) float64 per frame.
    image_names: n lists of c relative image paths, e.g. "cam0/000000.png"
        (relative to the dataset's images/ dir); unique, no whitespace.
    distortions: c × (Distortion or None), the lens of each camera's images (then
        ``intrinsics`` are the raw, distorted cameras' K); None: all pinhole.
    Returns out_dir.

    Raises ValueError on inconsistent shapes, non-finite values, non-rigid
    transforms (rotation tolerance 1e-6), bad sizes or bad names.
    """
    out_dir = Path(out_dir)
    K, sizes_v, cfr, wfr, names = _validate(intrinsics, sizes, cam_from_rig, world_from_rig, image_names)
    distortions = [None] * len(K) if distortions is None else list(distortions)
    if len(distortions) != len(K) or not all(d is None or isinstance(d, Distortion) for d in distortions):
        raise InputError(f"distortions must hold a Distortion or None for each of the {len(K)} cameras")
    rec = _build_reconstruction(K, sizes_v, cfr, wfr, names, distortions)

    with atomic_dir(out_dir) as tmp_dir:
        rec.write_text(str(tmp_dir))
    logger.info(
        "wrote COLMAP text model to %s: %d cameras, %d frames, %d images",
        out_dir, rec.num_cameras(), rec.num_frames(), rec.num_images(),
    )
    return out_dir
