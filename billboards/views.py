"""The captured images a build reads: :class:`Views`, each image's intrinsics, pose, size and
file, with the per-image photometric gains divided out and lenses removed as it is read."""

from __future__ import annotations

import hashlib
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from capture.dataset import read_image
from core.fileio import read_png

from .photometry import apply_gains

#: The most bytes of images :func:`with_image_cache` keeps (and at most a quarter of the free disk).
IMAGE_CACHE_BYTES = 4 << 30


@dataclass(frozen=True, eq=False)
class Views:
    """The captured images. K (v, 3, 3) float64; world_from_cam (v, 4, 4) float64;
    sizes (v, 2) int (width, height); paths: PNG file per view; gains (v, 3) float64
    per-view RGB exposure × white-balance gains that :meth:`image` divides out
    (:mod:`billboards.photometry`; None: images as captured). rig and cams (v,) int64: the
    :class:`capture.rig.Rig` and camera of each view, whose lens :meth:`image` removes
    (the PNG files hold the raw images; K is the undistorted pinhole); None: the files are
    pinhole images already. cache: a directory where :meth:`image` keeps what it returns, as
    .npy, for every process that reads the same views (None: each read decodes the file); see
    :func:`with_image_cache`. Picklable (a rig is arrays and small dataclasses)."""

    K: np.ndarray
    world_from_cam: np.ndarray
    sizes: np.ndarray
    paths: tuple[Path, ...]
    gains: np.ndarray | None = None
    rig: object | None = None
    cams: np.ndarray | None = None
    cache: Path | None = None

    def __len__(self) -> int:
        return len(self.paths)

    @property
    def centres(self) -> np.ndarray:
        """(v, 3) float64 camera centres."""
        return self.world_from_cam[:, :3, 3]

    def image(self, i: int) -> np.ndarray:
        """(h, w, 3) uint8 RGB, divided by the view's gains; a bad file raises DataFormatError naming it.
        The path of a lazy synthetic dataset's image names a frame it casts on demand. With a
        ``cache``, the first read of a view keeps the result there and later ones read it back."""
        if self.cache is None:
            return self.read_image(i)
        kept = self.cache / f"{i:06d}-{self._key(i)}.npy"
        try:
            image = np.load(kept)
            if image.shape == (int(self.sizes[i][1]), int(self.sizes[i][0]), 3) and image.dtype == np.uint8:
                return image
        except (OSError, ValueError, EOFError):  # not kept yet (or damaged: read and kept again)
            pass
        image = self.read_image(i)
        tmp = kept.with_name(f".{kept.stem}.tmp-{os.getpid()}.npy")
        try:  # a whole file or none: several processes may keep the same view at once
            np.save(tmp, image)
            os.replace(tmp, kept)
        except OSError:  # a full disk only costs the next read a decode
            tmp.unlink(missing_ok=True)
        return image

    def _key(self, i: int) -> str:
        """What view ``i``'s cached image depends on beyond its index: its file, gains and lens."""
        h = hashlib.sha1(str(self.paths[i]).encode())
        if self.gains is not None:
            h.update(np.ascontiguousarray(self.gains[i], dtype=np.float64).tobytes())
        if self.rig is not None:
            h.update(b"cam%d" % int(self.cams[i]))
        return h.hexdigest()[:16]

    def read_image(self, i: int) -> np.ndarray:
        """:meth:`image` read from its file every time (the cache's source)."""
        size = tuple(int(s) for s in self.sizes[i])
        if Path(self.paths[i]).is_file():
            image = read_png(self.paths[i], size)
        else:  # a lazy dataset's frame, or the missing file's DataFormatError
            image = read_image(self.paths[i], size)
        if self.rig is not None:  # a distorted camera's raw image → the pinhole image K describes
            image = self.rig.undistort(image, int(self.cams[i]))
        if self.gains is None:
            return image
        return apply_gains(image, self.gains[i])


def with_image_cache(views: Views, directory: Path) -> Views:
    """``views`` keeping each image in ``directory`` (created) after its first read, when all of
    them fit in :data:`IMAGE_CACHE_BYTES` and a quarter of the free disk there; else ``views``
    as they are. A build reads each view many times (photometry, the layer, sampling, the fit),
    in several processes: decoding a PNG and dividing its gains costs several times reading it
    back. The caller removes ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    need = int(np.prod(views.sizes, axis=1).sum()) * 3
    if need > min(IMAGE_CACHE_BYTES, shutil.disk_usage(directory).free // 4):
        return views
    return replace(views, cache=directory)


def views_from_dataset(dataset, frames=None) -> Views:
    """The (frame, camera) images of a :class:`capture.dataset.Dataset`: every frame, or ``frames``;
    frames without a pose (NaN ``world_from_rig``: not registered by SfM) are left out.
    ``Views.image`` returns what ``dataset.image`` does (undistorted where a camera has a lens)."""
    K, poses, sizes, paths, cams = [], [], [], [], []
    posed = dataset.posed
    for f in (range(dataset.num_frames) if frames is None else frames):
        if not posed[f]:
            continue
        for c in range(dataset.rig.num_cameras):
            K.append(dataset.rig.intrinsics[c])
            poses.append(dataset.world_from_cam(f, c))
            sizes.append(dataset.rig.sizes[c])
            paths.append(dataset.image_path(f, c))
            cams.append(c)
    distorted = dataset.rig.distortions is not None  # pinhole rigs: the files are read as they are
    return Views(np.asarray(K, dtype=np.float64).reshape(-1, 3, 3),
                 np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
                 np.asarray(sizes, dtype=np.int64).reshape(-1, 2), tuple(paths),
                 rig=dataset.rig if distorted else None, cams=np.asarray(cams, dtype=np.int64) if distorted else None)
