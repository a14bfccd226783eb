"""A dataset → nerfstudio's ``transforms.json`` and images (``bbcity export nerfstudio``), so
that nerfstudio's methods (nerfacto, splatfacto …) train on the same capture and compare with
a billboard model on the same held-out frames.

``OUT/images/cam{c}_{FRAME}.png`` holds every posed frame's image of every camera as the
dataset serves it (undistorted: :meth:`capture.dataset.Dataset.image`; a lazy dataset's are cast),
flat so that nerfstudio's downscaled copies (``images_2/NAME``) keep the names apart.
``OUT/transforms.json`` has one frame entry per image: its camera's pose (``transform_matrix``:
camera-to-world, OpenGL axes, in the dataset's z-up world and units) and the pinhole
intrinsics the dataset serves (``rig.intrinsics``; ``camera_model`` PINHOLE; cx, cy in
nerfstudio's pixel convention, :data:`.nerfstudio.PIXEL_OFFSET` more than ours), at the top
level when every camera shares them, else in each frame. Frames without a pose (a photo
folder before SfM) are left out, and said how many.

``holdout`` N (``bbcity recon/build --holdout N``) leaves the frames
:func:`capture.dataset.held_out_frames` picks out of training, as build leaves them out of
its textures: "train_filenames" lists every camera's images of the other frames,
"test_filenames" and "val_filenames" camera 0's images of the held-out frames (the views
``bbcity eval`` compares); nerfstudio then trains and evaluates on exactly those (it reads
the lists when the file has them, for every split). Without a holdout the file has no lists.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.dataset import held_out_frames, load_dataset
from core.errors import InputError
from core.fileio import atomic_dir, write_json, write_png

from .nerfstudio import GL_FROM_CV, PIXEL_OFFSET

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class NerfstudioExportConfig:
    holdout: int = 0  # every n-th frame held out of training, as recon/build --holdout (0: none; else ≥ 2)

    def __post_init__(self):
        if isinstance(self.holdout, bool) or not isinstance(self.holdout, int):
            raise InputError(f"holdout must be an integer, got {self.holdout!r}")
        held_out_frames(0, self.holdout)  # 0 or ≥ 2: its ValueError names the rule


def camera_entry(K: np.ndarray, size: tuple[int, int]) -> dict:
    """nerfstudio's intrinsics of a pinhole camera K (3, 3) float64 (OpenCV pixel centres) of
    ``size`` (width, height)."""
    return {"camera_model": "PINHOLE", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]) + PIXEL_OFFSET, "cy": float(K[1, 2]) + PIXEL_OFFSET,
            "w": int(size[0]), "h": int(size[1])}


def export_nerfstudio(dataset: os.PathLike | str, out_dir: os.PathLike | str,
                      config: NerfstudioExportConfig = NerfstudioExportConfig(),
                      poses: os.PathLike | str | None = None, progress=None) -> Path:
    """Write the dataset ``dataset`` as a nerfstudio dataset in ``out_dir`` (new; written
    whole or not at all). poses: a poses.json to use instead of the dataset's (the one
    ``bbcity recon --poses sfm`` wrote to its WORK). Returns ``out_dir``."""
    out = Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    ds = load_dataset(dataset, poses=poses)
    rig = ds.rig
    posed = ds.posed
    if not posed.any():
        raise InputError(f"{ds.root}: no frame has a pose (find them first with bbcity recon --poses sfm, then "
                         "export with --poses WORK/poses.json)")
    held = {f for f in held_out_frames(ds.num_frames, config.holdout) if posed[f]}
    cameras = [camera_entry(rig.intrinsics[c], rig.sizes[c]) for c in range(rig.num_cameras)]
    shared = all(cam == cameras[0] for cam in cameras)
    frames, train, test = [], [], []
    todo = np.flatnonzero(posed)
    with atomic_dir(out) as tmp:
        for n, f in enumerate(todo):
            for c in range(rig.num_cameras):
                name = f"images/cam{c}_{ds.frame_names[f]}.png"
                write_png(tmp / name, ds.image(int(f), c))
                entry = {"file_path": name, "transform_matrix": (ds.world_from_cam(int(f), c) @ GL_FROM_CV).tolist()}
                frames.append(entry if shared else {**entry, **cameras[c]})
                if f not in held:
                    train.append(name)
                elif c == 0:
                    test.append(name)
            if progress is not None:
                progress(n + 1, len(todo))
        meta = {**(cameras[0] if shared else {}), "frames": frames}
        if held:
            meta.update(train_filenames=train, val_filenames=test, test_filenames=test)
        meta["bbcity"] = {"dataset": str(ds.root.resolve()), "holdout": config.holdout,
                          "held_out_frames": sorted(int(f) for f in held), "world": "the dataset's (z up)"}
        write_json(tmp / "transforms.json", meta)
    skipped = int((~posed).sum())
    logger.info("wrote %s: %d images of %d frames × %d cameras%s%s", out, len(frames), len(todo), rig.num_cameras,
                f"; {skipped} frames without a pose left out" if skipped else "",
                f"; {len(held)} frames held out (test_filenames: camera 0)" if held else "")
    return out
