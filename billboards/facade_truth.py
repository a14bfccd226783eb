"""The facade layer's depth against the synthetic street's ground truth (the build report's
``layer.facade_depth``): each EPI column's facade offset, and a plane fitted to the cloud per
column, against the distance to the first building box."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from data_synth import load_scene
from data_synth.scene import Kind
from recon.epi import EpiPass

from .geometry import ray_box_interval
from .layer import FacadeColumns, LayerConfig, facade_columns


def facade_truth(columns: FacadeColumns, scene, height: float = 3.0) -> np.ndarray:
    """(c,) float64 true facade offset of each column: the distance from the path line, along
    the pass's facing, to the first building box, at ``height`` m (NaN: no building).
    scene: a :class:`data_synth.scene.Scene` (its building boxes)."""
    epi = columns.epi
    boxes = scene.object_bounds[scene.object_kind == Kind.BUILDING]
    start = epi.origin[None, :] + columns.centre_along()[:, None] * epi.axis[None, :]
    start[:, 2] = height
    if len(boxes) == 0:
        return np.full(len(start), np.nan)
    t_in, t_out = ray_box_interval(start[:, None, :], epi.facing[None, None, :], boxes[None, :, 0], boxes[None, :, 1])
    hit = (t_in <= t_out) & (t_out > 0)
    t = np.where(hit, np.maximum(t_in, 0.0), np.inf).min(axis=1)
    return np.where(np.isfinite(t), t, np.nan)


def facade_depth_report(columns: list[FacadeColumns], cloud: np.ndarray, dataset_dir: os.PathLike | str,
                        config: LayerConfig) -> dict:
    """Facade depth of the EPI columns and of a plane fitted to the cloud per column (the same
    histogram peak and median, on the cloud's points instead of the EPI points), each against the
    ground truth of the synthetic dataset in ``dataset_dir`` (its scene re-created): relative
    error |d − d_true| / d_true over the columns that have a building."""
    def stats(errors: np.ndarray) -> dict:
        e = errors[np.isfinite(errors)]
        if e.size == 0:
            return {"columns": 0, "median_pct": float("nan"), "p90_pct": float("nan"), "within_2pct": float("nan")}
        return {"columns": int(e.size), "median_pct": float(np.median(e) * 100),
                "p90_pct": float(np.percentile(e, 90) * 100), "within_2pct": float(np.mean(e <= 0.02))}

    scene = load_scene(dataset_dir)
    epi_err, cloud_err = [], []
    cloud = np.asarray(cloud, np.float64)
    for cols in columns:
        truth = facade_truth(cols, scene)
        epi_err.append(np.abs(cols.offset - truth) / truth)
        # The cloud's own plane per column, on the same columns.
        side = cols.epi.offset(cloud) > 0
        as_epi = EpiPass(cols.epi.origin, cols.epi.axis, cols.epi.facing, cloud[side], np.zeros(int(side.sum())),
                         np.zeros(int(side.sum()), np.int32))
        fit = facade_columns(as_epi, cloud[side], cols.size, replace(config, min_points=config.min_points * 4))
        fitted = np.full(len(cols.offset), np.nan)
        if fit is not None:
            k = np.arange(len(cols.offset)) + cols.first - fit.first
            ok = (k >= 0) & (k < len(fit.offset))
            fitted[ok] = fit.offset[k[ok]]
        cloud_err.append(np.abs(fitted - truth) / truth)
    return {"epi": stats(np.concatenate(epi_err)), "cloud_plane_fit": stats(np.concatenate(cloud_err))}
