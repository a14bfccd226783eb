"""Pose sources for the rig: what they share, and the dataset's own poses.

Three sources, all returning ``world_from_rig`` (n, 4, 4) float64 in the
order of ``dataset.frame_names`` (rig frame: x forward, y left, z up; see
:mod:`capture.rig`), with NaN matrices for frames that have no pose:

* :func:`poses_given` (here) — the dataset's ``poses.json`` (GPS/IMU in a real capture).
* :func:`recon.colmap_poses.poses_from_colmap` — a COLMAP model the user already has.
* :func:`recon.sfm.poses_sfm` — structure from motion with pycolmap on the CPU, metric
  through the known rig.

Here also what they share: :class:`MissingFramesError`, :func:`poses_unknown` (a
dataset without any pose, e.g. a photo folder) and :func:`frame_passes` (which drive
each frame belongs to). Alignment and errors of trajectories: :mod:`recon.trajectory`.
``recon.pipeline.estimate_poses`` picks the source.
"""

from __future__ import annotations

import os

import numpy as np

from capture.dataset import Dataset
from core import DataFormatError
from core.fileio import read_json

__all__ = ["MissingFramesError", "frame_passes", "poses_given", "poses_unknown"]


class MissingFramesError(DataFormatError):
    """A pose source has no pose for some frames; ``missing`` lists their names."""

    def __init__(self, path: os.PathLike | str, missing: list[str], total: int, hint: str = ""):
        self.missing = list(missing)
        shown = ", ".join(missing[:20]) + (f", … ({len(missing) - 20} more)" if len(missing) > 20 else "")
        super().__init__(path, f"{len(missing)} of {total} frames have no pose: {shown}{hint}")


def poses_unknown(dataset: Dataset) -> bool:
    """Whether no frame of the dataset has a pose (``poses.json`` of a photo folder)."""
    return not dataset.posed.any()


def poses_given(dataset: Dataset) -> np.ndarray:
    """The dataset's own poses (``poses.json``; GPS/IMU in a real capture).

    Returns world_from_rig (n, 4, 4) float64, a copy, in ``dataset.frame_names`` order.
    A dataset with no known pose (a photo folder) raises DataFormatError.
    """
    if poses_unknown(dataset):
        raise DataFormatError(dataset.root / "poses.json", "poses unknown: use --poses sfm")
    return np.array(dataset.world_from_rig, dtype=np.float64, copy=True)


def frame_passes(dataset: Dataset) -> np.ndarray:
    """(n,) int64 pass of each frame from ``poses.json`` (``"pass"``; 0 where absent).

    A pass is one continuous drive; frames of different passes are different
    sequences (the return pass of a street looks at the other side).
    """
    path = dataset.root / "poses.json"
    frames = read_json(path).get("frames", [])
    by_name = {fr.get("name"): fr.get("pass", 0) for fr in frames if isinstance(fr, dict)}
    passes = np.zeros(dataset.num_frames, dtype=np.int64)
    for i, name in enumerate(dataset.frame_names):
        p = by_name.get(name, 0)
        if not isinstance(p, int) or isinstance(p, bool):
            raise DataFormatError(path, f"frame {name}: \"pass\" must be an integer, got {p!r}")
        passes[i] = p
    return passes
