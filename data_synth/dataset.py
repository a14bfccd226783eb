"""Dataset writer and reader.

Layout of a dataset directory::

    dataset.json              manifest, written last: its presence marks a complete dataset
    synth_report.json         timings of the run that wrote it (the only file that varies) and the
                              street's coverage (shares of road, sidewalk and facades the rig sees)
    rig.json                  intrinsics, lens distortion ("none", radtan or fisheye) and cam_from_rig per camera
    poses.json                world_from_rig per frame, float64
    images/cam{c}/NNNNNN.png  RGB images
    colmap/                   the same cameras and poses as a COLMAP text model
    gt/scene.json             the generator's configuration (re-creates the scene) and digest
    gt/mesh.ply               the scene's triangle mesh
    gt/objects/*.npy          kind (k,) int16, seed (k,) uint32, bounds (k, 2, 3) float64
    gt/triangle_object.npy    object id per mesh triangle (m,) int32
    gt/depth/cam{c}/NNNNNN.npy  z-depth (h, w) float32, NaN = sky
    gt/ids/cam{c}/NNNNNN.npy    object id (h, w) int32, −1 = sky

Images and ground truth are stored as the raw cameras see them (distorted, when
rig.json gives a lens); :class:`Dataset` returns them undistorted, lined up with
``rig.intrinsics``.

A user's own capture needs only ``rig.json``, ``poses.json`` and ``images/``.

A *lazy* dataset (``SynthConfig(lazy=True)``, :mod:`data_synth.lazy`) has no ``images/`` and no
``gt/`` files but ``gt/scene.json``: ``dataset.json`` says ``"images": "lazy"`` and
:meth:`Dataset.image`, :meth:`Dataset.gt_depth`, :meth:`Dataset.gt_ids` and
:func:`data_synth.read_image` cast each frame when it is read, the bytes the stored dataset of
the same settings holds. It is written in well under a second whatever the street's length.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import open3d as o3d

from core.errors import InputError
from core.fileio import DataFormatError, atomic_path, load_npy, read_json, read_png, save_npy, write_json, write_png
from core.tasks import run_tasks
from core.workdir import sweep_temporaries, temporary

from .colmap_export import write_colmap_text
from .coverage import street_coverage
from .lazy import LAZY_IMAGES, TILE_M, LazyImages, check_frame_names, lazy_source, view_reach
from .rig import Rig, RigConfig, drive_path, load_poses, make_rig, orbit_path, save_poses
from .scene import Scene
from .section import object_table, scene_digest, scene_settings
from .street import StreetConfig, build_street, free_building, street_settings
from .town import TownConfig, build_town, street_centres

logger = logging.getLogger(__name__)

DATASET_FORMAT = "bbcity-dataset"
SCENE_FORMAT = "bbcity-scene"
FORMAT_VERSION = 1
SCENES = ("street", "town")
#: Capture paths: "drive" along the street (and back), or "orbit": one loop round a free-standing building.
PATHS = ("drive", "orbit")
#: An orbit keeps this far (metres) from the corners of its building and from anything else.
ORBIT_CLEARANCE_M = 2.0


MAX_SPP = 16  # supersampling per pixel axis at most (256 rays a pixel)


@dataclass(frozen=True)
class SynthConfig:
    scene: str = "street"  # "street" or "town"
    street: StreetConfig = field(default_factory=StreetConfig)  # used when scene == "street"
    town: TownConfig = field(default_factory=TownConfig)  # used when scene == "town"
    rig: RigConfig = field(default_factory=RigConfig)  # cameras and their mounting
    frames: int = 100  # frames per pass, evenly spaced along the path
    return_pass: bool = True  # a drive: back in the other lane so both sides are captured (an orbit is one loop)
    lane_offset: float = 1.75  # a drive's distance from the street's centre line, metres
    town_path_length: float = 300.0  # town: length of the drive along its middle street, metres
    spp: int = 2  # supersampling per pixel axis (spp² colour rays per pixel)
    ground_truth_depth: bool = True  # write gt/depth and gt/ids for every image
    lazy: bool = False  # write no images: cast each frame when it is read (data_synth.lazy)
    path: str = "drive"  # "drive" (along the street) or "orbit" (one loop round the street's free-standing building)
    orbit_radius: float = 25.0  # orbit: the circle's radius about the building's centre, metres

    def __post_init__(self):
        if self.scene not in SCENES:
            raise InputError(f"unknown scene {self.scene!r}; expected one of {SCENES}")
        if self.path not in PATHS:
            raise InputError(f"SynthConfig.path must be one of {PATHS}, got {self.path!r}")
        for name in ("frames", "spp"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InputError(f"SynthConfig.{name} must be an integer ≥ 1, got {value!r}")
        if self.spp > MAX_SPP:  # spp² rays a pixel: a lazy dataset's reader would cast for ever
            raise InputError(f"SynthConfig.spp must be at most {MAX_SPP} (spp² rays a pixel), got {self.spp}")
        for name in ("lane_offset", "town_path_length", "orbit_radius"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InputError(f"SynthConfig.{name} must be a finite number, got {value!r}")
        if self.town_path_length <= 0:
            raise InputError(f"SynthConfig.town_path_length must be positive, got {self.town_path_length}")
        if self.orbit_radius <= 0:
            raise InputError(f"SynthConfig.orbit_radius must be positive metres, got {self.orbit_radius}")
        if self.path == "orbit":
            self._check_orbit()
        for name in ("return_pass", "ground_truth_depth", "lazy"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"SynthConfig.{name} must be true or false, got {getattr(self, name)!r}")

    def _check_orbit(self) -> None:
        """An orbit circles the street's free-standing building (:func:`street.free_building`)
        clear of it and of everything else by ORBIT_CLEARANCE_M; ValueError otherwise."""
        r, gap = self.orbit_radius, ORBIT_CLEARANCE_M
        if self.scene != "street":
            raise InputError("path \"orbit\" needs the street scene: the town's houses stand in closed rows, "
                             "with no free path round one")
        if self.street.square < r + gap:
            raise InputError(f"path \"orbit\" of radius {r:g} m needs the street's open square (StreetConfig.square) "
                             f"to reach at least {r + gap:g} m from the building's centre, got {self.street.square:g}")
        lo, hi = free_building(self.street)
        corner = float(np.hypot(*(hi - lo))) / 2
        if r < corner + gap:
            raise InputError(f"SynthConfig.orbit_radius (--orbit-radius) {r:g} m passes within {gap:g} m of the "
                             f"free-standing building's corners (a {hi[0] - lo[0]:.1f} × {hi[1] - lo[1]:.1f} m "
                             f"footprint): at least {math.ceil((corner + gap) * 10) / 10:g} m")

    @property
    def passes(self) -> int:
        """Passes of the capture: an orbit's one loop, a drive's one or two (return_pass)."""
        return 2 if self.path == "drive" and self.return_pass else 1

    @property
    def path_length(self) -> float:
        """Metres the rig moves per pass: the street's length, the town drive's, or the
        orbit's circumference."""
        if self.path == "orbit":
            return 2 * math.pi * self.orbit_radius
        return float(self.street.length if self.scene == "street" else self.town_path_length)


def frames_for_spacing(path_length: float, spacing: float, closed: bool = False) -> int:
    """Frames per pass that put neighbouring frames at most ``spacing`` metres apart along a
    pass of ``path_length`` metres: ⌈length / spacing⌉ + 1 with both ends included, or
    ⌈length / spacing⌉ round a ``closed`` loop (an orbit: the last frame's neighbour is the first)."""
    if not (math.isfinite(path_length) and path_length > 0 and math.isfinite(spacing) and spacing > 0):
        raise InputError(f"path length and frame spacing must be positive metres, got {path_length}, {spacing}")
    return int(math.ceil(path_length / spacing - 1e-9)) + (0 if closed else 1)


def _from_dict(cls, data: dict):
    """Rebuild a flat config dataclass from JSON (lists back to tuples)."""
    fields = cls.__dataclass_fields__
    unknown = set(data) - set(fields)
    if unknown:
        raise InputError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


def build_scene(name: str, config: dict) -> Scene:
    """Generate the scene ``name`` ("street" or "town") from its configuration dict."""
    if name == "street":
        return build_street(_from_dict(StreetConfig, config))
    if name == "town":
        return build_town(_from_dict(TownConfig, config))
    raise InputError(f"unknown scene {name!r}; expected one of {SCENES}")


def capture_path(cfg: SynthConfig) -> tuple[np.ndarray, np.ndarray]:
    """The rig's trajectory: world_from_rig (n, 4, 4) float64 and pass index (n,) int32."""
    if cfg.path == "orbit":  # (a street: SynthConfig checks it)
        lo, hi = free_building(cfg.street)
        return orbit_path((lo + hi) / 2, cfg.orbit_radius, cfg.frames)
    if cfg.scene == "street":
        return drive_path(0.0, cfg.street.length, 0.0, cfg.frames, cfg.lane_offset, cfg.return_pass)
    centres = street_centres(cfg.town)
    y = centres[len(centres) // 2 if cfg.town.path_street < 0 else cfg.town.path_street]
    half = cfg.town_path_length / 2
    # narrow streets: drive near the middle, so that the facades are not at arm's length
    return drive_path(-half, half, y, cfg.frames, cfg.town.street_width / 8, cfg.return_pass)


def _config_json(cfg: SynthConfig) -> dict:
    data = json.loads(json.dumps(asdict(cfg)))
    data["street"] = json.loads(json.dumps(street_settings(cfg.street)))  # a street without a square keeps its bytes
    if data["path"] == "drive":  # drives keep the bytes they had before orbits
        del data["path"]
        if data["orbit_radius"] == SynthConfig.orbit_radius:
            del data["orbit_radius"]
    if data["rig"].get("distortion") == "none":  # pinhole datasets keep the bytes they had before lenses
        del data["rig"]["distortion"]
    if not data["lazy"]:  # stored datasets keep the bytes they had before lazy ones
        del data["lazy"]
    return data


def config_from_json(data: dict) -> SynthConfig:
    """Inverse of the configuration stored in ``dataset.json``."""
    data = dict(data)
    nested = {"street": StreetConfig, "town": TownConfig, "rig": RigConfig}
    for key, cls in nested.items():
        if key in data:
            data[key] = _from_dict(cls, data[key])
    return _from_dict(SynthConfig, data)


# --------------------------------------------------------------------------- writing

def _frame_files(root: Path, name: str, cams: int, gt: bool) -> list[Path]:
    files = [root / "images" / f"cam{c}" / f"{name}.png" for c in range(cams)]
    if gt:
        files += [root / "gt" / kind / f"cam{c}" / f"{name}.npy" for kind in ("depth", "ids") for c in range(cams)]
    return files


def _render_frame(task: tuple[str, LazyImages, int, int, bool]) -> float:
    """Render and write one frame's images (and ground truth). Returns seconds spent."""
    root_str, source, frame, cameras, gt = task
    start = time.perf_counter()
    root = Path(root_str)
    name = f"{frame:06d}"
    for c in range(cameras):
        # the raw camera: distorted images (and ground truth in raw pixels) for a lens; cast from
        # the frame's section, as a lazy dataset of the same settings casts it
        result = source.render(frame, c, keep=False)
        if gt:
            save_npy(root / "gt" / "depth" / f"cam{c}" / f"{name}.npy", result.depth)
            save_npy(root / "gt" / "ids" / f"cam{c}" / f"{name}.npy", result.ids)
        # the image goes last: a frame is complete when all its files exist
        write_png(root / "images" / f"cam{c}" / f"{name}.png", result.rgb)
    return time.perf_counter() - start


def write_mesh_ply(path: Path, scene: Scene) -> Path:
    """Atomically write the scene's triangle mesh (float64 vertices) as binary PLY."""
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(scene.vertices),
                                     o3d.utility.Vector3iVector(scene.triangles))
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False,
                                          write_vertex_normals=False, write_vertex_colors=False):
            raise OSError(f"{path}: Open3D could not write the mesh")
    return path


def _differences(a, b, prefix: str = "") -> list[str]:
    """Dotted keys at which two JSON values differ ("frames", "rig.width"); [prefix or
    "settings"] when they differ otherwise."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str) if a.get(k) != b.get(k)
                for d in _differences(a.get(k), b.get(k), f"{prefix}{k}.")]
    return [] if a == b else [prefix.rstrip(".") or "settings"]


def _write_capture(root: Path, rig: Rig, world_from_rig: np.ndarray, passes) -> list[str]:
    """rig.json, poses.json and the COLMAP model of the known poses; the frame names."""
    rig.save(root / "rig.json")
    save_poses(root / "poses.json", world_from_rig, passes)
    names = [f"{i:06d}" for i in range(len(world_from_rig))]
    write_colmap_text(root / "colmap", np.array([rig.raw_K(c) for c in range(rig.num_cameras)]), list(rig.sizes),
                      rig.cam_from_rig, world_from_rig,
                      [[f"cam{c}/{n}.png" for c in range(rig.num_cameras)] for n in names],
                      distortions=[rig.distortion(c) for c in range(rig.num_cameras)])
    return names


def write_dataset(cfg: SynthConfig, out_dir: os.PathLike | str, executor: Executor | None = None,
                  progress: bool | None = None) -> Path:
    """Generate the scene, render every frame and write the dataset to ``out_dir``.

    executor: runs frames in parallel (any ``concurrent.futures.Executor``); None
    renders in this process. An interrupted or failed run is resumed: run again
    with the same configuration, frames whose files all exist are kept (every file
    is written atomically), the temporaries of a killed run are removed. A directory
    holding a dataset (complete or not) with a different configuration is refused,
    never mixed: FileExistsError naming the settings that differ and how to proceed.
    Returns ``out_dir``.
    """
    root = Path(out_dir)
    cfg_dict = _config_json(cfg)
    existing = root / "gt" / "scene.json"
    if existing.exists():
        data = read_json(existing)
        stored = data.get("synth") if isinstance(data, dict) else None
        if stored != cfg_dict:
            differ = ", ".join(_differences(stored, cfg_dict)[:6])
            if (root / "dataset.json").exists():
                raise FileExistsError(f"{root} holds a dataset made with other settings ({differ}); choose a new "
                                      f"--out, or remove it (rm -r {root}) to write this one there")
            # a run that failed or was stopped: its settings finish it, any others need a clean directory
            raise FileExistsError(f"{root} holds an unfinished dataset (a run that failed or was stopped) made with "
                                  f"other settings ({differ}): run it again with those settings to finish it, or "
                                  f"remove it (rm -r {root}) to start this one there")
        logger.info("resuming the dataset in %s", root)
    elif root.exists() and any(p.is_file() and not any(temporary(part) for part in p.relative_to(root).parts) for p in root.rglob("*")):
        raise FileExistsError(f"{root} exists and is not an empty directory or a bbcity dataset")
    sweep_temporaries(root, locked=True)  # this writer owns the dataset directory
    if cfg.lazy:
        return _write_lazy(cfg, root)

    t0 = time.perf_counter()
    scene = build_scene(*scene_settings(cfg)[:2])
    rig = make_rig(cfg.rig)
    world_from_rig, passes = capture_path(cfg)
    t_scene = time.perf_counter() - t0
    logger.info("%s scene: %d objects, %d triangles (%.2f s)", cfg.scene, scene.num_objects,
                len(scene.triangles), t_scene)

    write_json(existing, {"format": SCENE_FORMAT, "version": FORMAT_VERSION, "scene": scene.name,
                          "config": scene.config, "digest": scene.digest(), "synth": cfg_dict})
    save_npy(root / "gt" / "objects" / "kind.npy", scene.object_kind)
    save_npy(root / "gt" / "objects" / "seed.npy", scene.object_seed)
    save_npy(root / "gt" / "objects" / "bounds.npy", scene.object_bounds)
    save_npy(root / "gt" / "triangle_object.npy", scene.triangle_object)
    write_mesh_ply(root / "gt" / "mesh.ply", scene)
    names = _write_capture(root, rig, world_from_rig, passes)

    # the frames are cast as a lazy dataset of these settings casts them (data_synth.lazy)
    source = LazyImages(root, json.dumps(cfg_dict, sort_keys=True), scene.digest(), view_reach(cfg), TILE_M,
                        check_digest=False)  # the digest was just made from this generator
    todo = [(str(root), source, i, rig.num_cameras, cfg.ground_truth_depth)
            for i, n in enumerate(names)
            if not all(p.exists() for p in _frame_files(root, n, rig.num_cameras, cfg.ground_truth_depth))]
    logger.info("rendering %d of %d frames × %d cameras", len(todo), len(names), rig.num_cameras)
    t1 = time.perf_counter()
    frame_seconds = run_tasks(_render_frame, todo, executor, desc="render", progress=progress)
    t_render = time.perf_counter() - t1
    t2 = time.perf_counter()
    # (the street's surfaces beside a drive: an orbit sees its building, not the street)
    coverage = street_coverage(scene, rig, world_from_rig) if cfg.scene == "street" and cfg.path == "drive" else None
    if coverage is not None:
        pct = {k: "n/a" if coverage[k] is None else f"{100 * coverage[k]:.1f} %"
               for k in ("road_sidewalk", "road_sidewalk_outboard", "facade", "facade_top_1m")}
        logger.info("the rig sees %s of road + sidewalk (%s of the part beside its paths), %s of the facades, "
                    "%s of their top metre", pct["road_sidewalk"], pct["road_sidewalk_outboard"], pct["facade"],
                    pct["facade_top_1m"])
    t_coverage = time.perf_counter() - t2

    write_json(root / "dataset.json", {
        "format": DATASET_FORMAT, "version": FORMAT_VERSION, "scene": cfg.scene,
        "frames": len(names), "cameras": rig.num_cameras, "image_size": list(rig.sizes[0]),
        "objects": scene.num_objects, "triangles": int(len(scene.triangles)),
        "ground_truth": True, "synth": cfg_dict,
    })
    # timings vary run to run, so they live apart from the byte-reproducible dataset files
    write_json(root / "synth_report.json", {
        "scene_seconds": t_scene, "render_seconds": t_render, "frames_rendered": len(todo),
        "median_frame_seconds": float(np.median(frame_seconds)) if frame_seconds else None,
        "coverage_seconds": t_coverage, "coverage": coverage,
    })
    return root


def _write_lazy(cfg: SynthConfig, root: Path) -> Path:
    """:func:`write_dataset` of a lazy dataset: settings, rig, poses, COLMAP model and
    ``gt/scene.json``; the scene is walked (object table, digest, reach), never held whole."""
    t0 = time.perf_counter()
    cfg_dict = _config_json(cfg)
    name, config, _ = scene_settings(cfg)
    kinds, _, _, num_triangles = object_table(name, config)
    digest = scene_digest(name, config)
    reach = view_reach(cfg)
    rig = make_rig(cfg.rig)
    world_from_rig, passes = capture_path(cfg)
    t_scene = time.perf_counter() - t0
    logger.info("%s scene: %d objects, %d triangles, %s (%.2f s)", name, len(kinds), num_triangles,
                "frames cast from the whole scene" if reach is None
                else f"sections of ± {reach:g} m around each {TILE_M:g} m tile", t_scene)
    write_json(root / "gt" / "scene.json", {"format": SCENE_FORMAT, "version": FORMAT_VERSION, "scene": name,
                                            "config": config, "digest": digest, "synth": cfg_dict})
    names = _write_capture(root, rig, world_from_rig, passes)
    write_json(root / "dataset.json", {
        "format": DATASET_FORMAT, "version": FORMAT_VERSION, "scene": name,
        "frames": len(names), "cameras": rig.num_cameras, "image_size": list(rig.sizes[0]),
        "objects": int(len(kinds)), "triangles": int(num_triangles), "ground_truth": True,
        "images": LAZY_IMAGES, "lazy": {"reach_m": reach, "tile_m": TILE_M}, "synth": cfg_dict,
    })
    write_json(root / "synth_report.json", {
        "scene_seconds": t_scene, "render_seconds": 0.0, "frames_rendered": 0, "median_frame_seconds": None,
        "coverage_seconds": 0.0, "coverage": None,
    })
    return root


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Dataset:
    """A validated dataset. world_from_rig: (n, 4, 4) float64; frame_names: n stems;
    lazy: how a lazy dataset's frames are cast (None: stored images)."""

    root: Path
    rig: Rig
    world_from_rig: np.ndarray
    frame_names: tuple[str, ...]
    lazy: LazyImages | None = None

    def __fspath__(self) -> str:  # a dataset stands for its directory (load_dataset returns it as it is)
        return str(self.root)

    def __str__(self) -> str:
        return str(self.root)

    @property
    def num_frames(self) -> int:
        return len(self.frame_names)

    @property
    def posed(self) -> np.ndarray:
        """(n,) bool: the frames that have a pose (a photo folder's are unknown until SfM)."""
        return np.isfinite(self.world_from_rig).all(axis=(1, 2))

    @property
    def has_ground_truth(self) -> bool:
        return (self.root / "gt" / "scene.json").is_file()

    def image_path(self, frame: int, cam: int) -> Path:
        """Where the raw image is; a lazy dataset's is not there: :func:`data_synth.read_image`
        reads both (as :meth:`image` does)."""
        return self.root / "images" / f"cam{cam}" / f"{self.frame_names[frame]}.png"

    def image(self, frame: int, cam: int) -> np.ndarray:
        """(h, w, 3) uint8 RGB, undistorted when the camera has a lens (pinhole ``rig.intrinsics``);
        a missing, truncated or wrongly sized file raises DataFormatError. A lazy dataset casts it."""
        if self.lazy is not None:
            raw = self.lazy.image(int(self.frame_names[frame]), cam)
        else:
            raw = read_png(self.image_path(frame, cam), self.rig.sizes[cam])
        return self.rig.undistort(raw, cam)

    def world_from_cam(self, frame: int, cam: int) -> np.ndarray:
        """(4, 4) float64 camera pose."""
        return self.rig.world_from_cam(self.world_from_rig[frame], cam)

    def _gt(self, kind: str, frame: int, cam: int, dtype) -> np.ndarray:
        w, h = self.rig.sizes[cam]
        path = self.root / "gt" / kind / f"cam{cam}" / f"{self.frame_names[frame]}.npy"
        if self.lazy is not None:
            raw = self.lazy.ground_truth(kind, int(self.frame_names[frame]), cam)
        else:
            raw = load_npy(path, dtype=dtype, shape=(h, w))
            if kind == "depth":  # NaN where nothing is hit; a hit lies in front of the camera
                bad = ~(np.isnan(raw) | (np.isfinite(raw) & (raw > 0)))
                if bad.any():
                    raise DataFormatError(path, f"holds {int(bad.sum())} depths that are neither NaN (no hit) nor "
                                                f"a positive distance, e.g. {raw[bad][0]:g}")
        # nearest raw pixel: no blending across depth edges or between object ids
        return self.rig.undistort(raw, cam, nearest=True)

    def gt_depth(self, frame: int, cam: int) -> np.ndarray:
        """(h, w) float32 ground-truth z-depth, NaN where nothing is hit; undistorted like
        :meth:`image` (nearest raw pixel, so within half a raw pixel of each pixel's ray)."""
        return self._gt("depth", frame, cam, np.float32)

    def gt_ids(self, frame: int, cam: int) -> np.ndarray:
        """(h, w) int32 ground-truth object id, −1 where nothing is hit; undistorted like :meth:`gt_depth`."""
        return self._gt("ids", frame, cam, np.int32)

    def verify(self) -> None:
        """Decode every image (slow, thorough; a lazy dataset casts every frame); the first bad
        file raises DataFormatError."""
        for f in range(self.num_frames):
            for c in range(self.rig.num_cameras):
                self.image(f, c)


def load_dataset(path: os.PathLike | str, poses: os.PathLike | str | None = None) -> Dataset:
    """Open a dataset directory: validate ``rig.json``, ``poses.json`` and that
    every image exists. Errors name the offending file.

    poses: another ``poses.json`` to use instead of the dataset's own (the poses a
    ``bbcity recon --poses sfm`` found, ``WORK/poses.json``): the same frame names in the
    same order; frames it gives ``null`` have no pose (NaN). A :class:`Dataset` passed as
    ``path`` is returned as it is (its poses kept; ``poses`` still replaces them), so that
    functions taking a dataset directory also take a dataset with poses from elsewhere.
    """
    if isinstance(path, Dataset):
        return path if poses is None else replace(path, world_from_rig=_replacement_poses(path, poses))
    root = Path(path)
    if not root.is_dir():
        raise DataFormatError(root, "dataset directory does not exist")
    rig = Rig.load(root / "rig.json")
    world_from_rig, names = load_poses(root / "poses.json")
    if not names:
        raise DataFormatError(root / "poses.json", "has no frames")
    lazy = lazy_source(root)
    dataset = Dataset(root, rig, world_from_rig, tuple(names), lazy)
    if lazy is not None:  # no image files: the frames must be the capture's
        _check_lazy_poses(lazy, names, world_from_rig, root / "poses.json")
    if poses is not None:
        dataset = replace(dataset, world_from_rig=_replacement_poses(dataset, poses))
    for f in range(0 if lazy is not None else dataset.num_frames):
        for c in range(rig.num_cameras):
            p = dataset.image_path(f, c)
            if not p.is_file():
                raise DataFormatError(p, f"image of frame {names[f]} camera {c} is missing")
    return dataset


def _check_lazy_poses(lazy: LazyImages, names, world_from_rig: np.ndarray, path: Path) -> None:
    """A lazy dataset's frames and poses are those of the capture its settings make (the
    images follow the settings); DataFormatError naming ``path`` otherwise."""
    capture, _ = capture_path(config_from_json(json.loads(lazy.config_json)))
    check_frame_names(names, path, len(capture))
    if not np.array_equal(world_from_rig, capture):
        raise DataFormatError(path, "differs from the capture path of the lazy dataset's settings (its images "
                                    "are cast from those): restore it, or write the dataset again")


def _replacement_poses(dataset: Dataset, path: os.PathLike | str) -> np.ndarray:
    """world_from_rig (n, 4, 4) float64 of ``path`` (a poses.json) for ``dataset``'s frames."""
    world_from_rig, names = load_poses(path)
    if tuple(names) != dataset.frame_names:
        raise DataFormatError(path, f"its {len(names)} frames are not the {dataset.num_frames} frames of "
                                    f"{dataset.root / 'poses.json'} (names and order must agree)")
    return world_from_rig


def load_scene(dataset_dir: os.PathLike | str) -> Scene:
    """Re-create a dataset's scene from its ``gt/`` (regenerated, then checked
    against the stored digest so that a changed generator cannot go unnoticed)."""
    path = Path(dataset_dir) / "gt" / "scene.json"
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != SCENE_FORMAT:
        raise DataFormatError(path, f"not a scene file (expected \"format\": \"{SCENE_FORMAT}\")")
    try:
        scene = build_scene(data["scene"], data["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise DataFormatError(path, f"cannot re-create the scene ({e})") from None
    if scene.digest() != data.get("digest"):
        raise DataFormatError(path, "the re-created scene differs from the one the dataset was made with "
                                    "(generator changed since)")
    return scene


def held_out_frames(num_frames: int, every: int) -> list[int]:
    """The frames left out for novel-view evaluation: one in every ``every`` (the middle one
    of each run of ``every``; 0: none). Recon, build and eval all follow this rule."""
    if every < 0 or every == 1:
        raise InputError(f"holdout must be 0 (none) or ≥ 2 (every n-th frame left out), got {every}")
    return [f for f in range(num_frames) if every and f % every == every // 2]
