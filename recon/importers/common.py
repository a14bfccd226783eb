"""What every importer shares: the axis change to the project's z-up world, rotations
cleaned of print rounding, and writing a dataset directory all at once."""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from pathlib import Path, PurePosixPath
from typing import Callable, Sequence

import cv2
import numpy as np
from PIL import Image as PILImage
from PIL import ImageOps

from capture.dataset import DATASET_FORMAT, FORMAT_VERSION
from capture.poses import save_poses
from capture.rig import Rig
from core.errors import InputError
from core.fileio import DataFormatError, write_bytes, write_json, write_png
from core.rigid import nearest_rotation
from core.workdir import hidden_name

logger = logging.getLogger(__name__)

#: (4, 4) float64: an OpenCV camera frame (x right, y down, z forward) → the
#: project's rig frame (x forward, y left, z up). Applied to a world that is a
#: camera's frame (KITTI's, COLMAP's first image), it makes z point up.
ZUP_FROM_CAMERA = np.array([[0.0, 0.0, 1.0, 0.0],
                            [-1.0, 0.0, 0.0, 0.0],
                            [0.0, -1.0, 0.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0]])

#: EXIF tag of a photo's orientation (IFD0): 1 as stored; 2–8 mirrored and/or turned.
TAG_ORIENTATION = 0x0112

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


def check_image(path: Path, size: tuple[int, int], named_in: str, expected: str) -> None:
    """DataFormatError naming ``path`` when the image is missing, unreadable or not ``size``
    (w, h) pixels; ``named_in`` says what named it ("the COLMAP model"), ``expected`` what
    gives its size ("COLMAP camera 3 is")."""
    if not path.is_file():
        raise DataFormatError(path, f"image named in {named_in} is missing")
    try:
        with PILImage.open(path) as im:
            got = im.size
    except Exception as e:  # Pillow raises many kinds for broken files
        raise DataFormatError(path, f"image could not be read ({e})") from None
    if got != tuple(size):
        raise DataFormatError(path, f"image is {got[0]}x{got[1]} but {expected} {size[0]}x{size[1]}")


def frame_names(image_names: Sequence[str]) -> list[str]:
    """Dataset frame names for image files: their stems, or the paths (without extension,
    "/" → "_") when stems repeat, or indices ``000000`` … when those repeat too."""
    stems = [PurePosixPath(n).stem for n in image_names]
    if len(set(stems)) == len(stems) and all(s and s not in (".", "..") for s in stems):
        return stems
    paths = [str(PurePosixPath(n).with_suffix("")).replace("/", "_").replace("\\", "_") for n in image_names]
    if len(set(paths)) == len(paths):
        return paths
    return [f"{i:06d}" for i in range(len(image_names))]


def exif_orientation(path: Path) -> int:
    """A photo's EXIF orientation, 1 (as stored) when it has none or an invalid one."""
    try:
        with PILImage.open(path) as im:
            orientation = im.getexif().get(TAG_ORIENTATION, 1)
    except Exception as e:  # Pillow raises many kinds for broken files
        raise DataFormatError(path, f"image could not be read ({e})") from None
    return orientation if orientation in range(1, 9) else 1


def _upright_pixels(source: Path) -> np.ndarray:
    """(h, w, 3) RGB or (h, w) grey uint8 pixels of a photo with its EXIF orientation applied."""
    try:
        with PILImage.open(source) as im:
            upright = ImageOps.exif_transpose(im)
            if upright.mode not in ("L", "RGB"):
                upright = upright.convert("RGB")
            return np.ascontiguousarray(np.asarray(upright))
    except Exception as e:  # Pillow raises many kinds for broken files
        raise DataFormatError(source, f"image could not be read ({e})") from None


def _copy_png(source: Path, target: Path, size: tuple[int, int], upright: bool = False) -> None:
    """Copy an image as PNG (decoded to check it, re-encoded when it is not a PNG, or when
    ``upright`` and it has an EXIF orientation other than 1: then with that applied)."""
    if upright and exif_orientation(source) != 1:
        pixels = _upright_pixels(source)
        h, w = pixels.shape[:2]
        if (w, h) != tuple(size):
            raise DataFormatError(source, f"image is {w}x{h} upright, expected {size[0]}x{size[1]} like the first "
                                          "image")
        write_png(target, pixels)
        return
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
                           progress: Callable[[int, int], None] | None = None, upright: bool = False) -> Path:
    """Write a dataset directory: ``rig.json``, ``poses.json``, ``images/cam{c}/NAME.png``
    and ``dataset.json`` (``source`` describes where it came from).

    world_from_rig: (n, 4, 4) float64. images: n frames × c camera source paths; with
    ``upright``, each image's EXIF orientation is applied (a phone's photos), else its pixels
    are stored as the file holds them.
    Everything goes into a temporary directory beside ``out_dir`` that is renamed at
    the end, so an interrupted import leaves nothing behind; an existing ``out_dir``
    is refused. Returns ``out_dir``.
    """
    out = Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    n, c = len(world_from_rig), rig.num_cameras
    if len(images) != n or any(len(row) != c for row in images):
        raise InputError(f"need {n} frames × {c} camera images")
    names = [f"{i:06d}" for i in range(n)] if names is None else list(names)
    tmp = out.parent / f".{hidden_name(out.name)}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        rig.save(tmp / "rig.json")
        try:  # the rig as check and every stage will read it: an import writes no dataset they refuse
            Rig.load(tmp / "rig.json")
        except DataFormatError as e:
            raise InputError(f"{source.get('path', source.get('kind', 'the input'))}: the camera it describes is "
                             f"refused by the dataset format ({e.problem})") from None
        for f, row in enumerate(images):
            for cam, src in enumerate(row):
                _copy_png(Path(src), tmp / "images" / f"cam{cam}" / f"{names[f]}.png", rig.sizes[cam], upright)
            if progress is not None:
                progress(f + 1, n)
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
