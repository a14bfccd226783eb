"""Rendering a model along a camera path (:mod:`render.paths`) into PNG frames or a video
(``bbcity render``)."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm


from core.fileio import atomic_path, disk_full, write_png

from .camera import default_intrinsics
from .context import create_context
from .paging import PagingConfig
from .renderer import BillboardRenderer
from .sky import SkyPass, render_over_sky
from .tiled_renderer import TiledRenderer

logger = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov")
#: H.264 settings of a video: x264's "superfast" preset at imageio's quality 8.3 keeps the frames as
#: close to the renders as the default preset ("medium") at quality 8 (43.3 against 43.1 dB over the
#: demo's fly-through) with a quarter of the encoder's CPU time, in a file 1.6× the size.
VIDEO_PRESET = "superfast"
VIDEO_QUALITY = 8.3


def render_path(model, poses: np.ndarray, out: os.PathLike | str, size=(1280, 720), *, K=None,
                decode: str = "gpu", cull: str = "frustum", fps: float = 30.0,
                progress: bool | None = None, sky=None, paging=None) -> Path:
    """Render ``poses`` (n, 4, 4) into ``out``: a video when it ends in a video suffix,
    else a directory of PNG frames (``frame_NNNNNN.png``). ``model``: a BillboardModel, or a
    :class:`billboards.model_set.ModelSet` drawn by a :class:`~render.tiled_renderer.TiledRenderer`
    under ``paging`` (a :class:`~render.paging.PagingConfig`; with it a BillboardModel is paged as
    a set of one tile), every frame waiting for the tiles it sees. ``sky``: a
    :class:`billboards.sky.Sky` drawn behind the model (None: a plain light-blue
    background). Written atomically: a
    video appears under its name only when complete, and the frames replace those of
    an earlier render (no stale ones stay) only once all are written; an interrupted
    render leaves ``out`` as it was."""
    out = Path(out)
    K = default_intrinsics(*size) if K is None else np.asarray(K, np.float64)
    ctx = create_context()
    sky_pass = None
    tiled = paging is not None or not hasattr(model, "centres")
    try:
        if tiled:
            renderer = TiledRenderer(ctx, model, decode, cull=cull, background=(0.55, 0.7, 0.9), sky=sky,
                                     paging=paging or PagingConfig())
        else:
            renderer = BillboardRenderer(ctx, model, decode, cull=cull, background=(0.55, 0.7, 0.9))
        with renderer:
            sky_pass = SkyPass(ctx, sky) if sky is not None and not tiled else None
            frames = (renderer.render(K, pose, size, wait="all") if tiled
                      else render_over_sky(renderer, sky_pass, K, pose, size) for pose in poses)
            bar = tqdm(frames, total=len(poses), desc="render", unit="frame",
                       disable=None if progress is None else not progress)
            if out.suffix.lower() in VIDEO_SUFFIXES:
                import imageio.v2 as imageio

                with atomic_path(out) as tmp:
                    # ffmpeg quiet: a failed write is ours to report, in one line (check_video)
                    writer = imageio.get_writer(tmp, fps=fps, codec="libx264", quality=VIDEO_QUALITY,
                                                output_params=["-preset", VIDEO_PRESET], macro_block_size=1,
                                                ffmpeg_log_level="fatal")
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
                    check_video(tmp, len(poses), out)
            else:
                _write_frames(bar, out)
    finally:
        if sky_pass is not None:
            sky_pass.release()
        ctx.release()
    logger.info("rendered %d frames → %s", len(poses), out)
    return out


def check_video(path: Path, frames: int, name: Path) -> None:
    """Raise OSError naming ``name`` unless the video at ``path`` holds ``frames`` frames: ffmpeg
    reports a failed write (a full disk) on its stderr only, and leaves a truncated file."""
    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-hide_banner", "-i", str(path), "-map", "0:v:0",
           "-c", "copy", "-f", "null", "-"]
    result = subprocess.run(cmd, capture_output=True, text=True, errors="replace")
    counts = re.findall(r"frame=\s*(\d+)", result.stderr)
    written = int(counts[-1]) if result.returncode == 0 and counts else 0
    if written != frames:
        code = errno.ENOSPC if disk_full(path.parent) else errno.EIO
        raise OSError(code, f"{os.strerror(code)}: the video holds {written} of {frames} frames", str(name))


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
