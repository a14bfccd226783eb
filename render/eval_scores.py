"""The scores of a novel-view evaluation: PSNR and SSIM of each method's image against a view's
truth over the whole image and over its masks (geometry, seen, covered), every method on every
view, their means per method and kind of viewpoint, and the work-precision points."""

from __future__ import annotations

import logging
import time

import numpy as np

from billboards.geometry import BILLBOARD, FACADE, GROUND, PLANE
from core.metrics import psnr, ssim

from .eval_config import TRAINING, WHERE
from .eval_methods import SYNTHESISED, Method
from .eval_views import EvalView

logger = logging.getLogger(__name__)

METRICS = ("psnr", "psnr_geometry", "psnr_seen", "psnr_covered", "ssim", "ssim_geometry", "ssim_seen", "ssim_covered")
#: The model's error split by the kind of quad that draws a pixel (PSNR over seen pixels), and for a
#: real capture by the horizon (PSNR over covered pixels above and below it).
KIND_NAMES = {FACADE: "facade", GROUND: "ground", BILLBOARD: "billboard", PLANE: "plane"}
#: … and synthesised ground apart: over the pixels with geometry (no capture camera saw it, so it
#: draws no seen pixel), with the share of those pixels it draws.
SPLIT_METRICS = tuple(f"psnr_seen_{name}" for name in KIND_NAMES.values()) + (
    "psnr_geometry_synthesised", "synthesised_fraction", "psnr_covered_above", "psnr_covered_below")


def exposure_matched(image: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (h, w, 3) uint8 times the per-channel gain that best fits ``truth`` over
    ``mask`` (h, w) bool in the least-squares sense (clipped to uint8): a real held-out
    frame has its own exposure and white balance, which no model can know."""
    a = image[mask].astype(np.float64)
    b = truth[mask].astype(np.float64)
    denominator = (a * a).sum(axis=0)
    gain = np.where(denominator > 0, (a * b).sum(axis=0) / np.maximum(denominator, 1e-12), 1.0)
    return np.clip(np.rint(image * gain), 0, 255).astype(np.uint8)


def score(image: np.ndarray, view: EvalView, covered: np.ndarray | None = None, real: bool = False) -> dict:
    """The metrics of ``image`` (h, w, 3) uint8 against the view's ground truth; with
    ``covered`` (h, w) bool (the pixels the method draws) also over those, and for a
    ``real`` view also over those after :func:`exposure_matched` ("psnr_covered_exposure")."""
    out = {}
    masks = [("", None), ("_geometry", view.geometry), ("_seen", view.seen)]
    if covered is not None:
        masks.append(("_covered", covered))
    for suffix, mask in masks:
        out["psnr" + suffix] = psnr(image, view.truth, mask)
        out["ssim" + suffix] = ssim(image, view.truth, mask)
    if view.near is not None:
        out["psnr_seen_near"] = psnr(image, view.truth, view.near)
    if real and covered is not None:
        out["psnr_covered_exposure"] = (psnr(exposure_matched(image, view.truth, covered), view.truth, covered)
                                        if covered.any() else float("nan"))
    return out


def evaluate_methods(methods: dict[str, Method], views: list[EvalView], images: dict | None = None,
                     keep: tuple[str, ...] = ()) -> tuple[list[dict], dict[str, dict]]:
    """Score every method on every view, one method at a time (a method with ``release()``
    is released after its views). Returns per-view rows and per-method info (bytes,
    seconds). ``images``: filled with {(method, view index): image} for methods in ``keep``."""
    rows, info = [], {}
    for name, method in methods.items():
        t0 = time.perf_counter()
        for i, view in enumerate(views):
            t1 = time.perf_counter()
            image = method(view.K, view.world_from_cam, view.size)
            gain = getattr(method, "gains", {}).get(view.frame)
            if gain is not None:  # the model's one exposure → the frame's own (a real capture's held-out frame)
                image = np.clip(np.rint(image * gain), 0, 255).astype(np.uint8)
            render_s = time.perf_counter() - t1
            # Coverage: the share of seen pixels the method draws (baselines draw black elsewhere).
            drawn = (method.covered(view.K, view.world_from_cam, view.size) if hasattr(method, "covered")
                     else np.any(image != 0, axis=-1))
            coverage = float(drawn[view.seen].mean()) if view.seen.any() else float("nan")
            split = {}
            if view.real:   # above and below the horizon (geometry: the pixels below it)
                split = {"psnr_covered_above": psnr(image, view.truth, drawn & ~view.geometry),
                         "psnr_covered_below": psnr(image, view.truth, drawn & view.geometry)}
            kinds = method.kinds(view.K, view.world_from_cam, view.size) if hasattr(method, "kinds") else None
            if kinds is not None and not view.real:
                split = {f"psnr_seen_{kind_name}": psnr(image, view.truth, view.seen & (kinds == kind))
                         for kind, kind_name in KIND_NAMES.items()}
                synthesised = view.geometry & (kinds == SYNTHESISED)
                split.update(psnr_geometry_synthesised=psnr(image, view.truth, synthesised),
                             synthesised_fraction=float(synthesised.sum() / max(int(view.geometry.sum()), 1)))
            rows.append({"frame": view.frame, "view": view.where, "method": name,
                         **score(image, view, drawn, real=view.real), **split,
                         "seen_fraction": float(view.seen.mean()), "coverage_seen": coverage, "render_s": render_s})
            if images is not None and name in keep:
                images[name, i] = image
        nbytes = getattr(method, "nbytes", None)
        info[name] = {"bytes": None if nbytes is None else int(nbytes), "seconds": time.perf_counter() - t0}
        if getattr(method, "seconds", None) is not None:
            info[name]["build_s"] = float(method.seconds)
        if hasattr(method, "release"):
            method.release()
        logger.info("%s: %s", name, ", ".join(
            f"{w} {_nanmean([r['psnr_seen'] for r in rows if r['method'] == name and r['view'] == w]):.2f} dB seen"
            for w in (*WHERE, TRAINING)))
    return rows, info


def summarise(rows: list[dict]) -> dict[str, dict]:
    """Mean of each metric per "method, view" (NaN-ignoring; NaN when no view measured it)."""
    summary = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        for where in (*WHERE, TRAINING):
            sel = [r for r in rows if r["method"] == method and r["view"] == where]
            if not sel:
                continue
            summary[f"{method}, {where}"] = {k: _nanmean([r.get(k, float("nan")) for r in sel])
                                             for k in (*METRICS, "psnr_covered_exposure", "psnr_seen_near",
                                                       "seen_fraction",
                                                       "coverage_seen", *SPLIT_METRICS)}
    return summary


def _nanmean(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def work_precision_points(summary: dict, method_info: dict, poisson_depth: int) -> list[dict]:
    """One point per method: family ("model", "Poisson mesh", "point projection" or the
    method's name), label, bytes and the seen-pixel PSNR on and off path."""
    points = []
    for name, info in method_info.items():
        if name == "Poisson mesh" or name.startswith("Poisson depth "):
            family = "Poisson mesh"
            label = f"depth {poisson_depth if name == 'Poisson mesh' else int(name.rsplit(' ', 1)[1])}"
        elif name == "model" or name.startswith("model: "):
            family, label = "model", name.split(": ", 1)[1] if ": " in name else "model"
        else:
            family, label = name, name
        points.append({"method": name, "family": family, "label": label, "bytes": info["bytes"],
                       **{f"psnr_seen_{w.replace(' ', '_')}": summary.get(f"{name}, {w}", {}).get("psnr_seen",
                                                                                                 float("nan"))
                          for w in WHERE}})
    return points

