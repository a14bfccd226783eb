"""What recon refuses of a dataset from its rig and poses alone, found before any work is
done: ``bbcity check`` runs both checks with recon's defaults, recon :func:`check_rig_pairs`
with its own settings before its workers start.

A rig of two or more cameras is matched in the pairs of :func:`recon.rectify.rig_pairs`:
each pair must rectify (a baseline, roughly horizontal, equal image sizes). A one-camera
capture with poses is matched against neighbouring frames (:mod:`recon.motion_stereo`): at
least one frame must have a stereo partner.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from capture.dataset import Dataset
from core.errors import InputError
from core.fileio import DataFormatError

from .motion_stereo import MotionStereoConfig, select_partners
from .rectify import rectify_rig
from .working_size import scaled_rig, working_scale


def check_rig_pairs(ds: Dataset, max_image_size: int | None) -> None:
    """DataFormatError naming ``rig.json`` when a stereo pair of a rig of two or more cameras
    does not rectify at recon's working size ``max_image_size``
    (:func:`recon.working_size.working_scale`)."""
    rig = ds.rig
    if rig.num_cameras > 1:
        try:
            rectify_rig(scaled_rig(rig, working_scale(rig.sizes[0], max_image_size)))
        except InputError as e:
            raise DataFormatError(ds.root / "rig.json", f"recon matches the cameras in pairs: {e}") from None


def check_motion_partners(ds: Dataset, motion: MotionStereoConfig, held_out: Sequence[int] = ()) -> None:
    """DataFormatError naming ``poses.json`` when no frame of a one-camera capture has a stereo
    partner among its posed frames not ``held_out`` (recon with the dataset's poses). A
    capture of more cameras, or without poses (a photo folder: SfM finds them), passes."""
    rig = ds.rig
    world_from_cam = ds.world_from_rig @ np.linalg.inv(rig.cam_from_rig[0])
    world_from_cam[list(held_out)] = np.nan
    if rig.num_cameras > 1 or not np.isfinite(world_from_cam).all(axis=(1, 2)).any():
        return
    partners = select_partners(world_from_cam, rig.intrinsics[0], rig.sizes[0], motion)
    if not (partners >= 0).any():
        raise DataFormatError(ds.root / "poses.json",
                              f"no frame of this one-camera capture has a stereo partner (neighbouring frames "
                              f"{motion.min_baseline_ratio:g}–{motion.max_baseline_ratio:g} × the scene depth "
                              "apart, moving sideways to the view; walking toward what is photographed gives none)")
