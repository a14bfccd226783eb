"""The scale of a capture without poses (photos, video): :func:`capture_scale` says where it
comes from, :func:`scale_factor` applies it to SfM's camera positions.

One moving camera has no scale. The importers record what the user knows in
``dataset.json`` "source": the metres between consecutive frames (``--step-length``), or
the photos' EXIF GPS positions as east/north/up metres ("gps_enu_m"); without either the
model stays in SfM's own units.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from capture.dataset import Dataset
from core import DataFormatError
from core.fileio import read_json

logger = logging.getLogger(__name__)

__all__ = ["CaptureScale", "MIN_GPS_SPAN", "capture_scale", "scale_factor"]

#: GPS positions fix SfM's scale only where two of them lie this far apart (metres): a phone's
#: GPS errs by a few metres.
MIN_GPS_SPAN = 20.0
#: At most this many frames, evenly spread, are paired to fix the scale by GPS (pairs grow as
#: their square).
MAX_GPS_FRAMES = 500


@dataclass(frozen=True)
class CaptureScale:
    """Where the scale of a dataset without poses comes from (``dataset.json`` "source"):
    ``kind`` "step_length" (metres between consecutive frames: ``step``), "gps" (positions
    (n, 3) float64 east/north/up metres per frame, NaN rows where a frame has none:
    ``gps``) or "arbitrary" (none: SfM's units, consecutive frames 1 unit apart)."""

    kind: str
    step: float | None = None
    gps: np.ndarray | None = None


def capture_scale(dataset: Dataset) -> CaptureScale:
    """The scale a dataset without poses asks SfM for: its "source" "step_length" (the
    importers' ``--step-length``) when given, else its "gps_enu_m" positions, else none."""
    path = dataset.root / "dataset.json"
    source = read_json(path).get("source", {}) if path.is_file() else {}
    source = source if isinstance(source, dict) else {}
    value = source.get("step_length")
    if value is not None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
            raise DataFormatError(path, f"source.step_length must be a positive number of metres, got {value!r}")
        return CaptureScale("step_length", step=float(value))
    gps = source.get("gps_enu_m")
    if gps is not None:
        try:
            positions = np.asarray(gps, dtype=np.float64)
        except (TypeError, ValueError):
            positions = np.zeros((0,))
        if positions.shape != (dataset.num_frames, 3) or not np.isfinite(positions).all():
            raise DataFormatError(path, f"source.gps_enu_m must hold {dataset.num_frames} finite [east, north, up] "
                                        "positions, one per frame")
        return CaptureScale("gps", gps=positions)
    return CaptureScale("arbitrary")


def scale_factor(scale: CaptureScale, positions: np.ndarray, ok: np.ndarray) -> tuple[float, str]:
    """The factor that brings SfM ``positions`` (m, 3) of frames ``ok`` (m,) int to the capture's
    scale, and the scale's kind as applied ("gps" falls back to "arbitrary" when the positions
    span less than :data:`MIN_GPS_SPAN`)."""
    gaps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    adjacent = gaps[np.diff(ok) == 1]  # frames next to each other in the capture, where there are any
    median = float(np.median(adjacent if adjacent.size else gaps)) if gaps.size else 0.0
    if scale.kind == "gps":
        pick = np.linspace(0, len(ok) - 1, min(len(ok), MAX_GPS_FRAMES)).round().astype(np.int64)
        g, positions = scale.gps[ok][pick], positions[pick]  # pairs of at most MAX_GPS_FRAMES frames
        i, j = np.triu_indices(len(pick), k=1)
        far = np.linalg.norm(g[i] - g[j], axis=1) >= MIN_GPS_SPAN
        sfm = np.linalg.norm(positions[i] - positions[j], axis=1)
        far &= sfm > 1e-12
        if far.any():
            # pairs far apart: the GPS error is small against their distance
            return float(np.median(np.linalg.norm(g[i[far]] - g[j[far]], axis=1) / sfm[far])), "gps"
        logger.warning("the photos' GPS positions span less than %g m: too little to scale SfM by; the model "
                       "stays in arbitrary units", MIN_GPS_SPAN)
    step = scale.step if scale.kind == "step_length" else 1.0
    return (step / median if median > 1e-12 else 1.0), ("step_length" if scale.kind == "step_length" else "arbitrary")
