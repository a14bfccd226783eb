"""The build report: the statistics of the chunks summed (:class:`Totals`), the facade layer's
counts (:func:`layer_report`), PSNR from summed squared errors; :class:`BuildResult`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.metrics import psnr_from_mse

from .build_config import BuildConfig
from .facade_truth import facade_depth_report
from .geometry import GROUND, PLANE
from .layer import Layer, LayerConfig
from .octree import Octree


@dataclass(frozen=True, eq=False)
class BuildResult:
    """What a build made: the model directory (a model or a model set) and its build report."""

    model: Path
    report: dict


def layer_report(layer: Layer, passes, points: np.ndarray, dataset, config: LayerConfig) -> dict:
    """Counts of the facade layer and, when ``dataset`` has ground truth, its facade depth against it."""
    report = {"enabled": True, "passes": len(passes), "epi_points": int(sum(len(p.points) for p in passes)),
              "facade_blocks": int((layer.kind != GROUND).sum()), "ground_blocks": int((layer.kind == GROUND).sum()),
              "side_wall_blocks": int(layer.side_wall.sum()), "kerb_blocks": int(layer.kerb.sum()),
              "ground_blocks_continued": int(layer.continued.sum()),
              "ground_blocks_unseen": int(layer.synthesised.sum()),
              "ground_blocks_by_times_split": np.bincount(layer.split[layer.kind == GROUND],
                                                          minlength=config.resolution.max_split + 1).tolist(),
              "explained_points": int(layer.explained.sum()), "points": int(len(points))}
    if layer.columns and dataset.has_ground_truth:
        report["facade_depth"] = facade_depth_report(layer.columns, points, dataset.root, config)
    return report


def psnr_db(sq_err: float, count: int) -> float | None:
    """PSNR (dB, peak 1) of a sum of squared errors over ``count`` values, capped at
    TOL.psnr_max_db for an exact decode; None when nothing was measured (valid JSON either way)."""
    return None if count == 0 else psnr_from_mse(sq_err / count)


def format_db(value: float | None) -> str:
    """A PSNR for the log: two decimals, or "n/a" when nothing was measured."""
    return "n/a" if value is None else f"{value:.2f}"


class Totals:
    """Accumulates the per-chunk statistics into the build report."""

    def __init__(self, d: int):
        self.sums: dict[str, float] = {}
        self.ranks = np.zeros(d + 1, dtype=np.int64)
        self.sampling: dict[str, int] = {}

    def add(self, stats: dict) -> None:
        """Add one chunk's (or one task's sampling) statistics."""
        for key, value in stats.items():
            if key == "ranks":
                self.ranks += np.asarray(value, dtype=np.int64)
            elif key == "sampling":
                for k, v in value.items():
                    self.sampling[k] = self.sampling.get(k, 0) + v
            else:
                self.sums[key] = self.sums.get(key, 0.0) + value

    def report(self, model, conf: BuildConfig, octree: Octree, num_views: int) -> dict:
        """The build report of ``model`` (a :class:`~billboards.model.BillboardModel`) built with
        ``conf`` over ``octree`` from ``num_views`` views: counts, bytes, ranks, PSNR, seconds."""
        s = self.sums
        raw_bytes = int(s.get("raw_values", 0))  # 8-bit RGBA samples: one byte per value
        nbytes = model.nbytes()
        last = int(np.max(np.flatnonzero(self.ranks))) if self.ranks.any() else 0
        return {
            "billboards": model.num_billboards, "voxels": octree.num_voxels, "octree_depth": octree.depth, "voxel_size": octree.voxel_size,
            "synthesised": int(np.count_nonzero(model.synthesised)),
            "planes": int(np.count_nonzero(model.kind == PLANE)),
            "nodes": int(octree.num_nodes), "views": num_views, "directions": conf.sampling.directions.num_directions,
            "tile": conf.sampling.tile, "slots": model.num_slots, "pages": len(model.pages),
            "rank_histogram": {str(r): int(c) for r, c in enumerate(self.ranks[:last + 1])},
            "mean_rank": float((self.ranks * np.arange(len(self.ranks))).sum() / max(1, self.ranks.sum())),
            "bytes": {"raw_samples": raw_bytes, "model": int(nbytes["total"]), **{k: int(v) for k, v in nbytes.items()}},
            "compression_ratio": raw_bytes / max(1, nbytes["total"]),
            "psnr_measured_on": f"every {conf.error_stride}th billboard" if conf.error_stride > 1 else "every billboard",
            "psnr": {"decoded_rgba_db": psnr_db(s.get("sq_err_decoded", 0), int(s.get("values", 0))),
                     "decoded_rgb_opaque_db": psnr_db(s.get("sq_err_decoded_rgb", 0), int(s.get("opaque_rgb_values", 0))),
                     "pca_rgba_db": psnr_db(s.get("sq_err_pca", 0), int(s.get("values", 0))),
                     "pca_rgb_opaque_db": psnr_db(s.get("sq_err_pca_rgb", 0), int(s.get("opaque_rgb_values", 0)))},
            "worker_seconds": {"sampling_s": s.get("sampling_s", 0.0), "pca_s": s.get("pca_s", 0.0),
                               "quantize_s": s.get("quantize_s", 0.0)},
            "sampling": self.sampling,
        }
