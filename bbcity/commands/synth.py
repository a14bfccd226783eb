"""``bbcity synth``: a synthetic street or town, driven by the camera rig, with ground truth."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from ..executor import default_workers
from ..options import GL_MAX_SIZE, MAX_FRAMES, MAX_LENGTH, UsageError, check_memory, float_range, int_range, \
    nonnegative_int, synth_bytes
from .common import command_executor, logger, workers_parent

#: `synth --cameras N`: each camera's offset along the row, metres.
CAMERA_BASELINES = {1: (0.0,), 2: (0.0, 0.8), 3: (0.0, 0.4, 0.8)}


def add(sub) -> None:
    """The ``synth`` command on the subcommands ``sub``."""
    from data_synth import RigConfig, StreetConfig
    from data_synth.config import MAX_SPP, ORBIT_CLEARANCE_M, PATHS, SynthConfig

    p = sub.add_parser(
        "synth", help="generate a synthetic dataset (street or town) with ground truth",
        description="""Generate a synthetic scene, drive the camera rig (three cameras by default) through it and
                       write images, rig.json, poses.json, a COLMAP model and ground truth (gt/).""",
        parents=[workers_parent()])
    p.add_argument("scene", choices=["street", "town"], help="scene to generate")
    p.add_argument("--out", type=Path, required=True, help="output dataset directory (new, or one to resume)")
    frames = p.add_mutually_exclusive_group()
    frames.add_argument("--frames", type=int_range(1, MAX_FRAMES), default=SynthConfig.frames,
                        help=f"frames per pass (default {SynthConfig.frames}); a return pass doubles it")
    frames.add_argument("--frame-spacing", type=float_range(0.0, MAX_LENGTH), default=None, metavar="M",
                        help="instead of --frames: at most M metres between neighbouring frames of a pass "
                             "(frames per pass = ceil(length / M) + 1)")
    p.add_argument("--length", type=float_range(0.0, MAX_LENGTH), default=StreetConfig.length,
                   help=f"street length, or the town drive's length, in metres (default {StreetConfig.length:g})")
    p.add_argument("--width", type=int_range(8, GL_MAX_SIZE, "the OpenGL texture limit"), default=None,
                   help=f"image width in pixels (default {RigConfig.width})")
    p.add_argument("--height", type=int_range(8, GL_MAX_SIZE, "the OpenGL texture limit"), default=None,
                   help=f"image height in pixels (default {RigConfig.height}, portrait)")
    p.add_argument("--seed", type=nonnegative_int, default=StreetConfig.seed,
                   help=f"scene seed; same seed, same bytes (default {StreetConfig.seed})")
    p.add_argument("--hfov", type=float_range(0.0, 170.0, hi_open=True), default=None,
                   help=f"horizontal field of view in degrees (default {RigConfig.hfov_deg:g})")
    p.add_argument("--pitch", type=float_range(-90.0, 90.0, lo_open=False), default=None,
                   help=f"upward tilt of the cameras in degrees (default {RigConfig.pitch_deg:g}; negative looks down)")
    p.add_argument("--cameras", type=int, choices=(1, 2, 3), default=None,
                   help="cameras in the rig's row: 1 (one camera: recon matches neighbouring frames), 2 (0.8 m "
                        "apart) or 3 (0, 0.4, 0.8 m; the default)")
    p.add_argument("--distortion", choices=["none", "radtan", "fisheye"], default=RigConfig.distortion,
                   help="lens of the raw images: none (pinhole, default), or a radial-tangential or fisheye "
                        "preset; images are stored distorted and read back undistorted")
    p.add_argument("--spp", type=int_range(1, MAX_SPP), default=SynthConfig.spp,
                   help=f"anti-aliasing: spp×spp rays per pixel (default {SynthConfig.spp})")
    p.add_argument("--no-return", action="store_true", help="drive one pass only (one side of the street)")
    p.add_argument("--path", choices=PATHS, default=SynthConfig.path,
                   help=f"drive (along the street, and back unless --no-return) or orbit (one loop round a "
                        f"free-standing building: the street opens into a square round the building of its "
                        f"right-hand row nearest its middle, the rig walks a circle of --orbit-radius about the "
                        f"building's centre, its cameras facing it; --frames or --frame-spacing along the circle) "
                        f"(default {SynthConfig.path})")
    p.add_argument("--orbit-radius", type=float_range(0.0, MAX_LENGTH), default=None, metavar="M",
                   help=f"--path orbit: the circle's radius about the building's centre, metres; nothing but the "
                        f"building stands within {ORBIT_CLEARANCE_M:g} m of it (default {SynthConfig.orbit_radius:g})")
    p.add_argument("--no-gt-depth", action="store_true", help="skip per-image ground-truth depth and ids")
    p.add_argument("--lazy", action="store_true",
                   help="write no images (nor ground-truth depth and ids): each frame is ray cast from a section "
                        "of the street when a later stage reads it, the same bytes a stored dataset holds; "
                        "kilobytes on disk whatever --length")
    p.set_defaults(func=run, check_options=config_from_args)


def config_from_args(args):
    """The SynthConfig the ``synth`` options describe; UsageError when the images its
    workers render at once would not fit in the available memory."""
    from data_synth import RigConfig, StreetConfig, TownConfig, frames_for_spacing
    from data_synth.config import ORBIT_CLEARANCE_M, SynthConfig

    orbit = args.path == "orbit"
    if args.orbit_radius is not None and not orbit:
        raise UsageError("--orbit-radius applies to --path orbit")
    if orbit and args.scene != "street":
        raise UsageError("--path orbit needs the street scene: the town's houses stand in closed rows, with no free "
                         "path round one")
    radius = SynthConfig.orbit_radius if args.orbit_radius is None else args.orbit_radius
    cfg = SynthConfig(
        scene=args.scene, path=args.path, orbit_radius=radius,
        # an orbit's street opens into a square round its building, clear of the circle
        street=StreetConfig(length=args.length, seed=args.seed, square=radius + ORBIT_CLEARANCE_M if orbit else 0.0),
        town=TownConfig(seed=args.seed),
        rig=RigConfig(**{k: v for k, v in (("width", args.width), ("height", args.height),
                                           ("hfov_deg", args.hfov), ("pitch_deg", args.pitch),
                                           ("distortion", args.distortion),
                                           ("baselines", CAMERA_BASELINES.get(args.cameras))) if v is not None}),
        frames=args.frames, return_pass=not args.no_return, town_path_length=args.length,
        spp=args.spp, ground_truth_depth=not args.no_gt_depth, lazy=args.lazy)
    if args.frame_spacing is not None:
        frames = frames_for_spacing(cfg.path_length, args.frame_spacing, closed=orbit)
        if frames > MAX_FRAMES:
            raise UsageError(f"--frame-spacing {args.frame_spacing:g} over {cfg.path_length:g} m makes {frames} "
                             f"frames per pass, more than {MAX_FRAMES}")
        cfg = dataclasses.replace(cfg, frames=frames)
    rig, frames = cfg.rig, cfg.frames * cfg.passes
    concurrent = min(args.workers or default_workers(), frames)  # each worker renders one frame at a time
    check_memory(synth_bytes(rig.width, rig.height, cfg.spp, rig.distortion != "none", concurrent),
                 f"synth --width {rig.width} --height {rig.height} --spp {cfg.spp} with {concurrent} workers")
    return cfg


def run(args) -> int:
    """Write the dataset; log its size and the time taken."""
    from data_synth import write_dataset

    cfg = config_from_args(args)
    start = time.perf_counter()
    with command_executor(args) as ex:
        out = write_dataset(cfg, args.out, executor=ex)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    logger.info("wrote %s: %.1f MB in %.1f s", out, size / 1e6, time.perf_counter() - start)
    return 0
