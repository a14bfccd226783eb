"""KITTI odometry sequences → a dataset (``bbcity import kitti``).

A sequence directory holds ``calib.txt`` (3×4 projection matrices P0..P3, row-major,
each line optionally prefixed ``P0:`` …; a ``Tr:`` line is ignored), ``poses.txt``
(one 3×4 ``world_from_cam0`` per frame, row-major; the world is cam0 of frame 0,
OpenCV axes) and a stereo pair of image folders: ``image_0``/``image_1`` (grey,
P0/P1), ``image_2``/``image_3`` (colour, P2/P3) or ``image_l``/``image_r`` (P0/P1).

KITTI's images are rectified: every P is K [I | t] in cam0's rectified frame, so the
cameras differ only by the translation t = K⁻¹ P[:, 3]. The dataset's rig frame has
the project's axes (x forward, y left, z up) with its origin ``camera_height`` below
cam0 (on the road); its world is the rig frame of the first frame. Grey images stay
grey PNGs (read back as RGB with equal channels).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from capture.rig import Rig
from core.errors import InputError
from core.fileio import DataFormatError

from .common import ZUP_FROM_CAMERA, clean_rigid, read_number_rows, write_imported_dataset

logger = logging.getLogger(__name__)

#: Image folder pairs by name, with the projection matrices they use.
CAMERA_PAIRS = {"grey": (("image_0", "image_1"), (0, 1)),
                "colour": (("image_2", "image_3"), (2, 3)),
                "lr": (("image_l", "image_r"), (0, 1))}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class KittiConfig:
    cameras: str = "auto"  # "grey" (image_0/1), "colour" (image_2/3), "lr" (image_l/r) or "auto" (colour, else grey, else lr)
    camera_height: float = 1.65  # cam0 above the road, metres (KITTI's rig): the rig frame's origin
    first: int = 0  # first frame to import
    count: int | None = None  # frames to import (None: to the end)
    step: int = 1  # import every step-th frame

    def __post_init__(self):
        if self.cameras not in ("auto", *CAMERA_PAIRS):
            raise InputError(f"cameras must be auto, {', '.join(CAMERA_PAIRS)}; got {self.cameras!r}")
        if not np.isfinite(self.camera_height) or self.camera_height < 0:
            raise InputError(f"camera_height must be a finite non-negative height, got {self.camera_height}")
        if self.first < 0 or self.step < 1 or (self.count is not None and self.count < 1):
            raise InputError("first must be ≥ 0, step ≥ 1 and count ≥ 1")


#: A stereo pair's baseline, metres (KITTI's: 0.54): shorter or longer ones are no car rig's.
MIN_BASELINE, MAX_BASELINE = 0.01, 10.0
#: Farthest a pose may lie from the sequence's origin, metres (beyond: a corrupt number).
MAX_POSITION = 1e7


def read_calib(path: Path) -> dict[int, np.ndarray]:
    """``calib.txt`` → {camera index: (3, 4) float64 P}. Prefixed lines name their camera;
    unprefixed files hold 2 (P0, P1) or 4 (P0..P3) lines."""
    if not path.is_file():
        raise DataFormatError(path, "calibration file is missing")
    named: dict[int, np.ndarray] = {}
    plain = []
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        key = fields[0][:-1] if fields[0].endswith(":") else None
        if key is not None:
            fields = fields[1:]
        try:
            values = np.array([float(v) for v in fields])
        except ValueError:
            raise DataFormatError(path, f"line {i} is not 12 numbers") from None
        if values.size != 12 or not np.all(np.isfinite(values)):
            raise DataFormatError(path, f"line {i} has {values.size} values, expected 12 finite numbers (a 3×4 P)")
        if key is None:
            plain.append(values.reshape(3, 4))
        elif key in ("P0", "P1", "P2", "P3"):
            named[int(key[1])] = values.reshape(3, 4)
        elif key != "Tr":
            raise DataFormatError(path, f"line {i}: unknown entry {key!r} (expected P0..P3 or Tr)")
    if plain and named:
        raise DataFormatError(path, "mixes lines with and without P0:…P3: names")
    if plain:
        if len(plain) not in (2, 4):
            raise DataFormatError(path, f"has {len(plain)} lines; expected 2 (P0, P1) or 4 (P0..P3) projection matrices")
        named = dict(enumerate(plain))
    for c, P in named.items():
        K = P[:, :3]
        if abs(K[0, 1]) > 1e-6 or np.abs(K[2] - [0, 0, 1]).max() > 1e-6 or K[0, 0] <= 0 or K[1, 1] <= 0 \
                or abs(K[1, 0]) > 1e-6:
            raise DataFormatError(path, f"P{c} is not a rectified pinhole K [I | t] (left 3×3 must be upper "
                                        "triangular with positive focal lengths and last row 0 0 1)")
    return named


def read_poses(path: Path) -> np.ndarray:
    """``poses.txt`` → (n, 4, 4) float64 world_from_cam0 (rotations cleaned of rounding)."""
    rows = read_number_rows(path, 12, "poses")
    if len(rows) == 0:
        raise DataFormatError(path, "has no poses")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    far = np.flatnonzero(np.abs(poses[:, :3, 3]).max(axis=1) > MAX_POSITION)
    if len(far):
        raise DataFormatError(path, f"line {far[0] + 1}: a position beyond {MAX_POSITION:g} m from the origin")
    return np.array([clean_rigid(T, path, f"line {i + 1}") for i, T in enumerate(poses)])


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def choose_cameras(root: Path, cameras: str) -> str:
    """The camera pair to import: ``cameras`` itself, or for "auto" the first present of
    colour, grey, lr."""
    if cameras != "auto":
        folders = CAMERA_PAIRS[cameras][0]
        for f in folders:
            if not (root / f).is_dir():
                raise DataFormatError(root / f, f"image folder of the {cameras} cameras is missing")
        return cameras
    for name in ("colour", "grey", "lr"):
        if all((root / f).is_dir() for f in CAMERA_PAIRS[name][0]):
            return name
    raise DataFormatError(root, "no stereo image folders (image_0/image_1, image_2/image_3 or image_l/image_r)")


def rig_from_cam0(camera_height: float) -> np.ndarray:
    """(4, 4) float64: KITTI's cam0 (whose poses poses.txt holds, whichever pair is
    imported) in the rig frame: the project's axes, origin ``camera_height`` below it."""
    T = ZUP_FROM_CAMERA.copy()
    T[2, 3] = camera_height
    return T


def kitti_rig(calib: dict[int, np.ndarray], cams: tuple[int, int], size: tuple[int, int], camera_height: float,
              calib_path: Path) -> Rig:
    """The two-camera rig of projection matrices ``cams`` (rig frame: see the module doc)."""
    missing = [c for c in cams if c not in calib]
    if missing:
        raise DataFormatError(calib_path, f"lacks P{missing[0]}, needed for the chosen cameras")
    cam0_from_rig = np.linalg.inv(rig_from_cam0(camera_height))
    Ks, Ts, offsets = [], [], []
    for c in cams:
        K = calib[c][:, :3].copy()
        cam_from_cam0 = np.eye(4)
        cam_from_cam0[:3, 3] = np.linalg.solve(K, calib[c][:, 3])
        Ks.append(K)
        Ts.append(cam_from_cam0 @ cam0_from_rig)
        offsets.append(-cam_from_cam0[:3, 3])  # the camera's centre in cam0's frame, metres
    left, right = offsets
    baseline = right - left
    if not (MIN_BASELINE <= baseline[0] <= MAX_BASELINE) or np.abs(baseline[1:]).max() > 0.1 * baseline[0]:
        # a rectified pair's right camera lies to the right of the left one, along x
        raise DataFormatError(calib_path, f"P{cams[1]} is not {MIN_BASELINE:g}–{MAX_BASELINE:g} m to the right of "
                                          f"P{cams[0]} along x (offset {np.round(baseline, 4).tolist()} m)")
    return Rig(np.array(Ks), (tuple(size),) * len(cams), np.array(Ts))


def import_kitti(sequence_dir: os.PathLike | str, out_dir: os.PathLike | str,
                 config: KittiConfig = KittiConfig(), progress=None) -> Path:
    """Import a KITTI odometry sequence into the dataset directory ``out_dir`` (new)."""
    root = Path(sequence_dir)
    if not root.is_dir():
        raise DataFormatError(root, "sequence directory does not exist")
    which = choose_cameras(root, config.cameras)
    folders, cams = CAMERA_PAIRS[which]
    calib = read_calib(root / "calib.txt")
    world_from_cam0 = read_poses(root / "poses.txt")
    files = [_image_files(root / f) for f in folders]
    for folder, listed in zip(folders, files):
        if len(listed) != len(world_from_cam0):
            raise DataFormatError(root / "poses.txt", f"has {len(world_from_cam0)} poses but {folder}/ has "
                                                       f"{len(listed)} images")
    if [p.stem for p in files[0]] != [p.stem for p in files[1]]:
        raise DataFormatError(root / folders[1], f"image names differ from those in {folders[0]}/")
    for i, path in enumerate(files[0]):  # line i of poses.txt is frame i: the images must number 0, 1, 2 …
        if not path.stem.isdigit() or int(path.stem) != i:
            raise DataFormatError(path, f"is image {i} of {folders[0]}/ in name order, but KITTI names frame {i} "
                                        f"{i:06d} (line {i + 1} of poses.txt): a frame is missing or misnamed")
    stop = len(world_from_cam0) if config.count is None else min(len(world_from_cam0), config.first + config.count * config.step)
    keep = list(range(config.first, stop, config.step))
    if not keep:
        raise InputError(f"{root}: no frames from {config.first} (the sequence has {len(world_from_cam0)})")
    first = cv2.imread(str(files[0][keep[0]]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise DataFormatError(files[0][keep[0]], "image could not be read")
    size = (first.shape[1], first.shape[0])
    rig = kitti_rig(calib, cams, size, config.camera_height, root / "calib.txt")
    to_rig = rig_from_cam0(config.camera_height)
    # world = the rig frame of the first imported frame
    world_from_rig = np.array([to_rig @ np.linalg.inv(world_from_cam0[keep[0]]) @ world_from_cam0[f]
                               @ np.linalg.inv(to_rig) for f in keep])
    images = [[files[0][f], files[1][f]] for f in keep]
    names = [files[0][f].stem for f in keep]
    source = {"kind": "kitti", "path": str(root.resolve()), "cameras": which, "frames": keep,
              "camera_height": config.camera_height}
    return write_imported_dataset(out_dir, rig, world_from_rig, images, source, names=names, progress=progress)
