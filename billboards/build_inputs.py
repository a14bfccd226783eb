"""What a build reads besides the cloud: the dataset's posed frames and their views, the
frames held out, the per-image photometric gains, and the model's build info that records
them. One copy for a model (:func:`billboards.build.main`) and a model set
(:func:`billboards.build_tiles.build_tiled`)."""

from __future__ import annotations

import os
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from core.errors import InputError
from capture.dataset import held_out_frames, load_dataset

from .build_config import BuildConfig
from .photometry import estimate_gains
from .views import Views, views_from_dataset


@dataclass(frozen=True, eq=False)
class BuildInputs:
    """The capture a build samples its textures from.

    dataset: the dataset (None: a cloud alone); frames: the posed frames whose images the
    textures are sampled from; held_out: the posed frames left out of the textures, which can
    be viewpoints (eval needs their poses); views: the (frame, camera) images of ``frames`` in
    the order of :func:`~billboards.views.views_from_dataset`, with their gains once estimated
    (None: no dataset); exposure: which [frame, camera] each gain belongs to and the gains (V, 3)
    as lists (the model info's "exposure"; None: no gains estimated).
    """

    dataset: object | None = None
    frames: list[int] = field(default_factory=list)
    held_out: list[int] = field(default_factory=list)
    views: Views | None = None
    exposure: dict | None = None

    @property
    def cameras(self) -> int:
        """Cameras of the rig (0 without a dataset)."""
        return self.dataset.rig.num_cameras if self.dataset is not None else 0


def read_inputs(conf: BuildConfig, dataset_dir: os.PathLike | str | None,
                poses: os.PathLike | str | None) -> BuildInputs:
    """The dataset in ``dataset_dir`` (None: none) with ``poses`` (a ``poses.json`` used instead
    of its own; None: its own), its frames split into the textures' and the held-out ones
    (``conf.holdout``), frames without a pose left out. Raises InputError when no frame has a
    pose, or when the source is images and there is no dataset."""
    if dataset_dir is None:
        if conf.source == "images":
            raise InputError("source 'images' needs the dataset's images and poses (--images DATASET)")
        return BuildInputs()
    dataset = load_dataset(dataset_dir, poses=poses)
    posed = dataset.posed
    if not posed.any():
        where = poses if poses is not None else Path(dataset_dir) / "poses.json"
        raise InputError(f"{where}: no frame has a pose (a photo folder: `bbcity recon DATASET --poses sfm`, "
                         "then `bbcity build WORK`)")
    # the frames left out of the textures that can be viewpoints (eval needs their poses)
    held_out = [f for f in held_out_frames(dataset.num_frames, conf.holdout) if posed[f]]
    frames = [f for f in range(dataset.num_frames) if f not in set(held_out) and posed[f]]
    return BuildInputs(dataset, frames, held_out, views_from_dataset(dataset, frames))


def check_views_see(conf: BuildConfig, inputs: BuildInputs, points: np.ndarray, cloud_path, dataset_dir) -> None:
    """Raise InputError when images are the source and no view sees any of the cloud's ``points``
    (N, 3) float64: every texel would stay transparent, an empty-looking model that builds
    without complaint (wrong dataset or poses)."""
    views = inputs.views
    if views is not None and conf.source == "images" and len(views) \
            and not sees_any(views, points, conf.sampling.max_distance):
        raise InputError(f"no camera of {dataset_dir} sees any point of {cloud_path}: wrong dataset or "
                         f"poses? (cloud within {_box(points)}, cameras within {_box(views.centres)})")


def with_gains(conf: BuildConfig, inputs: BuildInputs, points: np.ndarray,
               progress: bool | None, executor: Executor | None = None) -> tuple[BuildInputs, dict]:
    """``inputs`` with per-image exposure and white balance estimated from the cloud ``points``
    (N, 3) float64 (or a sample of it, :func:`~billboards.photometry.estimate_gains`) and divided
    out of every view before anything reads its colours (the layer's EPIs, the sky, the
    textures), so the eigen-textures spend no rank on them; and the build report's
    "photometry" (the views read in parallel by ``executor``). Unchanged (``{"enabled": False}``) when photometry is off, the source is not
    images, or there are no views or no points."""
    views = inputs.views
    if not (conf.photometry is not None and conf.photometry.enabled and views is not None
            and conf.source == "images" and len(views) and len(points)):
        return inputs, {"enabled": False}
    photometry = estimate_gains(views, points, conf.photometry, progress=progress, executor=executor)
    # which (frame, camera) each gain belongs to, in the order of views_from_dataset
    exposure = {"views": [[f, c] for f in inputs.frames for c in range(inputs.cameras)],
                "gains": photometry.gains.tolist()}
    return replace(inputs, views=replace(views, gains=photometry.gains), exposure=exposure), photometry.report()


def model_info(conf: BuildConfig, inputs: BuildInputs, cloud_path, dataset_dir, poses) -> dict:
    """The model's build info: the texture source, the cloud, dataset and poses file (absolute:
    the model means the same from any directory, the viewer finds the poses), the held-out
    frames and the exposure of each view (eval gives a held-out frame its neighbours')."""
    info = {"source": conf.source, "occlusion_aware": conf.sampling.occlusion,
            "cloud": str(Path(cloud_path).resolve()),
            "dataset": None if dataset_dir is None else str(Path(dataset_dir).resolve()),
            "held_out_frames": inputs.held_out}
    if inputs.exposure is not None:
        info["exposure"] = inputs.exposure
    if poses is not None and dataset_dir is not None:
        info["poses"] = str(Path(poses).resolve())
    return info


def sees_any(views: Views, points: np.ndarray, max_distance: float, sample: int = 50_000,
             batch: int = 64) -> bool:
    """Whether any view sees any of (every n-th of) ``points`` (m, 3) float64 world: in front of
    it, inside its image and nearer than ``max_distance`` (m, beyond which the sampler uses no
    camera). A cheap test (a sample, projected into ``batch`` views at a time), not occlusion."""
    pts = points[::max(1, -(-len(points) // sample))]
    for b in range(0, len(views), batch):
        T, K = views.world_from_cam[b:b + batch], views.K[b:b + batch]
        rel = pts[None, :, :] - T[:, None, :3, 3]                          # (v, n, 3)
        cam = np.matmul(rel, T[:, :3, :3])                                  # R^T (p − C)
        z = cam[..., 2]
        front = (z > 1e-3) & (np.einsum("vnk,vnk->vn", rel, rel) < max_distance ** 2)
        z = np.where(front, z, 1.0)
        u = K[:, None, 0, 0] * cam[..., 0] / z + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * cam[..., 1] / z + K[:, None, 1, 2]
        w, h = views.sizes[b:b + batch, 0, None], views.sizes[b:b + batch, 1, None]
        if np.any(front & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)):
            return True
    return False


def _box(xyz: np.ndarray) -> str:
    """'[x0, y0, z0] … [x1, y1, z1]' of (n, 3) positions, metres."""
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    return f"[{', '.join(f'{x:.1f}' for x in lo)}] … [{', '.join(f'{x:.1f}' for x in hi)}] m"
