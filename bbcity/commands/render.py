"""``bbcity render``: a billboard model rendered offscreen along a camera path into PNG frames or
a video."""

from __future__ import annotations

import re
from pathlib import Path

from ..options import MAX_FPS, MAX_FRAMES, RENDER_BYTES_PER_PIXEL, float_range, int_range
from .common import FRAME_SIZE, OwnOutput, draw_modes_parent, gpu_budget_parent, load_drawable, logger, paging, \
    size_parent

#: What a render's frames directory holds: its frames replace those there.
FRAME_FILES = OwnOutput(re.compile(r"frame_\d{6}\.png"), "a render's frames", "its frames replace those there")


def writes_video(out: Path) -> bool:
    """Whether ``--out`` names a video file (rather than a folder of frames)."""
    from render.fly_through import VIDEO_SUFFIXES

    return out.suffix.lower() in VIDEO_SUFFIXES


def add(sub) -> None:
    """The ``render`` command on the subcommands ``sub``."""
    p = sub.add_parser("render", help="render a billboard model along a camera path into frames or a video",
                       description="""Render MODEL offscreen (EGL) along --path: capture (the capture drive), orbit
                                      (a
                                      circle above the model) or FILE (a
                                      dataset directory, or a JSON list of 4×4
                                     
                                      world_from_cam matrices) into PNG frames (--out DIR) or a video (--out X.mp4).""",
                       parents=[size_parent(FRAME_SIZE, RENDER_BYTES_PER_PIXEL,
                                            f"default {FRAME_SIZE[0]} {FRAME_SIZE[1]}"),
                                draw_modes_parent(), gpu_budget_parent()])
    p.add_argument("model", type=Path, help="billboard model directory, plain or tiled (tiles.json)")
    p.add_argument("--path", default="capture", help="capture, orbit or a FILE (default capture)")
    p.add_argument("--out", type=Path, required=True, help="frames directory, or a video file (.mp4, .mkv, ...)")
    p.add_argument("--frames", type=int_range(1, MAX_FRAMES), default=300,
                   help="frames along capture/orbit paths (default 300)")
    p.add_argument("--fps", type=float_range(0.0, MAX_FPS), default=30.0, help="video frame rate (default 30)")
    p.set_defaults(func=run, writes_file=writes_video, own_output=FRAME_FILES)


def run(args) -> int:
    """Render the path into ``--out``."""
    from billboards.sky import read_sky
    from render.fly_through import render_path
    from render.paths import camera_path
    from render.tiled_renderer import path_model

    model = load_drawable(args.model, args.gpu_budget is not None)
    poses = camera_path(path_model(model), args.path, args.frames)
    render_path(model, poses, args.out, tuple(args.size), decode=args.decode, cull=args.cull, fps=args.fps,
                sky=read_sky(args.model), paging=paging(args))
    logger.info("wrote %s", args.out)
    return 0
