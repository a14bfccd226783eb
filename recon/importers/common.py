"""What every importer shares: the axis change to the project's z-up world, rotations
cleaned of print rounding, and writing a dataset directory all at once."""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from core.fileio import DataFormatError, write_bytes, write_json
from core.rigid import nearest_rotation
from data_synth.dataset import DATASET_FORMAT, FORMAT_VERSION
from data_synth.rig import Rig, save_poses

logger = logging.getLogger(__name__)

#: (4, 4) float64: an OpenCV camera frame (x right, y down, z forward) → the
#: project's rig frame (x forward, y left, z up). Applied to a world that is a
#: camera's frame (KITTI's, COLMAP's first image), it makes z point up.
ZUP_FROM_CAMERA = np.array([[0.0, 0.0, 1.0, 0.0],
                            [-1.0, 0.0, 0.0, 0.0],
                            [0.0, -1.0, 0.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0]])

#: Largest deviation from orthonormality of a stored rotation that is taken for
#: rounding (files print 7 significant digits) and cleaned; more is an error.
ROTATION_TOLERANCE = 1e-3


def clean_rigid(T: np.ndarray, path: Path, what: str) -> np.ndarray:
    """(4, 4) float64 rigid transform from a rounded one; an error naming ``what`` when it
    is not a rotation up to :data:`ROTATION_TOLERANCE`."""
    T = np.asarray(T, dtype=np.float64)
    if not np.all(np.isfinite(T)):
        raise DataFormatError(path, f"{what} has non-finite values")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        raise DataFormatError(path, f"{what} is not a rotation and translation")
    out = np.eye(4)
    out[:3, :3] = nearest_rotation(R)
    out[:3, 3] = T[:3, 3]
    return out


def read_number_rows(path: Path, columns: int, what: str) -> np.ndarray:
    """The rows of a text file of numbers → (n, columns) float64. A leading ``NAME:``
    on a line is skipped (KITTI's calib.txt); blank lines are ignored. Errors name the line."""
    if not path.is_file():
        raise DataFormatError(path, f"{what} file is missing")
    rows = []
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if fields[0].endswith(":"):
            fields = fields[1:]
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise DataFormatError(path, f"line {i} is not {columns} numbers") from None
        if len(values) != columns or not all(np.isfinite(values)):
            raise DataFormatError(path, f"line {i} has {len(values)} values, expected {columns} finite numbers")
        rows.append(values)
    return np.array(rows, dtype=np.float64).reshape(-1, columns)


def _copy_png(source: Path, target: Path, size: tuple[int, int]) -> None:
    """Copy an image as PNG (decoded to check it, re-encoded when it is not a PNG)."""
    image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataFormatError(source, "image could not be read")
    h, w = image.shape[:2]
    if (w, h) != tuple(size):
        raise DataFormatError(source, f"image is {w}x{h}, expected {size[0]}x{size[1]} like the first image")
    if image.dtype != np.uint8:
        raise DataFormatError(source, f"image has {image.dtype} pixels, expected 8-bit")
    if source.suffix.lower() == ".png":
        write_bytes(target, source.read_bytes())
    else:
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise OSError(f"{target}: PNG encoding failed")
        write_bytes(target, buf.tobytes())


def write_imported_dataset(out_dir: os.PathLike | str, rig: Rig, world_from_rig: np.ndarray,
                           images: Sequence[Sequence[Path]], source: dict,
                           names: Sequence[str] | None = None,
                           progress: Callable[[int, int], None] | None = None) -> Path:
    """Write a dataset directory: ``rig.json``, ``poses.json``, ``images/cam{c}/NAME.png``
    and ``dataset.json`` (``source`` describes where it came from).

    world_from_rig: (n, 4, 4) float64. images: n frames × c camera source paths.
    Everything goes into a temporary directory beside ``out_dir`` that is renamed at
    the end, so an interrupted import leaves nothing behind; an existing ``out_dir``
    is refused. Returns ``out_dir``.
    """
    out = Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    n, c = len(world_from_rig), rig.num_cameras
    if len(images) != n or any(len(row) != c for row in images):
        raise ValueError(f"need {n} frames × {c} camera images")
    names = [f"{i:06d}" for i in range(n)] if names is None else list(names)
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        for f, row in enumerate(images):
            for cam, src in enumerate(row):
                _copy_png(Path(src), tmp / "images" / f"cam{cam}" / f"{names[f]}.png", rig.sizes[cam])
            if progress is not None:
                progress(f + 1, n)
        rig.save(tmp / "rig.json")
        save_poses(tmp / "poses.json", world_from_rig, np.zeros(n, dtype=np.int32), names=names)
        write_json(tmp / "dataset.json", {"format": DATASET_FORMAT, "version": FORMAT_VERSION, "frames": n, "cameras": c,
                                          "image_size": list(rig.sizes[0]), "ground_truth": False,
                                          "source": source})
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info("imported %d frames × %d cameras into %s", n, c, out)
    return out
