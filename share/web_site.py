"""``bbcity export web``: a model or a tiled set as a static site that any HTTP server serves.

A site is a folder::

    index.html, *.js      the viewer (share/viewer: WebGL2, no framework, no run-time download)
    shaders.json          the desktop's shaders (render/shaders) as GLSL ES 3.00, per program variant
    site.json             what to show: the model or the tiles (world bounds, GPU bytes), the sky,
                          the start view, the capture path, the GPU budget of a tiled set
    model/ or tiles/NAME/ model.json, tables.bin, atlas_NNN.bin, coef_NNN.bin (share.web_model)

The site is written whole or not at all (a temporary folder renamed into place); an existing
``--out`` is refused. The viewer streams a tiled set's tiles nearest first within the budget.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from billboards.model import MANIFEST
from billboards.model_set import TILES_FILE, ModelSet, directory_bytes, load_model_set
from billboards.sky import read_sky
from core.errors import InputError
from core.fileio import atomic_dir, read_json, write_json
from render.paths import capture_camera_poses, densify_poses, drive_path_for
from render.program import es_stage_sources

from .web_camera import DEFAULT_FOV_DEG, pose_view
from .web_model import write_model

FORMAT = "bbcity-web-site"
VERSION = 1
VIEWER_FILES = ("index.html", "viewer.js", "camera.js", "culling.js", "model.js", "tiles.js", "sky.js")
MAX_PATH_POSES = 20000  # capture-path poses kept for playback
MAX_BUDGET_MB = 1e9  # a petabyte: the budget's bytes stay an exact integer


@dataclass(frozen=True)
class WebConfig:
    """Options of ``bbcity export web`` (the CLI derives its options from these fields)."""

    gpu_budget_mb: float = 1024.0  # GPU memory a tiled set's resident tiles may take in the browser (MB)
    fov_deg: float = DEFAULT_FOV_DEG  # vertical field of view of the start view and the capture path (degrees)
    path_step: float = 0.25  # the capture path played back ('P') with the eye at most this far per frame (m)

    def __post_init__(self):
        if not (np.isfinite(self.gpu_budget_mb) and 0 < self.gpu_budget_mb <= MAX_BUDGET_MB):
            raise InputError(f"gpu_budget_mb must be a number of megabytes in (0, {MAX_BUDGET_MB:g}], "
                             f"got {self.gpu_budget_mb}")
        if not (np.isfinite(self.fov_deg) and 1.0 <= self.fov_deg <= 170.0):
            raise InputError(f"fov_deg must lie within [1, 170] degrees, got {self.fov_deg}")
        if not (np.isfinite(self.path_step) and self.path_step > 0):
            raise InputError(f"path_step must be a positive number of metres, got {self.path_step}")


def web_programs() -> dict[str, tuple[str, dict]]:
    """The viewer's programs: name → (shader file, defines). The draw pass per storage-slot count,
    source and filter (``draw_s2_v0_l1``: two slots, from the decoded atlas, bilinear), the
    pre-blend pass per storage-slot count, the decode pass and the sky."""
    programs = {f"draw_s{s}_v{view}_l{lin}": ("billboard.glsl", {"STORAGE_SLOTS": s, "VIEW": view, "LINEAR": lin,
                                                                  "MULTIVIEW": 0})
                for s in (2, 4) for view in (0, 1) for lin in (0, 1)}
    programs.update({f"blend_s{s}": ("billboard_blend.glsl", {"STORAGE_SLOTS": s}) for s in (2, 4)})
    programs["decode"] = ("billboard_decode.glsl", {})
    programs["sky"] = ("sky.glsl", {})
    return programs


def export_web(model_path: Path, out: Path, config: WebConfig = WebConfig(), dataset: Path | None = None) -> dict:
    """Write the site of the model or tiled set at ``model_path`` into the new folder ``out``;
    ``dataset``: whose camera-0 poses are the capture path (default: the model's own, when it is
    still there). Returns a report: files, bytes of the site and of the model, seconds."""
    t0 = time.perf_counter()
    out = Path(out)
    if out.exists() or out.is_symlink():
        raise FileExistsError(f"{out}: already exists; give a new folder for the site")
    model_set = load_model_set(model_path)  # a plain model directory reads as a set of one tile
    with atomic_dir(out) as tmp:
        site = _write_models(model_set, tmp)
        first = model_set.load_tile(0) if len(model_set) else None
        poses = _capture_path(first, dataset)
        if poses is not None:
            poses = densify_poses(poses, config.path_step)[:MAX_PATH_POSES]
        site.update(format=FORMAT, version=VERSION, model_digest=model_digest(model_set), fov_deg=config.fov_deg,
                    gpu_budget_bytes=int(config.gpu_budget_mb * 1e6),
                    path=[] if poses is None else [_pose_row(p) for p in poses],
                    start=_start_view(poses, first))
        sky = read_sky(model_set.root)
        if sky is None and first is not None:
            sky = read_sky(model_set.tiles[0].path)
        site["sky"] = None if sky is None else {"colours": sky.colours.astype(float).tolist(),
                                                "elevation_deg": list(sky.elevation_deg)}
        write_json(tmp / "site.json", site)
        write_json(tmp / "shaders.json", {name: es_stage_sources(file, defines)
                                          for name, (file, defines) in web_programs().items()})
        viewer = resources.files("share").joinpath("viewer")
        for name in VIEWER_FILES:
            (tmp / name).write_bytes(viewer.joinpath(name).read_bytes())
    site_bytes, model_bytes = directory_bytes(out), directory_bytes(model_path)
    return {"site": str(out), "tiles": len(model_set), "site_bytes": site_bytes, "model_bytes": model_bytes,
            "size_ratio": site_bytes / max(model_bytes, 1), "path_poses": len(site["path"]),
            "seconds": time.perf_counter() - t0}


def model_digest(model_set: ModelSet) -> str:
    """SHA-256 of the manifests of a set's tiles (tiles.json first, for a tiled set): what names
    the model a site was exported from."""
    h = hashlib.sha256()
    files = ([model_set.root / TILES_FILE] if model_set.tiled else []) + [t.path / MANIFEST for t in model_set.tiles]
    for f in files:
        h.update(f.read_bytes())
    return h.hexdigest()


def check_site_of(site: Path, model_path: Path) -> None:
    """ValueError unless ``site`` (a checked site folder) was exported from the model at ``model_path``."""
    doc = read_json(Path(site) / "site.json")
    if not isinstance(doc, dict) or doc.get("model_digest") != model_digest(load_model_set(model_path)):
        raise InputError(f"{site}: this site was not exported from {model_path} (export it again: "
                         f"bbcity export web {model_path} --out NEW_SITE)")


def _write_models(model_set: ModelSet, tmp: Path) -> dict:
    """Each tile's files (``model/`` for a plain model, ``tiles/NAME/`` for a set); the site's
    part that lists them."""
    if not model_set.tiled:
        (tmp / "model").mkdir()
        doc = write_model(model_set.load_tile(0), tmp / "model")
        lo, hi = model_set.bounds
        return {"kind": "model", "tiles": [{"name": "model", "dir": "model", "lo": lo.tolist(), "hi": hi.tolist(),
                                            "gpu_bytes": doc["gpu_bytes"], "billboards": doc["billboards"]}]}
    tiles = []
    (tmp / "tiles").mkdir()
    for i, tile in enumerate(model_set.tiles):
        folder = tmp / "tiles" / tile.name
        folder.mkdir()
        doc = write_model(model_set.load_tile(i), folder)
        tiles.append({"name": tile.name, "dir": f"tiles/{tile.name}", "lo": tile.lo.tolist(), "hi": tile.hi.tolist(),
                      "gpu_bytes": doc["gpu_bytes"], "billboards": doc["billboards"]})
    return {"kind": "set", "tiles": tiles}


def _capture_path(first, dataset: Path | None) -> np.ndarray | None:
    """(n, 4, 4) camera-0 poses of the capture (``dataset``'s, else the one the first tile
    records), or None."""
    return None if first is None else capture_camera_poses(first, dataset)


def _pose_row(pose: np.ndarray) -> list[float]:
    """A pose as the viewer's path holds it: world_from_cam's rotation row by row, then the eye."""
    return [round(float(v), 6) for v in (*pose[:3, :3].reshape(-1), *pose[:3, 3])]


def _start_view(poses: np.ndarray | None, model) -> list[float]:
    """x, y, z, yaw°, pitch° of the first capture pose; else the start of the model's drive path."""
    if poses is not None and len(poses):
        return [round(v, 6) for v in pose_view(poses[0])]
    if model is None:
        return [0.0, 0.0, 2.0, 0.0, 0.0]
    path = drive_path_for(model)
    return [round(v, 6) for v in pose_view(path.pose(0.0))]

