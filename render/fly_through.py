"""Rendering a model along a camera path into PNG frames or a video (``bbcity render``).

Paths: ``capture`` drives the capture path (the model's dataset poses, else along
its extent), ``orbit`` circles the model from above, or a file: a dataset
directory (its camera-0 poses) or a JSON list of 4×4 ``world_from_cam`` matrices.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm

from data_synth.fileio import DataFormatError, as_matrix, atomic_path, check_rigid, read_json, write_png

from .benchmark import default_intrinsics
from .camera import look_at
from .context import create_context
from .renderer import BillboardRenderer
from .sky import SkyPass, render_over_sky
from .viewer import drive_path_for

logger = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov")


def capture_poses(model, frames: int) -> np.ndarray:
    """(frames, 4, 4) float64 poses evenly spaced along the capture (drive) path."""
    path = drive_path_for(model)
    return np.stack([path.pose(path.length * i / max(frames, 1)) for i in range(frames)])


def orbit_poses(model, frames: int, height: float = 15.0) -> np.ndarray:
    """(frames, 4, 4) float64 poses on a circle around the model's centre, looking at it."""
    c = np.asarray(model.centres, np.float64)
    origin = np.asarray(model.origin, np.float64)
    if len(c) == 0:
        centre, radius = origin, 10.0
    else:
        lo, hi = c.min(0), c.max(0)
        centre = origin + (lo + hi) / 2
        radius = max(5.0, 0.6 * float(np.linalg.norm(hi[:2] - lo[:2])))
    angles = 2 * np.pi * np.arange(frames) / max(frames, 1)
    eyes = centre + np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(frames, height)], 1)
    return np.stack([look_at(e, centre) for e in eyes]) if frames else np.zeros((0, 4, 4))


def file_poses(path: os.PathLike | str) -> np.ndarray:
    """Poses from a dataset directory (camera 0 of every frame) or a JSON list of 4×4
    ``world_from_cam`` matrices; errors name the file."""
    path = Path(path)
    if path.is_dir():
        from data_synth import load_dataset

        ds = load_dataset(path)
        posed = np.flatnonzero(ds.posed).tolist()
        if not posed:
            raise DataFormatError(path / "poses.json", "no frame has a pose (--path capture follows the poses "
                                                       "the model was built with)")
        return np.stack([ds.world_from_cam(f, 0) for f in posed])
    data = read_json(path)
    if not isinstance(data, list) or not data:
        raise DataFormatError(path, "expected a non-empty JSON list of 4×4 world_from_cam matrices")
    return np.stack([check_rigid(as_matrix(m, (4, 4), path, f"[{i}]"), path, f"[{i}]") for i, m in enumerate(data)])


def camera_path(model, path: str, frames: int) -> np.ndarray:
    """(n, 4, 4) world_from_cam poses for ``path`` = "capture", "orbit" or a file."""
    if path == "capture":
        return capture_poses(model, frames)
    if path == "orbit":
        return orbit_poses(model, frames)
    return file_poses(path)


def render_path(model, poses: np.ndarray, out: os.PathLike | str, size=(1280, 720), *, K=None,
                decode: str = "gpu", cull: str = "frustum", fps: float = 30.0,
                progress: bool | None = None, sky=None) -> Path:
    """Render ``poses`` (n, 4, 4) into ``out``: a video when it ends in a video suffix,
    else a directory of PNG frames (``frame_NNNNNN.png``). ``sky``: a
    :class:`billboards.sky.Sky` drawn behind the model (None: a plain light-blue
    background). Written atomically: a
    video appears under its name only when complete, and the frames replace those of
    an earlier render (no stale ones stay) only once all are written; an interrupted
    render leaves ``out`` as it was."""
    out = Path(out)
    K = default_intrinsics(*size) if K is None else np.asarray(K, np.float64)
    ctx = create_context()
    sky_pass = None
    try:
        with BillboardRenderer(ctx, model, decode, cull=cull, background=(0.55, 0.7, 0.9)) as renderer:
            sky_pass = SkyPass(ctx, sky) if sky is not None else None
            frames = (render_over_sky(renderer, sky_pass, K, pose, size) for pose in poses)
            bar = tqdm(frames, total=len(poses), desc="render", unit="frame",
                       disable=None if progress is None else not progress)
            if out.suffix.lower() in VIDEO_SUFFIXES:
                import imageio.v2 as imageio

                with atomic_path(out) as tmp:
                    writer = imageio.get_writer(tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1,
                                                ffmpeg_log_level="error")
                    try:
                        for image in bar:
                            writer.append_data(image)
                    except BaseException:
                        # imageio's context manager leaves the writer open on an exception: ffmpeg
                        # would go on and write the temporary file after atomic_path removed it
                        with contextlib.suppress(Exception):
                            writer.close()
                        raise
                    writer.close()
            else:
                _write_frames(bar, out)
    finally:
        if sky_pass is not None:
            sky_pass.release()
        ctx.release()
    logger.info("rendered %d frames → %s", len(poses), out)
    return out


def _write_frames(images, out: Path) -> None:
    """Write ``images`` as ``out/frame_NNNNNN.png`` through a temporary directory inside ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".frames.tmp-", dir=out))
    try:
        for i, image in enumerate(images):
            write_png(tmp / f"frame_{i:06d}.png", image)
        for old in out.glob("frame_*.png"):
            old.unlink()
        for new in sorted(tmp.iterdir()):
            os.replace(new, out / new.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def save_poses_json(path: os.PathLike | str, poses: np.ndarray) -> Path:
    """Write poses (n, 4, 4) as the JSON list :func:`file_poses` reads."""
    from data_synth.fileio import write_bytes

    return write_bytes(path, json.dumps([p.tolist() for p in np.asarray(poses, np.float64)]).encode())
