"""The dataset format: a capture's cameras, poses and images, and the reader :func:`load_dataset`.

Layout of a dataset directory::

    dataset.json              manifest, written last: its presence marks a complete dataset
    synth_report.json         timings of the run that wrote it (the only file that varies) and the
                              street's coverage (shares of road, sidewalk and facades the rig sees)
    rig.json                  intrinsics, lens distortion ("none", radtan or fisheye) and cam_from_rig per camera
    poses.json                world_from_rig per frame, float64
    images/cam{c}/NNNNNN.png  RGB images
    colmap/                   the same cameras and poses as a COLMAP text model
    gt/scene.json             the generator's configuration (re-creates the scene) and digest
    gt/mesh.ply               the scene's triangle mesh
    gt/objects/*.npy          kind (k,) int16, seed (k,) uint32, bounds (k, 2, 3) float64
    gt/triangle_object.npy    object id per mesh triangle (m,) int32
    gt/depth/cam{c}/NNNNNN.npy  z-depth (h, w) float32, NaN = sky
    gt/ids/cam{c}/NNNNNN.npy    object id (h, w) int32, −1 = sky

Images and ground truth are stored as the raw cameras see them (distorted, when
rig.json gives a lens); :class:`Dataset` returns them undistorted, lined up with
``rig.intrinsics``.

A user's own capture needs only ``rig.json``, ``poses.json`` and ``images/`` (the
importers of :mod:`recon.importers` write ``dataset.json`` too); ``synth_report.json``,
``colmap/`` and ``gt/`` are the synthetic generator's (:mod:`data_synth`).

A dataset whose ``dataset.json`` says ``"images": KIND`` has no ``images/`` (and no ``gt/``
files but ``gt/scene.json``): an image source of that kind (:mod:`capture.sources`; the
generator's *lazy* datasets, ``"images": "lazy"``, :mod:`data_synth.lazy`) makes each frame
when it is read, by :meth:`Dataset.image`, :meth:`Dataset.gt_depth`, :meth:`Dataset.gt_ids`
and :func:`read_image` alike.
"""

from __future__ import annotations

import functools
import logging
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, load_npy, read_json, read_png

from .poses import load_poses, posed
from .rig import Rig, is_int
from .sources import ImageSource, image_source

DATASET_FORMAT = "bbcity-dataset"
#: Version of ``dataset.json``.
FORMAT_VERSION = 1

_FRAME_NAME = re.compile(r"\d{6}")

logger = logging.getLogger(__name__)
_WARNED: set[str] = set()  # dataset.json files warned about in this process


@dataclass(frozen=True)
class Dataset:
    """A validated dataset. world_from_rig: (n, 4, 4) float64; frame_names: n stems;
    lazy: the image source a lazy dataset's frames are made by (:mod:`capture.sources`;
    None: stored images)."""

    root: Path
    rig: Rig
    world_from_rig: np.ndarray
    frame_names: tuple[str, ...]
    lazy: ImageSource | None = None

    def __fspath__(self) -> str:  # a dataset stands for its directory (load_dataset returns it as it is)
        return str(self.root)

    def __str__(self) -> str:
        return str(self.root)

    @property
    def num_frames(self) -> int:
        return len(self.frame_names)

    @property
    def posed(self) -> np.ndarray:
        """(n,) bool: the frames that have a pose (a photo folder's are unknown until SfM)."""
        return posed(self.world_from_rig)

    @property
    def has_ground_truth(self) -> bool:
        return (self.root / "gt" / "scene.json").is_file()

    @property
    def has_gt_depth(self) -> bool:
        """Whether :meth:`gt_depth` and :meth:`gt_ids` can be read: ground truth with per-image
        depth and ids (``gt/depth`` and ``gt/ids``, or a lazy dataset that casts them; a dataset
        written with ``synth --no-gt-depth`` has the scene alone)."""
        if not self.has_ground_truth:
            return False
        if self.lazy is not None:
            return bool(self.lazy.has_gt_depth)
        return all((self.root / "gt" / kind).is_dir() for kind in ("depth", "ids"))

    def image_path(self, frame: int, cam: int) -> Path:
        """Where the raw image is; a lazy dataset's is not there: :func:`read_image`
        reads both (as :meth:`image` does)."""
        return self.root / "images" / f"cam{cam}" / f"{self.frame_names[frame]}.png"

    def image(self, frame: int, cam: int) -> np.ndarray:
        """(h, w, 3) uint8 RGB, undistorted when the camera has a lens (pinhole ``rig.intrinsics``);
        a missing, truncated or wrongly sized file raises DataFormatError. A lazy dataset makes it."""
        if self.lazy is not None:
            raw = self.lazy.image(int(self.frame_names[frame]), cam)
        else:
            raw = read_png(self.image_path(frame, cam), self.rig.sizes[cam])
        return self.rig.undistort(raw, cam)

    def world_from_cam(self, frame: int, cam: int) -> np.ndarray:
        """(4, 4) float64 camera pose."""
        return self.rig.world_from_cam(self.world_from_rig[frame], cam)

    def _gt_path(self, kind: str, frame: int, cam: int) -> Path:
        """Where a stored dataset keeps the raw ground truth ``kind`` ("depth", "ids")."""
        return self.root / "gt" / kind / f"cam{cam}" / f"{self.frame_names[frame]}.npy"

    def _raw_gt(self, kind: str, frame: int, cam: int, dtype) -> np.ndarray:
        """The raw (distorted) ground truth ``kind``, validated: (h, w) of ``dtype``; depths NaN
        or positive. A lazy dataset makes it."""
        if self.lazy is not None:
            return self.lazy.ground_truth(kind, int(self.frame_names[frame]), cam)
        w, h = self.rig.sizes[cam]
        path = self._gt_path(kind, frame, cam)
        raw = load_npy(path, dtype=dtype, shape=(h, w))
        if kind == "depth":  # NaN where nothing is hit; a hit lies in front of the camera
            # fmin/fmax skip NaN (NaN when all are): two passes find whether a depth is ≤ 0 or inf
            if np.fmin.reduce(raw, axis=None) <= 0 or np.fmax.reduce(raw, axis=None) == np.inf:
                bad = ~(np.isnan(raw) | (np.isfinite(raw) & (raw > 0)))
                raise DataFormatError(path, f"holds {int(bad.sum())} depths that are neither NaN (no hit) nor "
                                            f"a positive distance, e.g. {raw[bad][0]:g}")
        else:  # −1 where nothing is hit, else an object of the scene
            objects = self.num_objects
            if raw.min() < -1 or raw.max() >= objects:
                bad = (raw < -1) | (raw >= objects)
                raise DataFormatError(path, f"holds {int(bad.sum())} object ids outside −1 (no hit) to {objects - 1} "
                                            f"(the {objects} objects of {self._objects_path}), e.g. {raw[bad][0]}")
        return raw

    @property
    def _objects_path(self) -> Path:
        return self.root / "gt" / "objects" / "kind.npy"

    @functools.cached_property
    def num_objects(self) -> int:
        """How many objects the ground-truth scene has (``gt/objects/kind.npy``; its ids are 0 … n − 1)."""
        return len(load_npy(self._objects_path, dtype=np.int16, shape=(None,)))

    def _gt(self, kind: str, frame: int, cam: int, dtype) -> np.ndarray:
        """The ground truth ``kind`` undistorted like the images."""
        # nearest raw pixel: no blending across depth edges or between object ids
        return self.rig.undistort(self._raw_gt(kind, frame, cam, dtype), cam, nearest=True)

    def gt_depth(self, frame: int, cam: int) -> np.ndarray:
        """(h, w) float32 ground-truth z-depth, NaN where nothing is hit; undistorted like
        :meth:`image` (nearest raw pixel, so within half a raw pixel of each pixel's ray)."""
        return self._gt("depth", frame, cam, np.float32)

    def gt_ids(self, frame: int, cam: int) -> np.ndarray:
        """(h, w) int32 ground-truth object id, −1 where nothing is hit; undistorted like :meth:`gt_depth`."""
        return self._gt("ids", frame, cam, np.int32)

    def verify(self) -> None:
        """Decode every image and every stored ground-truth array (slow, thorough; a lazy dataset
        makes every image): each must be its camera's size, no camera's images may all be one
        flat colour (stereo would have nothing to match), and no depth array may be all NaN (a
        camera that sees nothing). Per-image depth and ids come together or not at all. The first
        bad file raises DataFormatError."""
        first: list[np.ndarray | None] = [None] * self.rig.num_cameras  # camera → its flat colour so far
        flat = [True] * self.rig.num_cameras
        for f in range(self.num_frames):
            for c in range(self.rig.num_cameras):
                rgb = self.image(f, c)
                if flat[c]:
                    first[c] = rgb[0, 0].copy() if first[c] is None else first[c]
                    flat[c] = bool((rgb == first[c]).all())
        if any(flat):
            c = flat.index(True)
            raise DataFormatError(self.image_path(0, c).parent,
                                  f"every image of camera {c} is the one flat colour {tuple(first[c].tolist())}: "
                                  "nothing to reconstruct or texture")
        if self.lazy is not None or not self.has_ground_truth:
            return  # a lazy dataset's ground truth is cast with its images
        stored = [kind for kind in ("depth", "ids") if (self.root / "gt" / kind).is_dir()]
        if len(stored) == 1:
            missing = {"depth", "ids"}.difference(stored).pop()
            raise DataFormatError(self.root / "gt" / missing, f"is missing while gt/{stored[0]} is there: per-image "
                                                               "ground truth needs both (or neither)")
        for kind, dtype in (("depth", np.float32), ("ids", np.int32)):
            if kind not in stored:
                continue  # written without per-image ground truth (synth --no-gt-depth)
            for f in range(self.num_frames):
                for c in range(self.rig.num_cameras):
                    path = self._gt_path(kind, f, c)
                    if not path.is_file():
                        raise DataFormatError(path, f"ground-truth {kind} of frame {self.frame_names[f]} camera {c} "
                                                    "is missing")
                    raw = self._raw_gt(kind, f, c, dtype)
                    if kind == "depth" and np.isnan(raw).all():
                        raise DataFormatError(path, "ground-truth depth is NaN everywhere: the camera would see "
                                                    "nothing of the scene")


def load_dataset(path: os.PathLike | str, poses: os.PathLike | str | None = None, strict: bool = False) -> Dataset:
    """Open a dataset directory: validate ``rig.json``, ``poses.json``, that ``dataset.json``
    (when there is one) agrees with them, and that every image exists (cheap checks only:
    :meth:`Dataset.verify` decodes the files). Errors name the offending file.

    poses: another ``poses.json`` to use instead of the dataset's own (the poses a
    ``bbcity recon --poses sfm`` found, ``WORK/poses.json``): the same frame names in the
    same order; frames it gives ``null`` have no pose (NaN). A :class:`Dataset` passed as
    ``path`` is returned as it is (its poses kept; ``poses`` still replaces them), so that
    functions taking a dataset directory also take a dataset with poses from elsewhere.

    strict: also refuse what the stages only warn about: a ``dataset.json`` that says
    ``"ground_truth": true`` of a dataset without ``gt/`` (a synthetic dataset copied without
    it reads as a capture without ground truth); ``bbcity check`` reads datasets so.
    """
    if isinstance(path, Dataset):
        return path if poses is None else replace(path, world_from_rig=_replacement_poses(path, poses))
    root = Path(path)
    if not root.is_dir():
        raise DataFormatError(root, "dataset directory does not exist")
    rig = Rig.load(root / "rig.json")
    world_from_rig, names = load_poses(root / "poses.json")
    if not names:
        raise DataFormatError(root / "poses.json", "has no frames")
    _check_manifest(root, rig, len(names), strict)
    lazy = image_source(root)
    dataset = Dataset(root, rig, world_from_rig, tuple(names), lazy)
    if lazy is not None:  # no image files: the rig and frames must be the ones the source makes
        lazy.check_rig(rig, root / "rig.json")
        lazy.check_frames(names, world_from_rig, root / "poses.json")
    if poses is not None:
        dataset = replace(dataset, world_from_rig=_replacement_poses(dataset, poses))
    for f in range(0 if lazy is not None else dataset.num_frames):
        for c in range(rig.num_cameras):
            p = dataset.image_path(f, c)
            if not p.is_file():
                raise DataFormatError(p, f"image of frame {names[f]} camera {c} is missing")
    return dataset


def _check_manifest(root: Path, rig: Rig, num_frames: int, strict: bool) -> None:
    """DataFormatError naming ``dataset.json`` (when there is one: a capture of one's own may
    have none) where it disagrees with the rest of the dataset: its ``"frames"`` with
    ``poses.json``, ``"cameras"`` and ``"image_size"`` with ``rig.json`` (the writers give
    camera 0's size), ``"ground_truth": true`` without ``gt/scene.json`` (with ``strict``;
    else a warning). A key left out is not checked."""
    path = root / "dataset.json"
    if not path.is_file():
        return
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataFormatError(path, "not a dataset manifest (expected a JSON object)")
    if "format" in data and data["format"] != DATASET_FORMAT:
        raise DataFormatError(path, f"\"format\" is {data['format']!r}, expected \"{DATASET_FORMAT}\"")
    for key, value, what in (("frames", num_frames, f"{root / 'poses.json'} has {num_frames} frames"),
                             ("cameras", rig.num_cameras, f"{root / 'rig.json'} has {rig.num_cameras} cameras")):
        if key in data and not (is_int(data[key]) and data[key] == value):
            raise DataFormatError(path, f"\"{key}\" is {data[key]!r} but {what}")
    if "image_size" in data:
        w, h = rig.sizes[0]
        size = data["image_size"]
        if not (isinstance(size, list) and len(size) == 2 and all(is_int(v) for v in size) and size == [w, h]):
            raise DataFormatError(path, f"\"image_size\" is {size!r} but camera 0 of {root / 'rig.json'} is "
                                        f"{w}x{h} ([width, height] expected)")
    if "ground_truth" in data:
        gt = data["ground_truth"]
        if not isinstance(gt, bool):
            raise DataFormatError(path, f"\"ground_truth\" must be true or false, got {gt!r}")
        if gt and not (root / "gt" / "scene.json").is_file():
            problem = DataFormatError(path, f"\"ground_truth\" is true but {root / 'gt' / 'scene.json'} is missing "
                                            "(copy the dataset's gt/ along, or set it false)")
            if strict:
                raise problem
            if str(path) not in _WARNED:
                _WARNED.add(str(path))
                logger.warning("%s; read as a capture without ground truth", problem)


def _replacement_poses(dataset: Dataset, path: os.PathLike | str) -> np.ndarray:
    """world_from_rig (n, 4, 4) float64 of ``path`` (a poses.json) for ``dataset``'s frames."""
    world_from_rig, names = load_poses(path)
    if tuple(names) != dataset.frame_names:
        raise DataFormatError(path, f"its {len(names)} frames are not the {dataset.num_frames} frames of "
                                    f"{dataset.root / 'poses.json'} (names and order must agree)")
    return world_from_rig


def held_out_frames(num_frames: int, every: int) -> list[int]:
    """The frames left out for novel-view evaluation: one in every ``every`` (the middle one
    of each run of ``every``; 0: none). Recon, build and eval all follow this rule."""
    if every < 0 or every == 1:
        raise InputError(f"holdout must be 0 (none) or ≥ 2 (every n-th frame left out), got {every}")
    return [f for f in range(num_frames) if every and f % every == every // 2]


def read_image(path: os.PathLike | str, size: tuple[int, int] | None = None) -> np.ndarray:
    """The raw image a dataset holds at ``path`` (``DATASET/images/cam{c}/NNNNNN.png``): the PNG
    file, or, for a lazy dataset, the frame made on demand. (h, w, 3) uint8 RGB; ``size``
    (width, height) is checked. What :func:`core.fileio.read_png` does for files, errors
    naming the file alike."""
    p = Path(path)
    if not p.is_file() and p.parent.parent.name == "images" and _FRAME_NAME.fullmatch(p.stem) \
            and p.suffix == ".png" and p.parent.name.startswith("cam") and p.parent.name[3:].isdigit():
        source = image_source(p.parent.parent.parent)
        if source is not None:
            rgb = source.image(int(p.stem), int(p.parent.name[3:]))
            if size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(int(s) for s in size):
                raise DataFormatError(p, f"is {rgb.shape[1]}x{rgb.shape[0]}, expected {size[0]}x{size[1]}")
            return rgb
    return read_png(p, size)
