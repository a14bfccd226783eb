"""Lazy datasets: images ray cast when they are read, from a section of the street.

A lazy dataset (``bbcity synth --lazy``, ``SynthConfig(lazy=True)``) holds what a stored one
holds except the pixels: ``dataset.json`` (with ``"images": "lazy"`` and the section
settings), ``rig.json``, ``poses.json``, ``colmap/`` and ``gt/scene.json`` (settings and
digest), a few hundred bytes per frame. Reading an image (:meth:`capture.dataset.Dataset.image`,
or :func:`capture.dataset.read_image` with the path it would have; :class:`LazyImages` is the
image source "lazy" of :mod:`capture.sources`) ray casts the frame from the capture pose its
settings make, with the renderer and settings that would have stored it; ground-truth depth
and ids (unless the settings say ``ground_truth_depth=False``) are cast the same way, without
colour.

**Sections.** A frame, lazy or stored (:func:`data_synth.write_dataset` casts the frames it
stores the same way, so both hold the same bytes), is cast against :func:`data_synth.scene_section` of the x-window
``[k·tile − reach − s, (k + 1)·tile + reach + s]``, where k = ⌊x_rig / tile⌋ is the frame's
tile (``tile`` = 50 m), s the farthest camera from the rig's origin and ``reach``
(:func:`view_reach`) the farthest along the street, from any camera of the capture, that any
of its rays (every 4th pixel corner and the image's edges, distorted ones undistorted) can meet a building, pillar,
pole or beam: the ray's run inside the slab of y and z those objects occupy, plus 5 % and
2 m. Beyond the slab a ray meets only the ground, road and sidewalks, which span the whole
street and are in every section whole. So a frame cast from its section shows what the
whole street shows: every ray meets the same triangle at the same float32 distance (Embree's
hit distance depends on the ray and the triangle, not on the other triangles), but for rays
that meet two objects at one distance exactly (the shared edge of two neighbouring, flush
facades: about one ray in a million), where which one wins depends on the ray-casting
structure; casting stored frames from the same sections makes those agree too. The default 115° portrait rig needs about 50 m (a section of 150 m of street).
A lens that sees along the street (a ray parallel to it, where no slab bounds it) is capped
at ``MAX_REACH_M`` (1 km): objects farther along than that are not drawn there (the long
surfaces and the sky are), so such a frame can differ from a stored one in those pixels.
The town is cast whole (its size does not depend on the drive's length), and so is an orbit's
street (``path`` "orbit": its cameras look every way, along the street too).

**Per process.** The few most recent sections (``SECTIONS_KEPT``) and frames
(``RESULTS_KEPT``, so that a frame's cameras, its ground truth and neighbouring frames that
motion stereo reads again are cast once) are kept; nothing grows with the street but the
object table a section keeps (about 30 bytes per metre). The first read in a process checks
the generator against the stored digest (a streamed digest: about 60 ms per kilometre).
The bytes do not depend on the process, the order of reads or what is kept.

**On disk.** Cast colour images are also kept as PNG files beside the dataset, within a bound
(``BBCITY_LAZY_CACHE_MB``), for every process that reads it (:mod:`data_synth.lazy_cache`): a
build reads each view many times, in several processes, and a cast costs a second or two.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.distortion import undistort
from capture.rig import Rig
from capture.sources import register_image_source
from core.fileio import DataFormatError, read_json

from .config import capture_path, config_from_json, config_json
from .lazy_cache import ImageCache, cache_limit_bytes
from .raycast import Renderer, RenderResult
from .rig import make_rig
from .section import object_table, scene_section, scene_settings, verify_digest

logger = logging.getLogger(__name__)

#: Tolerance (relative for K, metres for poses) of rig.json's numbers against the rig a lazy dataset's settings make (both
#: are written and read as JSON, so they agree exactly unless rig.json was edited).
RIG_TOL = 1e-9
#: The sections' grid along the street, metres: frames whose rig lies in one tile share a section.
TILE_M = 50.0
#: The longest reach a section is given, metres (lenses that see along the street).
MAX_REACH_M = 1000.0
#: Sections (each a ray-casting structure of about 150–300 m of street) and cast frames kept per process.
SECTIONS_KEPT = 3
RESULTS_KEPT = 6

LAZY_IMAGES = "lazy"  # dataset.json "images" of a lazy dataset: its image source's kind (capture.sources)


def view_reach(cfg) -> float | None:
    """How far along the street (|Δx|, metres, rounded up) from a camera of the capture of
    ``cfg`` (a :class:`data_synth.SynthConfig`) a ray of it can meet an object that is not
    in every section; None for a town or an orbit (cast whole). See the module's docstring."""
    if cfg.scene != "street" or cfg.path == "orbit":  # an orbit's cameras look every way along the street
        return None
    _, config, _ = scene_settings(cfg)
    _, _, bounds, _ = object_table("street", config)
    poses, passes = capture_path(cfg)
    x = poses[:, 0, 3]
    spans = (bounds[:, 0, 0] <= x.min()) & (bounds[:, 1, 0] >= x.max())  # ground, road, sidewalks
    other = bounds[~spans]
    if not len(other):
        return 0.0
    lo, hi = other[:, 0].min(axis=0), other[:, 1].max(axis=0)  # the slab (y and z) they occupy
    rig = make_rig(cfg.rig)
    reach = 0.0
    for p in np.unique(passes):  # the frames of a pass differ only in x
        pose = poses[np.flatnonzero(passes == p)[0]]
        for c in range(rig.num_cameras):
            reach = max(reach, _camera_reach(rig, c, rig.world_from_cam(pose, c), lo, hi))
    if not math.isfinite(reach) or reach > MAX_REACH_M:
        logger.warning("the rig sees along the street: sections reach %.0f m, objects beyond are not drawn",
                       MAX_REACH_M)
        return MAX_REACH_M
    return float(math.ceil(reach * 1.05 + 2.0))


def _camera_reach(rig: Rig, cam: int, world_from_cam: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """max |Δx| over camera ``cam``'s rays through every 4th pixel corner (and the image's
    edges) of their run inside the slab lo[1] ≤ y ≤ hi[1], lo[2] ≤ z ≤ hi[2] (inf when a ray
    runs in it without end)."""
    w, h = rig.sizes[cam]
    u, v = np.meshgrid(np.union1d(np.arange(0, w + 1, 4), [w]) - 0.5, np.union1d(np.arange(0, h + 1, 4), [h]) - 0.5)
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], -1) @ np.linalg.inv(rig.raw_K(cam)).T
    xy = pix[:, :2]
    if rig.distortion(cam) is not None:
        xy = undistort(xy, rig.distortion(cam))
        xy = xy[np.isfinite(xy).all(axis=1)]
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ world_from_cam[:3, :3].T
    C = world_from_cam[:3, 3]
    t_in = np.zeros(len(d))
    t_out = np.full(len(d), np.inf)
    for axis in (1, 2):
        da = d[:, axis]
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo[axis] - C[axis]) / da, (hi[axis] - C[axis]) / da
        moving = da != 0
        inside = (lo[axis] <= C[axis]) & (C[axis] <= hi[axis])
        t_in = np.where(moving, np.maximum(t_in, np.minimum(t1, t2)), np.where(inside, t_in, np.inf))
        t_out = np.where(moving, np.minimum(t_out, np.maximum(t1, t2)), np.where(inside, t_out, -np.inf))
    runs = t_out >= t_in
    if not runs.any():
        return 0.0
    dx = np.abs(d[runs, 0])
    with np.errstate(invalid="ignore"):
        far = np.where(dx > 0, dx * t_out[runs], 0.0)
    return float(far.max())


@dataclass(frozen=True)
class LazyImages:
    """What a lazy dataset's images are cast from: small and picklable (a worker process
    casts its own). root: the dataset directory (errors name its files); config_json: the
    canonical JSON of its :class:`data_synth.SynthConfig`; digest: ``gt/scene.json``'s;
    reach: metres (None: the whole scene); tile: metres; check_digest: check the generator
    against ``digest`` before the first cast in a process (the writer, which has just made
    the digest, does not)."""

    root: Path
    config_json: str
    digest: str
    reach: float | None
    tile: float
    check_digest: bool = True

    @classmethod
    def from_manifest(cls, root: os.PathLike | str, manifest: dict) -> "LazyImages":
        """From a lazy dataset's parsed ``dataset.json`` (and its ``gt/scene.json``);
        DataFormatError naming the file that is malformed. The opener of the image source
        ``"lazy"`` (:func:`capture.sources.register_image_source`)."""
        root = Path(root)
        path = root / "dataset.json"
        try:
            cfg = config_from_json(manifest["synth"])
        except (KeyError, TypeError, ValueError) as e:
            raise DataFormatError(path, f"a lazy dataset needs its \"synth\" settings ({e})") from None
        lazy = manifest.get("lazy")
        reach = lazy.get("reach_m", "?") if isinstance(lazy, dict) else "?"
        tile = lazy.get("tile_m") if isinstance(lazy, dict) else None
        if not (reach is None or _positive(reach, zero=True)) or not _positive(tile):
            raise DataFormatError(path, "\"lazy\" needs \"reach_m\" (metres ≥ 0, or null) and \"tile_m\" (metres > 0)")
        if not cfg.lazy:
            raise DataFormatError(path, "\"images\" is \"lazy\" but its settings are not (\"synth\".\"lazy\")")
        scene_path = root / "gt" / "scene.json"
        scene = read_json(scene_path)
        if not isinstance(scene, dict) or not isinstance(scene.get("digest"), str):
            raise DataFormatError(scene_path, "needs the scene's \"digest\"")
        return cls(root, json.dumps(config_json(cfg), sort_keys=True), scene["digest"],
                   None if reach is None else float(reach), float(tile))

    # ------------------------------------------------------------------ casting

    def _state(self) -> "_State":
        key = (self.config_json, self.digest if self.check_digest else None)
        with _LOCK:
            state = _STATES.get(key)
        if state is None:
            cfg = config_from_json(json.loads(self.config_json))
            name, config, _ = scene_settings(cfg)
            if self.check_digest:
                verify_digest(name, config, self.digest, self.root / "gt" / "scene.json")
            rig = make_rig(cfg.rig)
            poses, _ = capture_path(cfg)
            offset = float(np.linalg.norm(np.linalg.inv(rig.cam_from_rig)[:, :2, 3], axis=1).max())
            state = _State(cfg, name, config, rig, poses, offset)
            with _LOCK:
                _STATES[key] = state
                while len(_STATES) > 2:
                    _STATES.popitem(last=False)
        return state

    def section_box(self, frame: int) -> tuple[int | None, tuple, tuple]:
        """(tile index or None, lo (3,), hi (3,)): the section frame ``frame`` is cast from."""
        state = self._state()
        if self.reach is None:
            return None, (-np.inf,) * 3, (np.inf,) * 3
        k = math.floor(state.poses[frame][0, 3] / self.tile)
        margin = self.reach + state.offset
        return k, (k * self.tile - margin, -np.inf, -np.inf), ((k + 1) * self.tile + margin, np.inf, np.inf)

    def _renderer(self, frame: int) -> Renderer:
        k, lo, hi = self.section_box(frame)
        key = (self.config_json, k, self.reach, self.tile)
        with _LOCK:
            renderer = _RENDERERS.get(key)
            if renderer is not None:
                _RENDERERS.move_to_end(key)
                return renderer
        state = self._state()
        renderer = Renderer(scene_section((state.name, state.config), lo, hi))
        with _LOCK:
            _RENDERERS[key] = renderer
            while len(_RENDERERS) > SECTIONS_KEPT:
                _RENDERERS.popitem(last=False)
        return renderer

    def _check(self, frame: int, cam: int) -> None:
        state = self._state()
        if not (0 <= frame < len(state.poses)) or not (0 <= cam < state.rig.num_cameras):
            raise DataFormatError(self.root / "images" / f"cam{cam}" / f"{frame:06d}.png",
                                  f"a lazy dataset of {len(state.poses)} frames × {state.rig.num_cameras} "
                                  f"cameras has no frame {frame} camera {cam}")

    def render(self, frame: int, cam: int, colour: bool = True, keep: bool = True) -> RenderResult:
        """The raw frame ``frame`` (capture index) of camera ``cam``, as the stored dataset holds it
        (rgb, depth, ids); ``colour`` False may leave rgb zero (depth and ids only, cheaper);
        ``keep`` False does not keep it for the next read (the writer's single reads)."""
        self._check(frame, cam)
        key = (self.config_json, self.reach, self.tile, frame, cam)
        with _LOCK:
            cached = _RESULTS.get(key)
            if cached is not None and (cached[1] or not colour):
                _RESULTS.move_to_end(key)
                return cached[0]
        state = self._state()
        renderer = self._renderer(frame)
        rig, cfg = state.rig, state.cfg
        args = (rig.raw_K(cam), rig.world_from_cam(state.poses[frame], cam), rig.sizes[cam])
        if colour:
            result = renderer.render(*args, spp=cfg.spp, distortion=rig.distortion(cam))
        else:
            depth, ids = renderer.depth_ids(*args, spp=cfg.spp, distortion=rig.distortion(cam))
            result = RenderResult(np.zeros((*depth.shape, 3), np.uint8), depth, ids)
        if not keep:
            return result
        with _LOCK:
            _RESULTS[key] = (result, colour)
            _RESULTS.move_to_end(key)
            while len(_RESULTS) > RESULTS_KEPT:
                _RESULTS.popitem(last=False)
        return result

    def image(self, frame: int, cam: int) -> np.ndarray:
        """(h, w, 3) uint8 raw (distorted, where the camera has a lens) RGB of a frame (a new array):
        from the dataset's image cache (:mod:`data_synth.lazy_cache`) or cast, then kept there."""
        self._check(frame, cam)
        cache = self.cache()
        if cache is None:
            return self.render(frame, cam).rgb.copy()
        size = tuple(int(v) for v in self._state().rig.sizes[cam])
        rgb = cache.get(frame, cam, size)
        if rgb is None:
            rgb = self.render(frame, cam).rgb.copy()
            cache.put(frame, cam, rgb)
        return rgb

    def cache(self) -> ImageCache | None:
        """This process's :class:`~data_synth.lazy_cache.ImageCache` of the dataset's cast images
        (None when ``BBCITY_LAZY_CACHE_MB`` is 0)."""
        limit = cache_limit_bytes()
        if limit <= 0:
            return None
        key = (self.root, self.config_json, self.digest, limit)
        with _LOCK:
            cache = _CACHES.get(key)
        if cache is None:  # the directory named by what makes a frame
            casts = hashlib.sha256(f"{self.config_json}\n{self.digest}".encode()).hexdigest()[:16]
            with _LOCK:
                cache = _CACHES.setdefault(key, ImageCache(self.root.resolve() / "cache" / casts, limit))
        return cache

    @property
    def has_gt_depth(self) -> bool:
        """Whether :meth:`ground_truth` casts depth and ids (the settings' ``ground_truth_depth``)."""
        return bool(self._state().cfg.ground_truth_depth)

    def ground_truth(self, kind: str, frame: int, cam: int) -> np.ndarray:
        """Raw ``kind`` ("depth": (h, w) float32 NaN = sky; "ids": (h, w) int32, −1 = sky) of a frame;
        DataFormatError naming the file a stored dataset would hold when the settings leave it out."""
        if not self._state().cfg.ground_truth_depth:
            raise DataFormatError(self.root / "gt" / kind / f"cam{cam}" / f"{frame:06d}.npy",
                                  "this lazy dataset was made without ground-truth depth (--no-gt-depth)")
        result = self.render(frame, cam, colour=False)
        return (result.depth if kind == "depth" else result.ids).copy()

    def check_rig(self, rig: Rig, path: Path) -> None:
        """DataFormatError naming ``path`` (the dataset's rig.json) unless ``rig`` is the rig the
        settings cast the images with: the same sizes, raw intrinsics, lenses and poses."""
        made = self._state().rig
        problem = None
        if rig.num_cameras != made.num_cameras:
            problem = f"has {rig.num_cameras} cameras"
        else:
            for c in range(rig.num_cameras):
                lens, made_lens = rig.distortion(c), made.distortion(c)
                if tuple(rig.sizes[c]) != tuple(made.sizes[c]):
                    problem = f"gives camera {c} a size of {rig.sizes[c][0]}x{rig.sizes[c][1]}"
                elif not np.allclose(rig.raw_K(c), made.raw_K(c), rtol=RIG_TOL, atol=0):
                    problem = f"gives camera {c} other intrinsics"
                elif not np.allclose(rig.cam_from_rig[c], made.cam_from_rig[c], rtol=0, atol=RIG_TOL):
                    problem = f"gives camera {c} another place on the rig"
                elif (None if lens is None else lens.to_json()) != (None if made_lens is None else made_lens.to_json()):
                    problem = f"gives camera {c} another lens"
                if problem:
                    break
        if problem:
            w, h = made.sizes[0]
            raise DataFormatError(path, f"{problem}, unlike the rig the lazy dataset's settings cast its images with "
                                        f"({made.num_cameras} cameras, camera 0 {w}x{h}): restore it, or write the "
                                        "dataset again")

    def check_frames(self, names, world_from_rig: np.ndarray, path: Path) -> None:
        """A lazy dataset's frames and poses (n, 4, 4) float64 are those of the capture its
        settings make (the images follow the settings); DataFormatError naming ``path`` (its
        poses.json) otherwise."""
        capture, _ = capture_path(config_from_json(json.loads(self.config_json)))
        check_frame_names(names, path, len(capture))
        if not np.array_equal(world_from_rig, capture):
            raise DataFormatError(path, "differs from the capture path of the lazy dataset's settings (its images "
                                        "are cast from those): restore it, or write the dataset again")


def _positive(value, zero: bool = False) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and (value >= 0 if zero else value > 0))


@dataclass(frozen=True)
class _State:
    """A lazy dataset's settings made ready in this process."""

    cfg: object
    name: str
    config: dict
    rig: Rig
    poses: np.ndarray  # (n, 4, 4) float64 capture poses (the images follow these, not poses.json)
    offset: float  # metres: the farthest camera from the rig's origin


_LOCK = threading.RLock()  # the caches below may be read from several threads
_STATES: OrderedDict = OrderedDict()
_RENDERERS: OrderedDict = OrderedDict()
_RESULTS: OrderedDict = OrderedDict()
_CACHES: dict = {}


def check_frame_names(names, path: os.PathLike | str, frames: int) -> None:
    """A lazy dataset's frames are its capture's, in order, named ``000000``, ``000001`` …;
    DataFormatError naming ``path`` (its poses.json) otherwise."""
    if len(names) != frames or any(n != f"{i:06d}" for i, n in enumerate(names)):
        raise DataFormatError(path, f"a lazy dataset's frames are the {frames} frames of its capture, named "
                                    f"000000, 000001, … in order")


register_image_source(LAZY_IMAGES, LazyImages.from_manifest)  # also the entry point bbcity.image_sources "lazy"
