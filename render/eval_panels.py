"""The side-by-side images of a novel-view evaluation: the truth beside each method's image,
labelled with its PSNR."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from core.fileio import write_png
from core.metrics import psnr

from .eval_views import EvalView


def _panel(image: np.ndarray, width: int, label: str) -> np.ndarray:
    """``image`` (h, w, 3) uint8 resized to ``width`` pixels wide (aspect kept), ``label`` written
    in white with a black outline at its top-left corner."""
    h, w = image.shape[:2]
    height = max(1, round(h * width / w))
    out = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA if width < w else cv2.INTER_LINEAR)
    # a black outline: the white text shifted by one pixel each way (a thicker stroke
    # would advance the glyphs further and not line up)
    for dx, dy in ((-1, -1), (-1, 1), (1, -1), (1, 1), (0, 0)):
        colour = (255, 255, 255) if (dx, dy) == (0, 0) else (0, 0, 0)
        cv2.putText(out, label, (6 + dx, 16 + dy), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return out


def write_side_by_side(out_dir: Path, views: list[EvalView], images: dict, methods: tuple[str, ...],
                       panel_width: int, truth_label: str = "ground truth") -> list[str]:
    """For each view ``view_NNNNNN_{on,off}_path.png``: ground truth (``truth_label``) |
    each of ``methods`` (those drawn in ``images``), each ``panel_width`` pixels wide,
    labelled; side by side, or one above the other for images more than twice as wide
    as high. Returns the names."""
    names = []
    for i, view in enumerate(views):
        panels = [_panel(view.truth, panel_width, truth_label)]
        for method in methods:
            if (method, i) in images:
                image = images[method, i]
                where = "below horizon" if truth_label == "real" else "seen"
                panels.append(_panel(image, panel_width, f"{method} {psnr(image, view.truth, view.seen):.1f} dB {where}"))
        name = f"view_{view.frame:06d}_{view.where.replace(' ', '_')}.png"
        wide = view.size[0] > 2 * view.size[1]  # a wide camera (KITTI's 3.3:1) reads better stacked
        write_png(out_dir / name, np.concatenate(panels, axis=0 if wide else 1))
        names.append(name)
    return names
