"""``bbcity view``: a billboard model in an interactive window (fly, drive, toggles,
screenshots), or scripted frames and a screenshot under xvfb-run."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import MAX_FRAMES, RENDER_BYTES_PER_PIXEL, UsageError, int_range
from .common import FRAME_SIZE, draw_modes_parent, gpu_budget_parent, load_drawable, logger, paging, size_parent


def add(sub) -> None:
    """The ``view`` command on the subcommands ``sub``."""
    try:
        from render.viewer import KEYS_HELP, WINDOWS
    except ImportError:  # the viewer's GL dependencies are missing; the command still parses
        KEYS_HELP, WINDOWS = None, None

    p = sub.add_parser(
        "view", help="open a billboard model in an interactive window (fly, drive, toggles, screenshots)",
        description="""Open a billboard model in a moderngl-window window: mouse look and WASD/QE fly, a drive mode
                       along the capture path, GPU/CPU decode, level-of-detail, culling and view-interpolation
                       toggles; a HUD and the title bar show frame time and fps, draw and cull time, quads and
                       billboards drawn, quads per level of detail, tiles decoded, decode and cull mode. With
                       --script-frames it renders that many frames along the drive path, saves a screenshot and exits
                       (runs under xvfb-run).""",
        epilog=KEYS_HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[size_parent(FRAME_SIZE, RENDER_BYTES_PER_PIXEL,
                             f"window size (default {FRAME_SIZE[0]} {FRAME_SIZE[1]})"),
                 draw_modes_parent(), gpu_budget_parent()])
    p.add_argument("model", type=Path, help="billboard model directory, plain or tiled (tiles.json)")
    p.add_argument("--mode", choices=("drive", "fly"), default="drive", help="camera mode at start")
    p.add_argument("--exact", action="store_true",
                   help="start with level of detail off (GPU decode of every eigen image everywhere; key L toggles)")
    p.add_argument("--window", default="auto", choices=WINDOWS,
                   help="moderngl-window backend: auto (pyglet, else headless), pyglet, glfw, headless, ...")
    p.add_argument("--screenshot-dir", type=Path, default=Path("."), help="where F12/P screenshots go")
    p.add_argument("--script-frames", type=int_range(0, MAX_FRAMES), default=0,
                   help="render this many frames along the drive path (no input), save a screenshot, exit")
    p.add_argument("--screenshot", type=Path, default=None, help="PNG path for the --script-frames screenshot")
    p.add_argument("--script-keys", default="",
                   help="with --script-frames: comma-separated keys pressed one per frame from the first, "
                        "e.g. C,I,G (moderngl-window key names)")
    p.set_defaults(func=run, check_options=check)


def check(args) -> None:
    """UsageError for a headless window with no script, or a script key the viewer does not answer."""
    from render.viewer import KEY_NAMES

    if args.window == "headless" and args.script_frames == 0:
        raise UsageError("--window headless takes no input and never closes: give --script-frames N")
    keys = [k.strip().upper() for k in args.script_keys.split(",") if k.strip()]
    unknown = [k for k in keys if k not in KEY_NAMES]
    if unknown:
        raise UsageError(f"--script-keys: unknown key {unknown[0]!r}; the viewer answers {', '.join(KEY_NAMES)}")
    if "ESCAPE" in keys:
        raise UsageError("--script-keys: ESCAPE closes the viewer before its screenshot; leave it out")


def run(args) -> int:
    """Open the viewer (paged when the model is tiled or ``--gpu-budget`` is given)."""
    from billboards.model_set import ModelSet
    from billboards.sky import read_sky
    from render.paging import PagingConfig
    from render.viewer import run_viewer

    model = load_drawable(args.model, args.gpu_budget is not None)
    budget = paging(args) or (PagingConfig() if isinstance(model, ModelSet) else None)
    out = run_viewer(model, size=tuple(args.size), decode=args.decode, cull=args.cull, window=args.window,
                     screenshot_dir=args.screenshot_dir, script_frames=args.script_frames,
                     screenshot=args.screenshot, mode=args.mode,
                     script_keys=[k for k in args.script_keys.split(",") if k.strip()], sky=read_sky(args.model),
                     lod=not args.exact, paging=budget)
    if out is not None:
        logger.info("screenshot %s", out)
    return 0
