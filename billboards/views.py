"""The captured images a build reads: :class:`Views`, each image's intrinsics, pose, size and
file, with the per-image photometric gains divided out and lenses removed as it is read."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.dataset import read_image
from core.fileio import read_png

from .photometry import apply_gains


@dataclass(frozen=True, eq=False)
class Views:
    """The captured images. K (v, 3, 3) float64; world_from_cam (v, 4, 4) float64;
    sizes (v, 2) int (width, height); paths: PNG file per view; gains (v, 3) float64
    per-view RGB exposure × white-balance gains that :meth:`image` divides out
    (:mod:`billboards.photometry`; None: images as captured). rig and cams (v,) int64: the
    :class:`capture.rig.Rig` and camera of each view, whose lens :meth:`image` removes
    (the PNG files hold the raw images; K is the undistorted pinhole); None: the files are
    pinhole images already. Picklable (a rig is arrays and small dataclasses)."""

    K: np.ndarray
    world_from_cam: np.ndarray
    sizes: np.ndarray
    paths: tuple[Path, ...]
    gains: np.ndarray | None = None
    rig: object | None = None
    cams: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.paths)

    @property
    def centres(self) -> np.ndarray:
        """(v, 3) float64 camera centres."""
        return self.world_from_cam[:, :3, 3]

    def image(self, i: int) -> np.ndarray:
        """(h, w, 3) uint8 RGB, divided by the view's gains; a bad file raises DataFormatError naming it.
        The path of a lazy synthetic dataset's image names a frame it casts on demand."""
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
