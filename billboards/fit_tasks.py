"""The fit as the build runs it, in worker tasks (:mod:`billboards.fit` holds the maths).

1. The sampled textures of every quad lie in a memory-mapped (n, d, t, t, 4) uint8 file.
2. A batch of training views is ray cast against them (:func:`billboards.fit_cast.cast_view`, with
   the alpha the sampling gave) and its measurements written to one ``.npy`` file of
   :func:`~billboards.fit.record_dtype` rows sorted by quad (:func:`write_view_records`).
3. A range of quads reads its rows from every batch's file (:func:`read_records`), takes
   the eigen-textures of its sampled textures and solves their colours
   (:func:`fit_range`); the build then quantises them as it does sampled ones. :func:`fit_report` sums the ranges' residuals per iteration for the build report.
"""

from __future__ import annotations

import os
import time

import numpy as np

from core.arrays import sorted_span
from core.fileio import atomic_path
from core.metrics import psnr_from_mse

from .fit import FitConfig, Quads, problem, record_dtype, solve, transient_rows
from .fit_cast import Hits, cast_view, view_records
from .fit_subspace import slots, subspace, with_slots
from .pca import EigenTextures, PcaConfig, eigen_textures
from .views import Views


def unoccluded(hits: Hits, K: np.ndarray, depth: np.ndarray, scale: int, margin: float, rel: float) -> np.ndarray:
    """(r,) bool: the hits that nothing of a z-buffer lies in front of. depth (zh, zw) float32
    z-depth (m, inf where empty) at 1/``scale`` of the image's resolution
    (:func:`billboards.voxels.zbuffer`'s conservative ``nearest``); a hit counts as hidden
    when its z-depth is beyond the buffer's by more than ``margin`` m + ``rel`` of it."""
    u, v = hits.pixel[:, 0].astype(np.float64), hits.pixel[:, 1].astype(np.float64)
    z = hits.distance / np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
    zh, zw = depth.shape
    iu = np.clip(((u + 0.5) / scale).astype(np.int64), 0, zw - 1)
    iv = np.clip(((v + 0.5) / scale).astype(np.int64), 0, zh - 1)
    front = depth[iv, iu].astype(np.float64)
    return ~(z > front * (1.0 + rel) + margin)


def write_view_records(path: os.PathLike | str, quads: Quads, rgba: np.ndarray, views: Views, view_ids,
                       config: FitConfig, max_distance: float, occluders=None) -> dict:
    """Ray cast views ``view_ids`` (of ``views``, images divided by their gains) against
    ``quads`` with the alpha of ``rgba`` (n, d, t, t, 4) uint8 and write their measurements
    to ``path`` (sorted by quad, atomically). ``occluders``: for a tile, whose neighbours'
    quads are not among ``quads``, a function of a view's index → (depth, scale, margin, rel)
    of :func:`unoccluded`; a hit behind what that z-buffer holds (a neighbour's wall in front)
    is no measurement. Returns {"views", "rays", "records", "hidden", "cast_s"}."""
    t0 = time.perf_counter()
    n, d, t = rgba.shape[:3]
    alpha = rgba.reshape(n, d, t * t, 4)[..., 3]
    out, rays, hidden = [], 0, 0
    for i in view_ids:
        w, h = (int(s) for s in views.sizes[i])
        stride = config.stride((w, h))
        hits = cast_view(quads, alpha, views.K[i], views.world_from_cam[i], (w, h), stride=stride,
                         max_distance=max_distance, see_through=config.see_through)
        rays += len(range(0, w, stride)) * len(range(0, h, stride))
        if occluders is not None and len(hits.quad):
            seen = unoccluded(hits, views.K[i], *occluders(int(i)))
            hidden += int((~seen).sum())
            hits = Hits(*(getattr(hits, f)[seen] for f in Hits.__dataclass_fields__))
        if len(hits.quad):
            out.append(view_records(hits, views.image(int(i))))
    records = np.concatenate(out) if out else np.zeros(0, record_dtype(quads.corners))
    records = records[np.argsort(records["quad"], kind="stable")]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, records)
    return {"views": len(view_ids), "rays": rays, "records": len(records), "hidden": hidden,
            "cast_s": time.perf_counter() - t0}


def read_records(paths, begin: int, end: int) -> np.ndarray:
    """The rows of quads [begin, end) from every file of ``paths`` (each sorted by quad)."""
    parts = []
    for path in paths:
        rec = np.load(path, mmap_mode="r")
        if len(rec) == 0:
            continue
        lo, hi = sorted_span(rec["quad"], begin, end)
        parts.append(np.array(rec[lo:hi]))
    return np.concatenate(parts) if parts else None


def fit_range(quads: Quads, rgba: np.ndarray, begin: int, end: int, records: np.ndarray | None,
              config: FitConfig, deadline: float | None, pca: PcaConfig) -> tuple[EigenTextures, dict]:
    """The eigen-textures of quads [begin, end): those of their sampled textures in ``rgba``
    (n, d, t, t, 4) uint8 (also what a slit's block outside the range holds), their colour
    slots then solved against ``records`` (:mod:`billboards.fit_subspace`). Returns them
    (alpha, coefficients and ranks as sampled) and statistics: the squared residual (0..1
    colours, summed over channels) of the measurements kept before and after each
    iteration, the seconds at each, the measurements kept, and the transients left out
    with their squared residual before and after."""
    t0 = time.perf_counter()
    n, d, t = rgba.shape[:3]
    mine = np.array(rgba[begin:end])
    eig = eigen_textures(mine.reshape(end - begin, d, t * t * 4).astype(np.float32) / 255.0, pca)
    if records is None or len(records) == 0:
        return eig, {"measurements": 0, "transients": 0, "residual": [0.0], "transients_residual": [0.0, 0.0],
                     "seconds": [time.perf_counter() - t0]}
    prob = subspace(problem(quads, records, begin, end - begin, rgba.reshape(n, d, t * t, 4)), eig)
    z0 = slots(eig, t * t)
    passing = (transient_rows(prob, z0, config.transients) if config.transients is not None
               else np.zeros(len(prob.y), bool))
    left_out = prob.rows(passing)
    z, history, seconds = solve(prob.rows(~passing), z0, config.prior, config.iterations, deadline, clip=False)
    setup = time.perf_counter() - t0 - seconds[-1]
    return with_slots(eig, z), {
        "measurements": int((~passing).sum()), "transients": int(passing.sum()), "residual": history,
        "transients_residual": [float(np.square(left_out.apply(v) - left_out.y).sum()) for v in (z0, z)],
        "seconds": [setup + s for s in seconds]}


def fit_report(stats: list[dict], casts: list[dict], config: FitConfig, seconds: float) -> dict:
    """The build report's "fit": per iteration the training pixels' RMS error and PSNR in the
    fit's own rendering (every range's residual at that iteration, or its last if it
    stopped earlier) and the worker seconds spent by then; the views, rays, measurements
    and the measurements left out as transients (not in that residual; the PSNR of all the
    measurements, theirs too, before and after)."""
    measured = sum(s["measurements"] for s in stats)
    longest = max((len(s["residual"]) for s in stats), default=1)
    curve = []
    for k in range(longest):
        sq = sum(s["residual"][min(k, len(s["residual"]) - 1)] for s in stats)
        worker_s = sum(s["seconds"][min(k, len(s["seconds"]) - 1)] for s in stats)
        mse = sq / (3 * measured) if measured else float("nan")
        curve.append({"iteration": k, "rms": float(np.sqrt(mse)) if measured else None,
                      "psnr_db": psnr_from_mse(mse) if measured else None, "worker_s": worker_s})
    # every measurement, the transients left out too: what the training images see of the change
    everything = measured + sum(s["transients"] for s in stats)
    whole = [sum(s["residual"][k] + s["transients_residual"][j] for s in stats) for j, k in ((0, 0), (1, -1))]
    whole_db = [psnr_from_mse(sq / (3 * everything)) if everything else None for sq in whole]
    return {"enabled": True, "config": {k: getattr(config, k) for k in config.__dataclass_fields__},
            "views": sum(c["views"] for c in casts), "rays": sum(c["rays"] for c in casts),
            "measurements": int(measured), "transients": sum(s.get("transients", 0) for s in stats),
            "cast_worker_s": sum(c["cast_s"] for c in casts),
            "iterations": curve, "seconds": seconds,
            "psnr_before_db": curve[0]["psnr_db"], "psnr_after_db": curve[-1]["psnr_db"],
            "psnr_all_before_db": whole_db[0], "psnr_all_after_db": whole_db[1]}
