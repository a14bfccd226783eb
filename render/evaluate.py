"""Novel-view quality of a billboard model against the ground-truth renderer (``bbcity eval``).

Viewpoints: capture viewpoints (camera 0 of frames spread along the path; the frames
the model was built without, ``bbcity build --holdout N``, when it has them: "on path")
and the same cameras moved 2 m sideways, away from the facade they look at, and 1 m up
("off path"). The ground truth of each is :func:`data_synth.truth_view`.

Methods are a dict name → callable ``(K (3, 3), world_from_cam (4, 4), size (w, h)) →
(h, w, 3) uint8``; a callable's ``nbytes`` attribute (when it has one) is its size.

- ``model``: the billboard model (GPU decode, over its sky when it has one, else black);
  bytes: the model's arrays (+ the sky's bins).
- ``billboards only``: a model of the same cloud built without the facade layer
  (``bbcity build --layer none``), when given (``billboards_only=``).
- ``Poisson mesh``: the fused cloud meshed by screened Poisson reconstruction (depth
  10), ray cast with interpolated vertex colours (:class:`render.baselines.PoissonMesh`).
- ``point projection``: the fused cloud projected by Open3D, one pixel per point.
- for the work-precision diagram: Poisson meshes of other depths (8, 9, 11) and other
  models (e.g. other settings of the same build), on every view too.

Scores: PSNR and SSIM over the whole image, over the pixels where the ground truth has
geometry, over the *seen* pixels, those showing a surface that some capture camera
used for the textures saw (:mod:`render.seen`): the fair measure of what the capture
can tell, and over the pixels each method *covers* (draws). Baselines render black where
they have nothing; the model's sky (if any) fills its background, which shows in
whole-image scores only.

A real capture (a dataset without ``gt/``) has no ground-truth renderer: its views are
the held-out frames' own camera-0 images, on path only ("real" views). There, geometry
and seen pixels are the pixels below the horizon (rays pointing down: road, cars,
facades' lower storeys; the sky and tree tops above it are background), and coverage is
the share of those that a method draws.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from billboards.decode import decode_directions
from billboards.fit import quads_of
from billboards.fit_cast import cast_view
from billboards.geometry import BILLBOARD, FACADE, GROUND
from billboards.model_set import ModelSet
from core.errors import InputError
from core.metrics import psnr, ssim
from data_synth import load_dataset, load_scene, truth_view

from .baselines import PointProjector, PoissonMesh  # noqa: F401  (PointProjector: public here as before)
from .seen import SeenConfig, seen_in_dataset

logger = logging.getLogger(__name__)

BACKGROUND = (0.0, 0.0, 0.0)

#: A method: (K (3, 3), world_from_cam (4, 4), size (w, h)) → (h, w, 3) uint8.
Method = Callable[[np.ndarray, np.ndarray, tuple], np.ndarray]

METRICS = ("psnr", "psnr_geometry", "psnr_seen", "psnr_covered", "ssim", "ssim_geometry", "ssim_seen", "ssim_covered")
#: The model's error split by the kind of quad that draws a pixel (PSNR over seen pixels), and for a
#: real capture by the horizon (PSNR over covered pixels above and below it).
SYNTHESISED = 3  # not a kind of quad: ground blocks whose texture was synthesised (no camera saw them)
KIND_NAMES = {FACADE: "facade", GROUND: "ground", BILLBOARD: "billboard"}
#: … and synthesised ground apart: over the pixels with geometry (no capture camera saw it, so it
#: draws no seen pixel), with the share of those pixels it draws.
SPLIT_METRICS = tuple(f"psnr_seen_{name}" for name in KIND_NAMES.values()) + (
    "psnr_geometry_synthesised", "synthesised_fraction", "psnr_covered_above", "psnr_covered_below")
_UNUSED_COLOUR = (1.0, 0.0, 1.0)  # background for finding the pixels a model draws (magenta, absent from streets)
WHERE = ("on path", "off path")
#: Viewpoints of frames the textures came from: the ceiling a model reaches where it was made.
TRAINING = "training"


@dataclass(frozen=True)
class EvalConfig:
    views: int | None = None                # viewpoints: held-out frames when the model has them (synthetic: each also
                                            # off path); None: 8 synthetic, every held-out frame of a real capture
    size: tuple[int, int] | None = None     # image size (w, h); None: the dataset camera's
    sideways: float = 2.0                   # off-path views: moved this far back horizontally (m) …
    up: float = 1.0                         # … and this far up (m)
    poisson_depth: int = 10                 # octree depth of the "Poisson mesh" baseline
    workprecision_depths: tuple[int, ...] = (8, 9, 10, 11)  # Poisson depths of the work-precision diagram
    trim_quantile: float = 0.05             # Poisson vertices below this density quantile are removed
    seen: SeenConfig = field(default_factory=SeenConfig)     # the seen-pixel test
    panel_width: int = 320                  # side-by-side images: width of each panel (0: none written)
    model_sky: bool = True                  # draw models over their sky (False: on black, like the baselines)
    training_views: int = 4                 # also this many viewpoints of frames the textures came from ("training",
                                            # the capture camera itself; none when no frame was held out)
    near: float = 5.0                       # the near field: seen pixels of a synthetic view nearer than this (m)

    def __post_init__(self):
        if self.views is not None and self.views < 1:
            raise InputError(f"views must be ≥ 1, got {self.views}")
        if isinstance(self.views, bool) or (self.size is not None and any(isinstance(s, bool) for s in self.size)):
            raise InputError(f"views and size must be integers, got {self.views!r}, {self.size!r}")
        if self.size is not None and (len(self.size) != 2 or min(int(s) for s in self.size) < 1):
            raise InputError(f"size must be two positive integers (w, h), got {self.size}")
        if not all(1 <= int(d) <= 16 for d in (self.poisson_depth, *self.workprecision_depths)):
            raise InputError("Poisson depths must lie in [1, 16]")
        if not 0 <= self.trim_quantile < 1 or self.panel_width < 0:
            raise InputError("trim_quantile must be in [0, 1) and panel_width ≥ 0")
        if isinstance(self.training_views, bool) or self.training_views < 0:
            raise InputError(f"training_views must be an integer ≥ 0, got {self.training_views!r}")
        if not (math.isfinite(self.sideways) and math.isfinite(self.up)):
            raise InputError("sideways and up must be finite")
        if not (math.isfinite(self.near) and self.near > 0):
            raise InputError(f"near must be a finite distance > 0 (m), got {self.near}")


# --------------------------------------------------------------------------- viewpoints

def off_path(world_from_cam: np.ndarray, sideways: float = 2.0, up: float = 1.0) -> np.ndarray:
    """The camera moved ``sideways`` metres back along its horizontal viewing direction
    (away from what it looks at, toward the middle of the street) and ``up`` metres up."""
    pose = np.array(world_from_cam, dtype=np.float64)
    forward = pose[:3, 2].copy()
    forward[2] = 0.0
    norm = np.linalg.norm(forward)
    if norm > 1e-9:
        pose[:3, 3] -= sideways * forward / norm
    pose[2, 3] += up
    return pose


# --------------------------------------------------------------------------- views

@dataclass(eq=False)
class EvalView:
    """One viewpoint with its ground truth: truth (h, w, 3) uint8; geometry (h, w) bool
    (the ground truth hits a surface); seen (h, w) bool (a capture camera saw it); real:
    the truth is a captured image (geometry and seen: the pixels below the horizon); near
    (h, w) bool: seen pixels nearer than :attr:`EvalConfig.near` (None: not known)."""

    frame: int
    where: str              # "on path" | "off path"
    K: np.ndarray
    world_from_cam: np.ndarray
    size: tuple[int, int]
    truth: np.ndarray
    geometry: np.ndarray
    seen: np.ndarray
    real: bool = False
    near: np.ndarray | None = None


def choose_frames(info: dict | None, num_frames: int, views: int | None,
                  posed: np.ndarray | None = None) -> tuple[np.ndarray, list[int], bool]:
    """(frames, texture_frames, held_out): up to ``views`` frames (None: all) spread over the
    frames a model left out of its textures (``info["held_out_frames"]``), else over all
    frames; the frames the textures came from; whether the viewpoints were held out.
    posed: (num_frames,) bool, the frames that have a pose (None: all); the others are
    never chosen."""
    posed = np.ones(num_frames, bool) if posed is None else np.asarray(posed, bool)
    held = sorted({int(f) for f in (info or {}).get("held_out_frames", []) or []
                   if 0 <= int(f) < num_frames and posed[int(f)]})
    pool = np.asarray(held) if held else np.flatnonzero(posed)
    views = len(pool) if views is None else views
    frames = np.unique(pool[np.linspace(0, len(pool) - 1, max(1, views)).round().astype(int)])
    texture_frames = [f for f in range(num_frames) if f not in set(held) and posed[f]]
    return frames, texture_frames, bool(held)


def training_frames(texture_frames, count: int) -> np.ndarray:
    """(k,) int64: up to ``count`` of ``texture_frames`` (the frames the textures came from),
    spread evenly over them."""
    pool = np.asarray(texture_frames, np.int64)
    if count <= 0 or len(pool) == 0:
        return np.zeros(0, np.int64)
    return np.unique(pool[np.linspace(0, len(pool) - 1, count).round().astype(int)])


def view_camera(rig, size: tuple[int, int] | None) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """Camera 0 of ``rig`` rendered at ``size`` (w, h; None: its own): K (3, 3) float64
    scaled to that size, the size, and the camera's own size."""
    K = rig.intrinsics[0]
    native = tuple(int(s) for s in rig.sizes[0])
    size = native if size is None else tuple(int(s) for s in size)
    if size != native:
        K = np.diag([size[0] / native[0], size[1] / native[1], 1.0]) @ K
    return K, size, native


def prepare_views(dataset_dir: os.PathLike | str, frames, texture_frames, config: EvalConfig = EvalConfig(),
                  progress: Callable[[str], None] | None = None, training=()) -> list[EvalView]:
    """Ground truth, geometry and seen masks of each frame's camera-0 viewpoint, on and off path;
    and of each of ``training`` (frames the textures came from) at the capture camera itself."""
    ds = load_dataset(dataset_dir)
    if not ds.has_ground_truth:
        raise InputError(f"{dataset_dir}: evaluation needs a dataset with ground truth (gt/)")
    scene = load_scene(dataset_dir)
    K, size, _ = view_camera(ds.rig, config.size)
    views = []
    poses = [(f, where, pose) for f in frames
             for where, pose in (("on path", ds.world_from_cam(int(f), 0)),
                                 ("off path", off_path(ds.world_from_cam(int(f), 0), config.sideways, config.up)))]
    poses += [(f, TRAINING, ds.world_from_cam(int(f), 0)) for f in training]
    for f, where, pose in poses:
        truth, depth = truth_view(scene, K, pose, size)
        seen = seen_in_dataset(depth, K, pose, ds, texture_frames, config.seen)
        near = seen & (np.nan_to_num(depth, nan=np.inf) < config.near)
        views.append(EvalView(int(f), where, K, pose, size, truth, np.isfinite(depth), seen, near=near))
        if progress is not None:
            progress(f"frame {int(f)} {where}: {seen.mean():.0%} of the pixels seen")
    return views


def below_horizon(K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: the pixels whose viewing ray points down (world z < 0) — for a camera on
    a car, everything that is ground or stands on it, never the sky."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    return (rays @ np.asarray(world_from_cam, np.float64)[:3, :3].T)[..., 2] < 0


def prepare_real_views(dataset, frames, config: EvalConfig = EvalConfig(), where: str = "on path") -> list[EvalView]:
    """The camera-0 images of ``frames`` of a real capture as views (``where``: "on path" for
    held-out frames, :data:`TRAINING` for frames the textures came from; geometry and seen
    pixels: those below the horizon)."""
    K, size, native = view_camera(dataset.rig, config.size)
    views = []
    for f in frames:
        pose = dataset.world_from_cam(int(f), 0)
        truth = dataset.image(int(f), 0)
        if size != native:
            truth = cv2.resize(truth, size, interpolation=cv2.INTER_AREA)
        ground = below_horizon(K, pose, size)
        views.append(EvalView(int(f), where, K, pose, size, truth, ground, ground, real=True))
    return views


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


# --------------------------------------------------------------------------- methods

class ModelMethod:
    """A billboard model (or a tiled one, a :class:`~billboards.model_set.ModelSet`, every tile a
    view sees drawn) as a method (GPU decode, offscreen), over ``sky`` when given.

    visible: None (every quad) or the indices drawn; nbytes: the model's bytes (a set: its
    tiles' bytes on disk; + the sky's);
    gains: frame → (3,) float64 exposure gain that :func:`evaluate_methods` applies to the
    view of that frame (see :func:`neighbour_gains`); renders: a dict shared by methods of the
    same model and settings, so that each view is drawn once (None: no caching)."""

    def __init__(self, model, sky=None, visible=None, nbytes: int | None = None, decode: str = "gpu",
                 gains: dict[int, np.ndarray] | None = None, renders: dict | None = None):
        self.model, self.sky, self.visible, self.decode = model, sky, visible, decode
        self.gains = gains or {}
        self.renders = renders
        model_bytes = model.bytes if isinstance(model, ModelSet) else model.nbytes()["total"]
        self.nbytes = int(model_bytes + (sky.colours.nbytes if sky is not None else 0) if nbytes is None else nbytes)

    def _draw(self, K, world_from_cam, size, sky, background) -> np.ndarray:
        from .offscreen import render_view

        key = (np.asarray(K).tobytes(), np.asarray(world_from_cam).tobytes(), tuple(size), background)
        if self.renders is not None and key in self.renders:
            return self.renders[key]
        image = render_view(self.model, K, world_from_cam, size, decode=self.decode, visible=self.visible,
                            sky=sky, background=background)
        if self.renders is not None:
            self.renders[key] = image
        return image

    def __call__(self, K, world_from_cam, size) -> np.ndarray:
        return self._draw(K, world_from_cam, size, self.sky, BACKGROUND)

    def kinds(self, K, world_from_cam, size) -> np.ndarray | None:
        """(h, w) int8: the kind of quad the model draws at each pixel (−1: none; :data:`SYNTHESISED`
        for a synthesised ground block), found by ray casting its quads as the renderer places them
        (:func:`billboards.fit_cast.cast_view`); None for a tiled set."""
        if isinstance(self.model, ModelSet):
            return None
        if not hasattr(self, "_quads"):
            m = self.model
            self._quads = quads_of(m.origin, m.centres, m.base_yaw, m.kind, m.voxel_size, m.block_size, m.tile,
                                   m.yaw_offsets, m.pitches, m.pitched_quads, split=m.split, corner_dz=m.corner_dz)
            n, chunk = m.num_billboards, 1024
            self._alpha = np.concatenate([np.rint(decode_directions(m, np.arange(b, min(n, b + chunk)))[..., 3] * 255)
                                          .astype(np.uint8).reshape(-1, m.num_directions, m.tile * m.tile)
                                          for b in range(0, n, chunk)]) if n else np.zeros((0, 1, 1), np.uint8)
        hits = cast_view(self._quads, self._alpha, np.asarray(K, np.float64), np.asarray(world_from_cam, np.float64),
                         size, max_distance=np.inf)
        out = np.full((int(size[1]), int(size[0])), -1, np.int8)
        kind = np.where(self.model.synthesised > 0, SYNTHESISED, self.model.kind)
        out[hits.pixel[:, 1], hits.pixel[:, 0]] = kind[hits.quad]
        return out

    def covered(self, K, world_from_cam, size) -> np.ndarray:
        """(h, w) bool: the pixels the model draws (rendered once more over a colour no texel has)."""
        image = self._draw(K, world_from_cam, size, None, _UNUSED_COLOUR)
        return np.any(image != np.round(np.asarray(_UNUSED_COLOUR) * 255).astype(np.uint8), axis=-1)


def neighbour_gains(exposure: dict | None, frames, camera: int = 0) -> dict[int, np.ndarray]:
    """Frame → (3,) float64 gain of ``camera`` at each of ``frames``, from the gains that
    photometry found for the frames the textures came from (``exposure``: a model's
    ``info["exposure"]``, {"views": [[frame, camera], ...], "gains": [[r, g, b], ...]}):
    geometric interpolation between the nearest frames before and after (the nearest one
    at the ends). A camera's exposure drifts slowly along a drive; the held-out frame's
    own pixels are not used. Empty without ``exposure``."""
    if not exposure:
        return {}
    views = np.asarray(exposure.get("views", []), dtype=np.int64).reshape(-1, 2)
    gains = np.asarray(exposure.get("gains", []), dtype=np.float64).reshape(-1, 3)
    mine = (views[:, 1] == camera) & np.all(gains > 0, axis=1) if len(views) == len(gains) else np.zeros(0, bool)
    if not mine.any():
        return {}
    known = views[mine, 0]
    order = np.argsort(known)
    known, logs = known[order], np.log(gains[mine][order])
    out = {}
    for f in frames:
        out[int(f)] = np.exp([np.interp(f, known, logs[:, k]) for k in range(3)])
    return out


class LazyPoisson:
    """A :class:`PoissonMesh` method built on first use (meshing takes seconds to minutes),
    freed by :meth:`release` once its views are scored."""

    def __init__(self, cloud: dict, depth: int, trim_quantile: float):
        self.cloud, self.depth, self.trim_quantile = cloud, int(depth), float(trim_quantile)
        self.mesh: PoissonMesh | None = None
        self.nbytes: int | None = None
        self.seconds: float | None = None

    def __call__(self, K, world_from_cam, size) -> np.ndarray:
        if self.mesh is None:
            self.mesh = PoissonMesh(self.cloud["points"], self.cloud["colours"], self.cloud["normals"],
                                    depth=self.depth, trim_quantile=self.trim_quantile,
                                    viewpoints=self.cloud["viewpoints"])
            self.nbytes, self.seconds = self.mesh.nbytes, self.mesh.seconds
        return self.mesh.render(K, world_from_cam, size)

    def release(self) -> None:
        self.mesh = None


def read_cloud_for_baselines(cloud_path: os.PathLike | str, viewpoints: np.ndarray | None = None) -> dict:
    """The cloud as arrays: points (N, 3) float64, colours (N, 3) uint8, normals (N, 3)
    float64 or None, and ``viewpoints`` (v, 3) to orient estimated normals toward."""
    from recon.cloud_io import read_cloud

    pcd = read_cloud(cloud_path, require_colours=True)
    points = np.asarray(pcd.points).copy()
    colours = np.clip(np.rint(np.asarray(pcd.colors) * 255), 0, 255).astype(np.uint8)
    normals = np.asarray(pcd.normals).copy() if pcd.has_normals() else None
    del pcd
    return {"points": points, "colours": colours, "normals": normals, "viewpoints": viewpoints}


# --------------------------------------------------------------------------- evaluation

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


def evaluate_views(model, dataset_dir: os.PathLike | str, cloud_path: os.PathLike | str | None = None,
                   views: int | None = None, size: tuple[int, int] | None = None, *, sky=None,
                   billboards_only=None, extra_models: dict | None = None, extra_methods: dict[str, Method] | None = None,
                   config: EvalConfig | None = None, out_dir: os.PathLike | str | None = None) -> dict:
    """Novel-view scores of ``model`` (a :class:`billboards.model.BillboardModel` or a tiled
    :class:`billboards.model_set.ModelSet`, drawn over ``sky`` when given) and the baselines of the cloud at ``cloud_path`` (none without one);
    a JSON-ready dict (NaN as None).

    views, size: override ``config``'s. billboards_only: the model (or (model, sky)) of the
    same cloud built without the facade layer, scored as "billboards only". extra_models:
    label → model or (model, sky), scored as methods "model: label" (points of the
    work-precision diagram). extra_methods:
    name → :data:`Method` (e.g. a variant renderer), scored like the rest. out_dir: where
    the side-by-side images "ground truth | model | Poisson mesh" go (none if None).
    The viewpoints and the seen masks follow ``model.info`` (held-out frames).
    """
    t0 = time.perf_counter()
    config = config or EvalConfig()
    overrides = {k: v for k, v in (("views", views), ("size", tuple(size) if size is not None else None))
                 if v is not None}
    if overrides:
        config = dataclasses.replace(config, **overrides)
    if not config.model_sky:
        sky = None
        extra_models = {k: (v[0] if isinstance(v, tuple) else v) for k, v in (extra_models or {}).items()}
    ds = load_dataset(dataset_dir)
    info = model.info if isinstance(getattr(model, "info", None), dict) else {}
    real = not ds.has_ground_truth
    posed = ds.posed
    frames, texture_frames, held_out = choose_frames(info, ds.num_frames,
                                                     config.views if config.views or real else 8, posed)
    training = training_frames(texture_frames, config.training_views) if held_out else np.zeros(0, np.int64)
    if real:
        if not held_out:
            logger.warning("%s is a real capture and the model was built from every frame: the scores are of "
                           "frames it has seen (build with --holdout 4 for held-out views)", dataset_dir)
        eval_views = prepare_real_views(ds, frames, config) + prepare_real_views(ds, training, config, TRAINING)
    else:
        eval_views = prepare_views(dataset_dir, frames, texture_frames, config, progress=logger.info,
                                   training=training)

    gains = neighbour_gains(info.get("exposure"), [*frames, *training]) if real else {}
    renders: dict | None = {} if gains else None
    methods: dict[str, Method] = {"model": ModelMethod(model, sky, renders=renders)}
    if gains:
        # the model holds one exposure for the whole capture (photometry); a held-out frame had
        # its own: drawn as is, and with the exposure its neighbouring frames had (the same renders)
        methods["model, neighbours' exposure"] = ModelMethod(model, sky, gains=gains, renders=renders)
    if billboards_only is not None:
        m, s = billboards_only if isinstance(billboards_only, tuple) else (billboards_only, None)
        methods["billboards only"] = ModelMethod(m, s if config.model_sky else None)
    for label, entry in (extra_models or {}).items():
        m, s = entry if isinstance(entry, tuple) else (entry, None)
        methods[f"model: {label}"] = ModelMethod(m, s)
    methods.update(extra_methods or {})
    poisson_name = "Poisson mesh"
    if cloud_path is not None:
        viewpoints = np.stack([ds.world_from_cam(f, c)[:3, 3] for f in texture_frames
                               for c in range(ds.rig.num_cameras)]) if texture_frames else None
        cloud = read_cloud_for_baselines(cloud_path, viewpoints)
        methods[poisson_name] = LazyPoisson(cloud, config.poisson_depth, config.trim_quantile)
        for d in config.workprecision_depths:
            if int(d) != config.poisson_depth:
                methods[f"Poisson depth {int(d)}"] = LazyPoisson(cloud, int(d), config.trim_quantile)
        methods["point projection"] = PointProjector(cloud["points"], cloud["colours"])

    images: dict = {}
    drawn = ("model", *(f"model: {label}" for label in extra_models or {}), poisson_name)  # the side-by-side panels
    rows, method_info = evaluate_methods(methods, eval_views, images, keep=drawn)
    summary = summarise(rows)
    report = {
        "dataset": str(dataset_dir), "views": len(frames), "size": list(eval_views[0].size),
        "real": real, "held_out": held_out, "frames": frames.tolist(), "texture_frames": len(texture_frames),
        "training_frames": training.tolist(),
        "config": {"sideways": config.sideways, "up": config.up, "poisson_depth": config.poisson_depth,
                   "workprecision_depths": list(config.workprecision_depths),
                   "trim_quantile": config.trim_quantile, "seen": config.seen.__dict__, "near": config.near},
        "sky": sky is not None,
        "bytes": {name: i["bytes"] for name, i in method_info.items()},
        "methods": method_info,
        "summary": summary,
        "work_precision": work_precision_points(summary, method_info, config.poisson_depth),
        "per_view": rows,
    }
    if out_dir is not None and config.panel_width > 0:
        truth = "real" if real else "ground truth"
        report["images"] = write_side_by_side(Path(out_dir), eval_views, images, drawn, config.panel_width,
                                              truth_label=truth)
        report["image_panels"] = [truth, *drawn]
    report["seconds"] = time.perf_counter() - t0
    return json_ready(report)


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


def json_ready(value):
    """``value`` with non-finite floats as None (JSON null = no measurement) and numpy scalars as Python's."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# --------------------------------------------------------------------------- outputs

def _panel(image: np.ndarray, width: int, label: str) -> np.ndarray:
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
    from core.fileio import write_png

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
