"""The capture format: what a dataset is, whoever made it (the synthetic generator
:mod:`data_synth`, or :mod:`recon.importers` from a real capture: KITTI, COLMAP, photos, video).

- :mod:`capture.dataset` — the dataset directory: :class:`~capture.dataset.Dataset`,
  :func:`~capture.dataset.load_dataset`, :func:`~capture.dataset.read_image`, the held-out frames;
- :mod:`capture.rig` — calibrated cameras (:class:`~capture.rig.Rig`) and ``rig.json``;
- :mod:`capture.poses` — ``poses.json`` (``world_from_rig`` per frame) and unknown poses;
- :mod:`capture.distortion` — lens models (radtan, fisheye) and undistortion tables;
- :mod:`capture.sources` — image sources: datasets whose images are made when read (lazy);
- :mod:`capture.colmap` — COLMAP's conventions and the COLMAP text model of a rig's poses;
- :mod:`capture.native` — pycolmap, loaded after Open3D and OpenCV (import it from there).

This package imports only :mod:`core`; importing it loads neither Open3D nor pycolmap.
"""

from .dataset import Dataset, held_out_frames, load_dataset, read_image
from .poses import load_poses, save_poses
from .rig import Rig

__all__ = ["Dataset", "Rig", "held_out_frames", "load_dataset", "load_poses", "read_image", "save_poses"]
