"""The ``bbcity`` command line. The only place that configures logging."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import logging
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path

from core.errors import InputError
from recon.work import Work


from . import __version__
from .cli_share import add_export_kinds, add_fps_web_options, add_serve, check_fps_web, print_web_fps
from .executor import DEFAULT_RETRIES, EXECUTORS
from .options import (EVAL_BYTES_PER_PIXEL, GL_MAX_SIZE, MAX_CITY_SCALE, MAX_FPS, MAX_FRAMES, MAX_LENGTH,
                      MAX_PANEL_WIDTH, MAX_REPEATS, MAX_TILE, MIN_LENGTH, MIN_STEP, RENDER_BYTES_PER_PIXEL,
                      CommandParser, UsageError,
                      build_bytes, check_memory, dimension, float_range, gpu_budget_mb, holdout, int_range, length,
                      nonnegative_float, nonnegative_int, positive_float, positive_int, scheduler_address,
                      size_action, synth_bytes, worker_count, zero_or_at_least)

logger = logging.getLogger("bbcity")


# Options several subcommands share, as argparse parent parsers (``parents=[...]``): one
# definition each, so the commands cannot drift apart in type, check or help.

def _workers_parent() -> argparse.ArgumentParser:
    """``--workers``, ``--executor``, ``--scheduler`` and ``--retries`` of the commands that run
    their tasks in parallel (synth, recon, build): see :func:`_executor_options`."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--workers", type=worker_count, default=None,
                   help="parallel processes of the local pool or of the Dask cluster started here (default: one "
                        "per core)")
    p.add_argument("--executor", choices=EXECUTORS, default=None,
                   help="where tasks run: local (a process pool, the default) or dask (a Dask cluster: the one at "
                        "--scheduler, else one started on this machine)")
    p.add_argument("--scheduler", type=scheduler_address, default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, tcp://host:8786 (implies --executor dask; the dataset, work and "
                        "model directories must be at the same path on every worker's machine)")
    p.add_argument("--retries", type=nonnegative_int, default=None,
                   help=f"dask: times a failed task runs again (default {DEFAULT_RETRIES}); a task failing on bad "
                        f"input fails at once")
    return p


def _executor_options(args) -> dict:
    """``executor_scope``'s keywords from ``--executor``, ``--scheduler`` and ``--retries``
    (UsageError for a contradiction)."""
    kind = args.executor or ("dask" if args.scheduler is not None else "local")
    if kind == "local" and args.scheduler is not None:
        raise UsageError("--scheduler needs --executor dask")
    if kind == "local" and args.retries is not None:
        raise UsageError("--retries applies to --executor dask")
    if args.scheduler is not None and args.workers is not None:
        raise UsageError("--workers sizes a cluster started here; the cluster at --scheduler has the workers "
                         "started on its machines")
    return dict(kind=kind, scheduler=args.scheduler,
                retries=DEFAULT_RETRIES if args.retries is None else args.retries)


def _absolute_paths(args) -> None:
    """Make the path options absolute: Dask tasks carry paths, and a worker elsewhere resolves a
    relative one from its own directory."""
    for name, value in vars(args).items():
        if isinstance(value, Path):
            setattr(args, name, Path(os.path.abspath(value)))


def _size_parent(default: tuple[int, int] | None, bytes_per_pixel: int, help: str) -> argparse.ArgumentParser:
    """``--size W H`` of the commands that render (render, view, eval, fps): each edge within
    the OpenGL limit, W·H·``bytes_per_pixel`` within the available memory."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--size", type=dimension, nargs=2, default=default, metavar=("W", "H"),
                   action=size_action(bytes_per_pixel), help=help)
    return p


def _gpu_budget_parent() -> argparse.ArgumentParser:
    """``--gpu-budget MB`` of the commands that draw a model (render, view, fps)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--gpu-budget", type=gpu_budget_mb, default=None, metavar="MB",
                   help="GPU memory the model's tiles may hold, MB: a tiled model's tiles are loaded in the "
                        "background and uploaded and released as the eye moves (default: no limit; a plain "
                        "model is then paged as one tile)")
    return p


def _paging(args):
    """The PagingConfig of ``--gpu-budget`` (None without it)."""
    from render.paging import MB, PagingConfig

    return None if args.gpu_budget is None else PagingConfig(gpu_budget=int(args.gpu_budget * MB))


def _load_drawable(path: Path, paged: bool):
    """What render, view and fps draw from the model directory ``path``: a tiled model as its
    ModelSet, a plain one as its BillboardModel (as a ModelSet too when ``paged``)."""
    from billboards.model_reader import load
    from billboards.model_set import is_model_set, load_model_set

    if is_model_set(path) or paged:
        return load_model_set(path)
    return load(path)


def _draw_modes_parent() -> argparse.ArgumentParser:
    """``--decode`` and ``--cull`` of the commands that draw a billboard model (render, view)."""
    from render.culling import CULL_MODES

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--decode", choices=("gpu", "cpu"), default="gpu",
                   help="texture decode: in the shader (gpu) or on the CPU (default gpu)")
    p.add_argument("--cull", choices=CULL_MODES, default="frustum",
                   help="culling (default frustum)")
    return p


def _add_synth(sub) -> None:
    from data_synth.dataset import MAX_SPP, ORBIT_CLEARANCE_M, PATHS, SynthConfig

    p = sub.add_parser(
        "synth", help="generate a synthetic dataset (street or town) with ground truth",
        description="Generate a synthetic scene, drive the camera rig (three cameras by default) through it and write "
                    "images, rig.json, poses.json, a COLMAP model and ground truth (gt/).",
        parents=[_workers_parent()])
    p.add_argument("scene", choices=["street", "town"], help="scene to generate")
    p.add_argument("--out", type=Path, required=True, help="output dataset directory (new, or one to resume)")
    frames = p.add_mutually_exclusive_group()
    frames.add_argument("--frames", type=int_range(1, MAX_FRAMES), default=100,
                        help="frames per pass (default 100); a return pass doubles it")
    frames.add_argument("--frame-spacing", type=float_range(0.0, MAX_LENGTH), default=None, metavar="M",
                        help="instead of --frames: at most M metres between neighbouring frames of a pass "
                             "(frames per pass = ceil(length / M) + 1)")
    p.add_argument("--length", type=float_range(0.0, MAX_LENGTH), default=300.0,
                   help="street length, or the town drive's length, in metres (default 300)")
    p.add_argument("--width", type=int_range(8, GL_MAX_SIZE, "the OpenGL texture limit"), default=None,
                   help="image width in pixels (default 416)")
    p.add_argument("--height", type=int_range(8, GL_MAX_SIZE, "the OpenGL texture limit"), default=None,
                   help="image height in pixels (default 736, portrait)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="scene seed; same seed, same bytes (default 0)")
    p.add_argument("--hfov", type=float_range(0.0, 170.0, hi_open=True), default=None,
                   help="horizontal field of view in degrees (default 115)")
    p.add_argument("--pitch", type=float_range(-90.0, 90.0, lo_open=False), default=None,
                   help="upward tilt of the cameras in degrees (default 8; negative looks down)")
    p.add_argument("--cameras", type=int, choices=(1, 2, 3), default=None,
                   help="cameras in the rig's row: 1 (one camera: recon matches neighbouring frames), 2 (0.8 m "
                        "apart) or 3 (0, 0.4, 0.8 m; the default)")
    p.add_argument("--distortion", choices=["none", "radtan", "fisheye"], default="none",
                   help="lens of the raw images: none (pinhole, default), or a radial-tangential or fisheye "
                        "preset; images are stored distorted and read back undistorted")
    p.add_argument("--spp", type=int_range(1, MAX_SPP), default=2,
                   help="anti-aliasing: spp×spp rays per pixel (default 2)")
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
    p.set_defaults(func=_run_synth, check_options=_synth_config)


#: `synth --cameras N`: each camera's offset along the row, metres.
_CAMERA_BASELINES = {1: (0.0,), 2: (0.0, 0.8), 3: (0.0, 0.4, 0.8)}


def _synth_config(args):
    """The SynthConfig the ``synth`` options describe; UsageError when the images its
    workers render at once would not fit in the available memory."""
    from data_synth import RigConfig, StreetConfig, SynthConfig, TownConfig, frames_for_spacing
    from data_synth.dataset import ORBIT_CLEARANCE_M

    from .executor import default_workers

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
                                           ("baselines", _CAMERA_BASELINES.get(args.cameras))) if v is not None}),
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


def _run_synth(args) -> int:
    from data_synth import write_dataset

    from .executor import executor_scope

    cfg = _synth_config(args)
    start = time.perf_counter()
    with executor_scope(args.workers, **_executor_options(args)) as executor:
        out = write_dataset(cfg, args.out, executor=executor)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    logger.info("wrote %s: %.1f MB in %.1f s", out, size / 1e6, time.perf_counter() - start)
    return 0


def _add_import(sub) -> None:
    p = sub.add_parser(
        "import", help="a capture of your own (KITTI sequence, COLMAP model, photos, video, nerfstudio) → a dataset",
        description="Turn a capture into a dataset directory (rig.json, poses.json, images/) that recon, build "
                    "and eval read like a synthetic one. The new directory is written whole or not at all.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    k = kinds.add_parser("kitti", help="a KITTI odometry sequence (calib.txt, poses.txt, a stereo pair of image folders)",
                         description="Import a KITTI odometry sequence: calib.txt (P0..P3), poses.txt (world_from_cam0 "
                                     "per frame) and image_0/1 (grey), image_2/3 (colour) or image_l/r.")
    k.add_argument("sequence", type=Path, help="sequence directory")
    k.add_argument("--out", type=Path, required=True, help="new dataset directory")
    k.add_argument("--cameras", choices=("auto", "grey", "colour", "lr"), default="auto",
                   help="which stereo pair (default auto: colour, else grey, else image_l/r)")
    k.add_argument("--camera-height", type=nonnegative_float, default=1.65,
                   help="height of KITTI's cam0 (the left grey camera, whose poses poses.txt holds) above the road "
                        "in metres (default 1.65, KITTI's car)")
    k.add_argument("--first", type=nonnegative_int, default=0, help="first frame (default 0)")
    k.add_argument("--count", type=positive_int, default=None, help="frames to import (default: all)")
    k.add_argument("--step", type=positive_int, default=1, help="every n-th frame (default 1)")
    k.set_defaults(func=_run_import_kitti, check_options=_kitti_config)
    c = kinds.add_parser("colmap", help="a COLMAP sparse model (text or binary) and its image folder",
                         description="Import a COLMAP model: its cameras (pinhole, radtan and fisheye models kept, "
                                     "other lenses undistorted here), a rig of several cameras or one camera, and "
                                     "the registered poses, turned so that z points up (cameras held roughly "
                                     "level). The model's scale is kept.")
    c.add_argument("model", type=Path, help="COLMAP model directory (cameras, images[, rigs, frames] .txt or .bin)")
    c.add_argument("--images", type=Path, required=True, help="folder that the model's image names are relative to")
    c.add_argument("--out", type=Path, required=True, help="new dataset directory")
    c.add_argument("--metric", action="store_true", help="the model is in metres (recorded in dataset.json)")
    c.set_defaults(func=_run_import_colmap)
    f = kinds.add_parser("photos", help="a folder of one camera's photos (poses unknown: recon --poses sfm)",
                         description="Import a folder of JPEG/PNG photos of one camera, all the same size, in file-name "
                                     "order, stored upright (EXIF orientation). Intrinsics from --intrinsics (of the "
                                     "upright image) or the photos' EXIF focal length. The poses are unknown: "
                                     "reconstruct with `bbcity recon DATASET --poses sfm`, which scales the result to "
                                     "--step-length metres between consecutive photos, else to the photos' EXIF GPS "
                                     "positions.")
    f.add_argument("folder", type=Path, help="folder of photos")
    f.add_argument("--out", type=Path, required=True, help="new dataset directory")
    f.add_argument("--intrinsics", type=Path, default=None,
                   help="K file: 3 lines of a 3×3 matrix or one line \"fx fy cx cy\" (OpenCV pixel centres), "
                        "optionally followed by \"k1 k2 p1 p2 [k3]\" (default: EXIF)")
    f.add_argument("--sensor-width", type=positive_float, default=None,
                   help="sensor width in mm, with EXIF FocalLength when the photos lack a 35 mm equivalent")
    f.add_argument("--step-length", type=positive_float, default=None,
                   help="metres between consecutive photos, SfM's scale (default: none; SfM then takes it from the "
                        "photos' EXIF GPS positions when every photo has one, else its units are arbitrary)")
    f.set_defaults(func=_run_import_photos, check_options=_photos_config)
    _add_import_video(kinds)
    _add_import_nerfstudio(kinds)


def _add_import_video(kinds) -> None:
    from recon.importers.video_config import DEFAULT_FPS, VideoConfig  # light: no OpenCV, no Open3D

    d = VideoConfig()
    v = kinds.add_parser("video", help="a video of one camera (frames sampled, blurred ones dropped; poses unknown: "
                                       "recon --poses sfm)",
                         description="Import a video of one camera (any format ffmpeg reads): frames sampled at --fps "
                                     f"per second (default {DEFAULT_FPS:g}) or --frames spread over the video, the "
                                     f"sharpest of each {d.sharpest_of} consecutive frames kept and blurred ones "
                                     "dropped (variance of the Laplacian), named frame_NNNNNN by their index in the "
                                     "video. Intrinsics from --intrinsics (a video has no EXIF). The poses are "
                                     "unknown: reconstruct with `bbcity recon DATASET --poses sfm`.")
    v.add_argument("video", type=Path, help="video file")
    v.add_argument("--out", type=Path, required=True, help="new dataset directory")
    v.add_argument("--intrinsics", type=Path, default=None,
                   help="K file of the upright frames (required): 3 lines of a 3×3 matrix or one line "
                        "\"fx fy cx cy\" (OpenCV pixel centres), optionally followed by \"k1 k2 p1 p2 [k3]\"")
    rate = v.add_mutually_exclusive_group()
    rate.add_argument("--fps", type=positive_float, default=None,
                      help=f"frames kept per second of video (default {DEFAULT_FPS:g})")
    rate.add_argument("--frames", type=positive_int, default=None,
                      help="instead of --fps: this many frames spread evenly over the whole video")
    v.add_argument("--step-length", type=positive_float, default=None,
                   help="metres between consecutive kept frames (walking speed ÷ --fps), SfM's scale (default: "
                        "none, arbitrary units)")
    v.set_defaults(func=_run_import_video, check_options=_video_config)


def _add_import_nerfstudio(kinds) -> None:
    n = kinds.add_parser("nerfstudio", help="a nerfstudio transforms.json (one camera, given poses) and its images",
                         description="Import a nerfstudio dataset: transforms.json (intrinsics fl_x fl_y cx cy w h, "
                                     "camera_model PINHOLE/OPENCV/OPENCV_FISHEYE with k1..k4 p1 p2, frames of "
                                     "file_path and camera-to-world transform_matrix in OpenGL axes) and the images "
                                     "it names. Every frame must share one camera. A z-up world (nerfstudio's "
                                     "convention) is kept as it is; its scale is kept.")
    n.add_argument("transforms", type=Path, help="transforms.json, or the folder holding it")
    n.add_argument("--out", type=Path, required=True, help="new dataset directory")
    n.add_argument("--metric", action="store_true", help="the poses are in metres (recorded in dataset.json)")
    n.add_argument("--world", choices=("auto", "keep", "level"), default=None,
                   help="auto (default): keep the world when the cameras' up is near +z (nerfstudio's convention), "
                        "else turn it z-up; keep: never turn it; level: always turn it (origin at the first camera)")
    n.set_defaults(func=_run_import_nerfstudio, check_options=_nerfstudio_import_config)


def _run_import_colmap(args) -> int:
    from recon.importers.colmap import ColmapImportConfig, import_colmap

    out = import_colmap(args.model, args.images, args.out, ColmapImportConfig(metric=args.metric))
    logger.info("wrote %s", out)
    return 0


def _photos_config(args):
    from recon.importers.photos import PhotosConfig

    return PhotosConfig(intrinsics=args.intrinsics, sensor_width_mm=args.sensor_width, step_length=args.step_length)


def _run_import_photos(args) -> int:
    from recon.importers.photos import import_photos

    out = import_photos(args.folder, args.out, _photos_config(args))
    logger.info("wrote %s; its poses are unknown: bbcity recon %s --poses sfm", out, out)
    return 0


def _video_config(args):
    from recon.importers.video_config import VideoConfig

    given = {"intrinsics": args.intrinsics, "fps": args.fps, "frames": args.frames, "step_length": args.step_length}
    return VideoConfig(**{k: v for k, v in given.items() if v is not None})


def _run_import_video(args) -> int:
    from recon.importers.video import import_video

    out = import_video(args.video, args.out, _video_config(args))
    logger.info("wrote %s; its poses are unknown: bbcity recon %s --poses sfm", out, out)
    return 0


def _nerfstudio_import_config(args):
    from recon.importers.nerfstudio import NerfstudioImportConfig

    return NerfstudioImportConfig(metric=args.metric, **({"world": args.world} if args.world is not None else {}))


def _run_import_nerfstudio(args) -> int:
    from recon.importers.nerfstudio import import_nerfstudio

    out = import_nerfstudio(args.transforms, args.out, _nerfstudio_import_config(args))
    logger.info("wrote %s", out)
    return 0


def _add_export(sub) -> None:
    p = sub.add_parser(
        "export", help="a dataset → another tool's format (nerfstudio), to compare methods on the same capture",
        description="Write a dataset in another tool's format. The new directory is written whole or not at all.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    n = kinds.add_parser("nerfstudio", help="transforms.json and images/ for nerfstudio (nerfacto, splatfacto …)",
                         description="Write OUT/transforms.json and OUT/images/: every posed frame's image of every "
                                     "camera, undistorted, with its camera's pose (camera-to-world, OpenGL axes, the "
                                     "dataset's z-up world) and pinhole intrinsics. Frames without a pose are left "
                                     "out. --holdout N lists the frames recon/build --holdout N leave out as "
                                     "nerfstudio's test_filenames (camera 0, the views bbcity eval compares).")
    n.add_argument("dataset", type=Path, help="dataset directory (rig.json, poses.json, images/)")
    n.add_argument("--out", type=Path, required=True, help="new nerfstudio dataset directory")
    n.add_argument("--poses", type=Path, default=None,
                   help="a poses.json to use instead of the dataset's (e.g. WORK/poses.json of recon --poses sfm)")
    n.add_argument("--holdout", type=holdout, default=None,
                   help="hold every n-th frame out of training, as recon/build --holdout (default 0: none; "
                        "nerfstudio then splits by its own rule)")
    n.set_defaults(func=_run_export_nerfstudio, check_options=_nerfstudio_export_config)
    add_export_kinds(kinds)


def _nerfstudio_export_config(args):
    from recon.importers.nerfstudio_export import NerfstudioExportConfig

    return NerfstudioExportConfig(**({"holdout": args.holdout} if args.holdout is not None else {}))


def _run_export_nerfstudio(args) -> int:
    from recon.importers.nerfstudio_export import export_nerfstudio

    export_nerfstudio(args.dataset, args.out, _nerfstudio_export_config(args), poses=args.poses)
    return 0


def _kitti_config(args):
    from recon.importers.kitti import KittiConfig

    return KittiConfig(cameras=args.cameras, camera_height=args.camera_height, first=args.first, count=args.count,
                       step=args.step)


def _run_import_kitti(args) -> int:
    from recon.importers.kitti import import_kitti

    out = import_kitti(args.sequence, args.out, _kitti_config(args))
    logger.info("wrote %s", out)
    return 0


def _add_recon(sub) -> None:
    from recon.pipeline import ReconConfig

    p = sub.add_parser(
        "recon", help="stereo (rig of 1, 2 or 3 cameras) → fused coloured point cloud (cloud.ply)",
        description="Rectify each camera pair, match by SGBM with a left-right check, fuse the pairs per frame "
                    "(three cameras: three pairs that must agree; two: one pair; one: neighbouring frames), merge all frames by voxel hashing, remove outliers and write "
                    "WORK/cloud.ply and WORK/recon_report.json (with accuracy and completeness when "
                    "the dataset has ground truth).",
        parents=[_workers_parent()])
    p.add_argument("dataset", type=Path, help="dataset directory (rig.json, poses.json, images/)")
    p.add_argument("--out", type=Path, required=True, help="work directory")
    p.add_argument("--poses", choices=("given", "sfm", "colmap"), default="given",
                   help="pose source: given (poses.json, the default), sfm (pycolmap) or colmap (the COLMAP model "
                        "at --colmap-model)")
    p.add_argument("--colmap-model", type=Path, default=None, metavar="DIR",
                   help="with --poses colmap: the COLMAP model directory (cameras, images .txt or .bin)")
    p.add_argument("--preset", default="accurate", help="stereo preset: fast, balanced or accurate (default: accurate)")
    p.add_argument("--voxel-size", type=length, default=0.02,
                   help="fused cloud resolution in metres (default 0.02)")
    p.add_argument("--min-depth", type=length, default=None, help="nearest depth to match, metres")
    p.add_argument("--max-depth", type=float_range(MIN_LENGTH, lo_open=False, allow_inf=True), default=None,
                   help="farthest depth to match, metres (inf: no limit)")
    p.add_argument("--frame-stride", type=positive_int, default=1, help="use every n-th frame (default 1)")
    p.add_argument("--wls", action="store_true", help="WLS-filter the disparities (smoother, slower)")
    p.add_argument("--min-agree", type=int, choices=(2, 3), default=3,
                   help="three-camera rigs: pairs that must agree on a pixel's depth (default 3; 2 keeps more, "
                        "with more errors); a two-camera rig has one pair, one camera its own rule")
    p.add_argument("--holdout", type=holdout, default=0,
                   help="leave every n-th frame out of the cloud, for `bbcity eval` on held-out views (default 0: "
                        "none; 4 uses 75 %% of the frames); `bbcity build` of this WORK leaves the same frames out")
    p.add_argument("--max-image-size", type=nonnegative_int, default=ReconConfig.max_image_size,
                   help="stereo and SfM features work on images at most this many pixels along their longer side "
                        f"(default {ReconConfig.max_image_size}; 0: full size); a pair that does not fit in the "
                        "memory free is matched at half that, and half again")
    p.add_argument("--no-eval", action="store_true", help="skip the ground-truth evaluation")
    p.set_defaults(func=_run_recon, check_options=_recon_config)


def _recon_config(args):
    """The ReconConfig the ``recon`` options describe (UsageError for a bad combination)."""
    from recon.fusion import FusionConfig
    from recon.pipeline import POSE_SOURCES, ReconConfig
    from recon.stereo import PRESETS
    from recon.trinocular import TrinocularConfig

    if args.poses not in POSE_SOURCES:
        raise UsageError(f"--poses takes {', '.join(POSE_SOURCES)}; got {args.poses!r}")
    if args.poses == "colmap" and args.colmap_model is None:
        raise UsageError("--poses colmap needs --colmap-model DIR (the COLMAP model directory)")
    if args.poses != "colmap" and args.colmap_model is not None:
        raise UsageError(f"--colmap-model goes with --poses colmap, not --poses {args.poses}")
    if args.preset not in PRESETS:
        raise UsageError(f"unknown --preset {args.preset!r}; choose from {', '.join(PRESETS)}")
    stereo = PRESETS[args.preset]
    overrides = {k: v for k, v in (("min_depth", args.min_depth), ("max_depth", args.max_depth)) if v is not None}
    if args.wls:
        overrides["wls"] = True
    stereo = dataclasses.replace(stereo, **overrides)
    conf = ReconConfig(trinocular=TrinocularConfig(stereo=stereo, min_agree=args.min_agree), fusion=FusionConfig(voxel_size=args.voxel_size),
                       poses=args.poses, colmap_model=None if args.colmap_model is None else str(args.colmap_model),
                       frame_stride=args.frame_stride, max_image_size=args.max_image_size or None,
                       evaluate=not args.no_eval, holdout=args.holdout)
    return conf


def _run_recon(args) -> int:
    from recon.pipeline import main as recon_main

    from .executor import executor_scope

    conf = _recon_config(args)
    with executor_scope(args.workers, **_executor_options(args)) as executor:
        cloud = recon_main(conf, args.dataset, args.out, executor=executor)
    logger.info("wrote %s and %s", cloud, cloud.with_name("recon_report.json"))
    return 0


def _add_build(sub) -> None:
    from billboards.fit import FitConfig
    from billboards.octree import MAX_MIN_POINTS
    from billboards.geometry import MAX_SPLIT
    from billboards.layer import LayerConfig
    from billboards.resolution import ResolutionConfig
    from billboards.octree import MAX_DEPTH
    from billboards.wall_depth import WallDepthConfig

    p = sub.add_parser(
        "build", help="cloud + images → billboard model (octree, angular sampling, PCA, atlases)",
        description="Voxelise the fused cloud with an octree, give each voxel a view-facing billboard, "
                    "sample its texture in d directions from the captured images (occlusion-aware), "
                    "compress each billboard's stack by PCA into eigen-textures and pack them into atlas "
                    "pages. Writes MODEL/ (manifest.json, .npy arrays, atlas pages) and "
                    "MODEL/build_report.json.",
        parents=[_workers_parent()])
    p.add_argument("work", type=Path, nargs="?", default=None,
                   help="recon work directory (cloud.ply; recon_report.json names the dataset)")
    p.add_argument("--out", type=Path, required=True, help="model directory (replaced atomically)")
    p.add_argument("--cloud", type=Path, default=None, help="a PLY/PCD cloud of your own (instead of WORK/cloud.ply)")
    p.add_argument("--images", type=Path, default=None,
                   help="dataset directory with rig.json, poses.json and images/ (default: the one WORK was built from)")
    p.add_argument("--poses", type=Path, default=None,
                   help="a poses.json to use instead of the dataset's (default: WORK/poses.json when the recon "
                        "computed its poses, e.g. --poses sfm on a photo folder: the cloud is in their frame)")
    p.add_argument("--texture-source", choices=("images", "points"), default="images",
                   help="sample textures from the images (default) or splat the cloud's own points")
    p.add_argument("--voxel-size", type=length, default=0.5,
                   help="billboard/voxel edge in metres (default 0.5)")
    p.add_argument("--depth", type=int_range(0, MAX_DEPTH, "a Morton code's bits"), default=None,
                   help="octree depth instead of --voxel-size")
    p.add_argument("--min-points", type=int_range(1, MAX_MIN_POINTS), default=10,
                   help="points a voxel needs to get a billboard (default 10)")
    p.add_argument("--directions", type=positive_int, default=32, help="yaw directions per billboard (default 32)")
    p.add_argument("--spacing", type=float_range(0.0, 360.0), default=6.0,
                   help="degrees between directions (default 6)")
    p.add_argument("--pitches", type=float_range(-90.0, 90.0, hi_open=True), nargs="+", default=[0.0],
                   help="pitch rows in degrees (default 0)")
    p.add_argument("--pitched-quads", action="store_true", help="quads also tilt toward the viewer's elevation")
    p.add_argument("--tile", type=int_range(1, MAX_TILE), default=8,
                   help=f"texels per billboard side, at most --page-size and {MAX_TILE} (default 8)")
    p.add_argument("--naive", action="store_true", help="nearest-frame sampling without the occlusion test")
    p.add_argument("--ratio", type=float_range(0.0, 1.0), default=None,
                   help="PCA cumulative contribution ratio (default: the PcaConfig's)")
    p.add_argument("--max-error", type=nonnegative_float, default=None,
                   help="PCA RMS error bound in 8-bit units (default: the PcaConfig's; 0 turns the rule off)")
    p.add_argument("--rank", type=nonnegative_int, default=None,
                   help="fixed rank for every billboard (overrides the rules)")
    p.add_argument("--max-rank", type=nonnegative_int, default=None, help="largest rank (default: the PcaConfig's)")
    p.add_argument("--tile-mode", choices=("u8", "f16"), default="u8", help="eigen image precision (default u8)")
    p.add_argument("--coef-mode", choices=("f32", "f16", "u8"), default="f16",
                   help="coefficient precision (default f16)")
    p.add_argument("--page-size", type=dimension, default=8192,
                   help=f"atlas page edge in texels, at most {GL_MAX_SIZE} (default 8192)")
    p.add_argument("--holdout", type=holdout, default=None,
                   help="leave every n-th frame's images out of the textures (for `bbcity eval`; default: the "
                        "recon's --holdout, else 0: none)")
    p.add_argument("--layer", choices=("facades+ground", "facades", "ground", "none"), default="facades+ground",
                   help="the facade layer under the billboards: slits on the facades found in the EPIs and/or "
                        "blocks on flat ground (default both; none: billboards only)")
    p.add_argument("--block-size", type=length, default=None,
                   help="edge of the layer's blocks in metres (default: the voxel size)")
    p.add_argument("--ground-reach", type=nonnegative_float, default=LayerConfig.ground_reach,
                   help="continue the ground across gaps up to this wide (m) between ground cells where nothing "
                        "stands; blocks no camera saw get a texture synthesised from ground nearby, marked in the "
                        f"model (0: off; default {LayerConfig.ground_reach:g})")
    res = ResolutionConfig()
    p.add_argument("--ground-splits", type=int, choices=range(0, MAX_SPLIT + 1), default=res.max_split,
                   help="halve ground blocks up to this many times where the capture saw them finer than their "
                        f"texels (a texel at most {res.texel_pixels:g} capture pixels wide; 0: never; default "
                        f"{res.max_split})")
    p.add_argument("--side-walls", choices=("on", "off"), default="on" if LayerConfig.side_walls else "off",
                   help="slits on the walls at the ends of the facades (a building's side seen from the path), "
                        "instead of billboards (default on)")
    depth = WallDepthConfig()
    p.add_argument("--wall-reach", type=nonnegative_float, default=depth.reach,
                   help="grow side walls up to this far (m) beyond their deepest cloud point where the images show "
                        f"them against the sky (0: off; default {depth.reach:g})")
    p.add_argument("--wall-rise", type=nonnegative_float, default=depth.rise,
                   help="grow side walls up to this far (m) above their top where the images show them against "
                        f"the sky (0: off; default {depth.rise:g})")
    p.add_argument("--kerbs", choices=("on", "off"), default="on" if LayerConfig.kerbs else "off",
                   help="a fixed face on each step between two ground levels (a kerb) instead of billboards "
                        "(default on)")
    p.add_argument("--photometry", choices=("on", "off"), default="on",
                   help="estimate per-image exposure and white-balance gains from the overlaps and divide them "
                        "out before sampling textures (default on)")
    p.add_argument("--fit", choices=("on", "off"), default="on",
                   help="fit the sampled textures to the training images through the rendering, then compress "
                        "(default on)")
    p.add_argument("--fit-seconds", type=nonnegative_float, default=FitConfig.seconds,
                   help=f"wall-clock budget of the fit's iterations in seconds (default {FitConfig.seconds:g}; "
                        "each tile's with --tile-metres)")
    p.add_argument("--fit-alpha", choices=("on", "off"), default="on" if FitConfig.alpha else "off",
                   help="let the training images decide which texels of the facade layer and the ground are shown "
                        "and which are seen through, before the colours are fitted (default "
                        f"{'on' if FitConfig.alpha else 'off'}; a tiled build keeps the sampled alpha)")
    p.add_argument("--tile-metres", type=length, default=None,
                   help="build a model set of square tiles this wide, one at a time, so that memory does not grow "
                        "with the street (a whole number of voxels; the viewer pages them; a killed build resumes "
                        "its unfinished tiles; default: one model)")
    p.set_defaults(func=_run_build, check_options=_check_build)


def build_config_from_args(args):
    """The BuildConfig the ``build`` options describe."""
    from billboards.build import BuildConfig
    from billboards.fit import FitConfig
    from billboards.geometry import DirectionConfig
    from billboards.layer import LayerConfig
    from billboards.resolution import ResolutionConfig
    from billboards.octree import OctreeConfig
    from billboards.pca import PcaConfig
    from billboards.photometry import PhotometryConfig
    from billboards.sampling import SamplingConfig
    from billboards.wall_depth import WallDepthConfig

    pca = PcaConfig()
    overrides = {}
    if args.ratio is not None:
        overrides["ratio"] = args.ratio
    if args.max_error is not None:
        overrides["max_error"] = args.max_error if args.max_error > 0 else None
    if args.rank is not None:
        overrides["fixed_rank"] = args.rank
    if args.max_rank is not None:
        overrides["max_rank"] = args.max_rank
    pca = dataclasses.replace(pca, **overrides)
    directions = DirectionConfig(count=args.directions, spacing_deg=args.spacing, pitches_deg=tuple(args.pitches),
                                 pitched_quads=args.pitched_quads)
    octree = OctreeConfig(voxel_size=None if args.depth is not None else args.voxel_size, depth=args.depth,
                          min_points=args.min_points)
    sampling = SamplingConfig(tile=args.tile, directions=directions, occlusion=not args.naive)
    layer = None if args.layer == "none" else LayerConfig(facades="facades" in args.layer, ground="ground" in args.layer,
                                                          block_size=args.block_size, ground_reach=args.ground_reach,
                                                          side_walls=args.side_walls == "on", kerbs=args.kerbs == "on",
                                                          resolution=ResolutionConfig(max_split=args.ground_splits),
                                                          wall_depth=WallDepthConfig(reach=args.wall_reach,
                                                                                     rise=args.wall_rise))
    return BuildConfig(octree=octree, sampling=sampling, pca=pca, source=args.texture_source,
                       tile_mode=args.tile_mode, coef_mode=args.coef_mode, page_size=args.page_size,
                       holdout=args.holdout, layer=layer,
                       photometry=PhotometryConfig() if args.photometry == "on" else None,
                       fit=FitConfig(seconds=args.fit_seconds, alpha=args.fit_alpha == "on") if args.fit == "on"
                       else None,
                       tile_metres=args.tile_metres)


def _check_build(args) -> None:
    """UsageError when the ``build`` options contradict each other or the atlas pages, or
    when the workers' sampled textures would not fit in the available memory."""
    from .executor import default_workers

    if args.tile > args.page_size:
        raise UsageError(f"--tile {args.tile} is larger than the atlas page (--page-size {args.page_size})")
    if args.tile_metres is not None:
        if args.depth is not None:
            raise UsageError("--tile-metres needs --voxel-size, not --depth (tiles share one voxel grid)")
        voxels = args.tile_metres / args.voxel_size
        if abs(voxels - round(voxels)) > 1e-9:
            raise UsageError(f"--tile-metres {args.tile_metres:g} is not a whole number of voxels "
                             f"(--voxel-size {args.voxel_size:g})")
    d = args.directions * len(args.pitches)
    if d > args.page_size:  # a billboard's coefficient row (d texels) fills one atlas page row at most
        raise UsageError(f"--directions × --pitches = {d} directions do not fit an atlas page row "
                         f"(--page-size {args.page_size})")
    # every config validates its values; the work directory's --holdout is not read yet
    conf = build_config_from_args(argparse.Namespace(**{**vars(args), "holdout": args.holdout or 0}))
    n = args.workers or default_workers()
    check_memory(build_bytes(args.tile, d, conf.chunk, n, conf.chunk * conf.task_chunks if conf.fit else 0),
                 f"build --tile {args.tile} with {d} directions and {n} workers")


def _run_build(args) -> int:
    from billboards.build import main as build_main

    from .executor import executor_scope

    if args.work is None and args.cloud is None:
        raise UsageError("give a recon WORK directory or --cloud")
    cloud = args.cloud or args.work / "cloud.ply"
    _refuse_out_over(args.out, [cloud] + ([args.work / "recon_report.json"] if args.work is not None else []))
    dataset = _work_dataset(args) if args.work is not None and args.texture_source == "images" else args.images
    _refuse_out_over(args.out, [p for p in (dataset, args.poses) if p is not None])
    if args.holdout is None:
        args.holdout = Work.open(args.work).holdout() if args.work is not None and args.cloud is None else 0
    poses = args.poses
    if poses is None and args.work is not None and args.cloud is None and dataset is not None:
        poses = Work.open(args.work).poses_file()  # WORK's cloud lies in the frame of the poses its recon used
    conf = build_config_from_args(args)
    with executor_scope(args.workers, **_executor_options(args)) as executor:
        result = build_main(conf, cloud, dataset, args.out, executor=executor, poses=poses)
    r = result.report
    psnr = r["psnr"]["decoded_rgb_opaque_db"]  # None: no opaque texel measured
    logger.info("%d billboards, compression %.1f× at %s dB (decoded RGB), %.1f s → %s", r["billboards"],
                r["compression_ratio"], "n/a" if psnr is None else f"{psnr:.2f}", r["total_s"], result.model)
    return 0


def _refuse_out_over(out: Path, inputs: list[Path]) -> None:
    """UsageError when the output directory ``out`` is one of ``inputs`` or holds one: a
    command writes its output whole in place of ``out``, and would delete what it reads."""
    where = out.resolve()
    for path in inputs:
        source = Path(path).resolve()
        if where == source or where in source.parents:
            raise UsageError(f"--out {out} holds {path}, which this command reads; its output would replace "
                             "it: choose another directory")


def _work_dataset(args) -> Path:
    """The dataset of a command on a recon WORK directory (build, texture-sweep, sampling-eval):
    its ``--images``, else the one WORK was built from (its recon_report.json says)."""
    return args.images or Work.open(args.work).dataset()


def _add_texture_sweep(sub) -> None:
    p = sub.add_parser("texture-sweep", help="eigen-texture bytes and decode PSNR against build time",
                       description="Sample neighbouring billboards from the middle of the street once per texel "
                                   "size, compress them under fixed ranks 0–16, contribution ratios, error bounds "
                                   "and quantisation modes; write a table, JSON and a work-precision plot.")
    p.add_argument("work", type=Path, help="recon work directory (cloud.ply, recon_report.json)")
    p.add_argument("--out", type=Path, required=True, help="report directory")
    p.add_argument("--images", type=Path, default=None, help="dataset directory (default: WORK's)")
    p.add_argument("--count", type=positive_int, default=1024, help="billboards to sample (default 1024)")
    p.add_argument("--tiles", type=int_range(1, MAX_TILE), nargs="+", default=[8, 16, 32],
                   help="texel sizes (default 8 16 32)")
    p.set_defaults(func=_run_texture_sweep)


def _run_texture_sweep(args) -> int:
    from .sweeps import texture_sweep

    dataset = _work_dataset(args)
    texture_sweep(args.work / "cloud.ply", dataset, args.out, count=args.count, tiles=tuple(args.tiles))
    logger.info("wrote %s", args.out / "texture_sweep.md")
    return 0


def _add_sampling_eval(sub) -> None:
    p = sub.add_parser("sampling-eval", help="texture error of occlusion-aware vs naive sampling against ground truth",
                       description="On a synthetic dataset: sample billboards near occluders and at random with "
                                   "occlusion-aware and naive nearest-frame sampling, render the ground-truth "
                                   "texture of every sampled direction cut to the voxel's slab, and report PSNR "
                                   "(all texels, and the texels an occluder hides from the first camera).")
    p.add_argument("work", type=Path, help="recon work directory (cloud.ply, recon_report.json)")
    p.add_argument("--out", type=Path, required=True, help="report directory")
    p.add_argument("--images", type=Path, default=None, help="dataset directory with gt/ (default: WORK's)")
    p.add_argument("--count", type=positive_int, default=200, help="billboards per set (default 200)")
    p.add_argument("--voxel-size", type=length, default=0.5,
                   help="billboard/voxel edge in metres (default 0.5)")
    p.set_defaults(func=_run_sampling_eval)


def _run_sampling_eval(args) -> int:
    from billboards.evaluate import compare_sampling, markdown
    from billboards.octree import OctreeConfig
    from core.fileio import write_bytes, write_json

    dataset = _work_dataset(args)
    report = compare_sampling(dataset, args.work / "cloud.ply", OctreeConfig(voxel_size=args.voxel_size),
                              count=args.count)
    write_json(args.out / "sampling_eval.json", report)
    write_bytes(args.out / "sampling_eval.md", markdown(report).encode())
    logger.info("wrote %s", args.out / "sampling_eval.md")
    return 0


def _add_stereo_sweep(sub) -> None:
    p = sub.add_parser("stereo-sweep", help="stereo error against seconds per frame over SGBM settings",
                       description="Run trinocular stereo on a few frames of a dataset with ground truth for "
                                   "several SGBM settings; write a table, JSON and a work-precision plot.")
    p.add_argument("dataset", type=Path, help="dataset directory with gt/")
    p.add_argument("--out", type=Path, required=True, help="report directory")
    p.add_argument("--frames", type=positive_int, default=4,
                   help="frames to evaluate, spread along the path (default 4)")
    p.set_defaults(func=_run_stereo_sweep)


def _run_stereo_sweep(args) -> int:
    from .sweeps import stereo_sweep

    stereo_sweep(args.dataset, args.out, args.frames)
    print((args.out / "stereo_sweep.md").read_text())
    return 0


def _add_check(sub) -> None:
    p = sub.add_parser("check", help="validate a dataset (rig, poses, every image)",
                       description="Validate rig.json, poses.json and that every image exists; "
                                   "with --deep also decode every image and ground-truth array.")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--deep", action="store_true", help="decode every image (slow)")
    p.set_defaults(func=_run_check)


def _run_check(args) -> int:
    from data_synth import load_dataset

    ds = load_dataset(args.dataset)
    if args.deep:
        ds.verify()
    w, h = ds.rig.sizes[0]
    print(f"{ds.root}: {ds.num_frames} frames × {ds.rig.num_cameras} cameras, {w}x{h}, "
          f"ground truth: {'yes' if ds.has_ground_truth else 'no'}")
    return 0


def _add_bench(sub) -> None:
    p = sub.add_parser("bench", help="measure the stages against same-run baselines; write a report",
                       description="Run the whole pipeline on the standard scenes and write report.md, report.json "
                                   "and PNG plots to --out: the stage table, octree, stereo, textures, rendering "
                                   "(street and town culling), novel views and scaling (1×, 2×, 4× street length). "
                                   "Every speed is paired with a baseline measured in the same run.")
    p.add_argument("--out", type=Path, required=True, help="report directory")
    p.add_argument("--scene", choices=("all", "street", "town", "executor", "city"), default="all",
                   help="street: the pipeline and everything measured on its model; town: culling on the town; "
                        "executor: recon and build through the local pool and through Dask; city (not in all): "
                        "streets of --city-scales × --street-length built tile by tile and paged by the viewer")
    p.add_argument("--city-scales", type=int_range(1, MAX_CITY_SCALE), nargs="+", default=None,
                   help="street lengths of the city runs in multiples of --street-length (default 1 4 16)")
    p.add_argument("--gpu-budget", type=positive_int, default=None, metavar="MB",
                   help="city: the viewer's GPU budget (256); memory is flat from 1× only if the 1× street fills it")
    p.add_argument("--lazy", action="store_true",
                   help="city: datasets cast on demand (kilobytes on disk, no ground-truth depth), for long streets")
    p.add_argument("--quick", action="store_true", help="small inputs, for a smoke run (under 3 minutes)")
    p.add_argument("--repeats", type=int_range(1, MAX_REPEATS), default=None,
                   help="timings are the median of this many runs (3; quick 1)")
    p.add_argument("--street-length", type=float_range(1.0, MAX_LENGTH, lo_open=False), default=None,
                   help="metres of the 1× street of the pipeline runs (30; quick 9)")
    p.add_argument("--work", type=Path, default=None,
                   help="a recon work directory (e.g. of the default street): the billboard build, texture and "
                        "rendering sections use its cloud and images instead of the 1× street's")
    p.set_defaults(func=_run_bench)


def _run_bench(args) -> int:
    from .bench import BenchConfig, run_bench

    given = {"scene": args.scene, "work": None if args.work is None else str(args.work)}
    if args.repeats is not None:
        given["repeats"] = args.repeats
    if args.street_length is not None:
        given["street_length"] = args.street_length
    if args.city_scales is not None:
        given["city_scales"] = tuple(args.city_scales)
    if args.gpu_budget is not None:
        given["city_gpu_budget_mb"] = args.gpu_budget
    if args.lazy:
        given["city_lazy"] = True
    run_bench(BenchConfig.quick_config(**given) if args.quick else BenchConfig(**given), args.out)
    return 0


def _add_fps(sub) -> None:
    from render.culling import CULL_MODES

    p = sub.add_parser(
        "fps", help="frame rates of GPU vs CPU texture decode, with level of detail, overdraw and culling, on a "
                    "model (views and its capture path) or the town",
        description="Render MODEL offscreen (frustum culling unless --cull-mode) from capture-like viewpoints "
                    "of a street along +x (2 m up, facing either facade and along the street; the eye stepping "
                    "5 cm sideways every frame) and along the capture path of its dataset, timing every frame "
                    "(draw and read-back): per row the median "
                    "and 5th-percentile frame rate (from the median and 95th-percentile frame time), quads and "
                    "billboards drawn, tiles decoded, quads per level of detail (full/reduced/mean) and, per "
                    "view, fragments per pixel (overdraw); GPU decode with level of detail (--exact: every eigen "
                    "image) against CPU decode, the baseline, with their ratio measured in the same run; with "
                    "--cull also each culling mode's frame rate and drawn billboards (GPU decode); with --town "
                    "the culling modes on the town scene's meshes along its capture path. A tiled model "
                    "(tiles.json), or any model with --gpu-budget, is walked along its drive path paging its "
                    "tiles: the first frame's time, the frame times while paging, the GPU MB peak against the "
                    "budget, tiles uploaded and released.",
        parents=[_size_parent((1280, 720), RENDER_BYTES_PER_PIXEL, "default 1280 720"), _gpu_budget_parent()])
    p.add_argument("model", type=Path, nargs="?", default=None,
                   help="billboard model directory, plain or tiled (optional with --town)")
    p.add_argument("--gpu-frames", type=int_range(1, MAX_FRAMES), default=10, metavar="N",
                   help="timed frames per view with GPU decode, and per culling mode (default 10)")
    p.add_argument("--cpu-frames", type=int_range(1, MAX_FRAMES), default=3, metavar="N",
                   help="timed frames per view, and along the capture path, with CPU decode (default 3)")
    p.add_argument("--exact", action="store_true",
                   help="GPU decode without level of detail (every eigen image everywhere)")
    p.add_argument("--dataset", type=Path, default=None, metavar="DIR",
                   help="dataset whose camera-0 poses are the capture path (default: the model's, when its "
                        "manifest records one that is still there)")
    p.add_argument("--path-step", type=zero_or_at_least(MIN_STEP), default=0.25, metavar="M",
                   help="the capture path walked with the eye at most M metres per frame, rotations "
                        f"interpolated (default 0.25, at least {MIN_STEP:g}; 0: the capture frames as they are)")
    p.add_argument("--path-frames", type=int_range(0, MAX_FRAMES), default=240, metavar="N",
                   help="timed GPU frames along the capture path: N consecutive poses centred a quarter of "
                        "the way along (the middle of a there-and-back drive's outbound pass); 0: all (default 240)")
    p.add_argument("--cull-mode", choices=CULL_MODES, default="frustum",
                   help="culling of the decode rows and the capture path (default frustum, as render and view "
                        "draw; none: every billboard decoded and drawn)")
    p.add_argument("--cull", action="store_true", help="also compare the culling modes (GPU decode)")
    add_fps_web_options(p)
    p.add_argument("--town", action="store_true",
                   help="culling on the town scene's meshes along its capture path (default TownConfig)")
    p.add_argument("--walk-step", type=float_range(MIN_STEP, lo_open=False), default=1.0, metavar="M",
                   help=f"paging walk: metres the eye moves per frame along the drive path (default 1, at least "
                        f"{MIN_STEP:g})")
    p.add_argument("--walk-frames", type=int_range(0, MAX_FRAMES), default=0, metavar="N",
                   help="paging walk: frames (default 0: the whole drive path once)")
    p.set_defaults(func=_run_fps, check_options=_check_fps)


def _check_fps(args) -> None:
    if args.model is None and not args.town:
        raise UsageError("give a model directory, --town, or both")


def _run_fps(args) -> int:
    from billboards.model_reader import load
    from billboards.model_set import ModelSet
    from render.benchmark import town_cull_fps
    from render.paths import town_views
    from render.context import create_context, describe

    check_fps_web(args)  # a site of another model would time and compare nothing useful
    drawable = None if args.model is None else _load_drawable(args.model, args.gpu_budget is not None)
    tiled = isinstance(drawable, ModelSet) and drawable.tiled  # a bad model fails before any GL work
    model = (None if drawable is None or tiled else
             drawable if not isinstance(drawable, ModelSet) else load(args.model))
    size = tuple(args.size)
    ctx = create_context()
    try:
        print(describe(ctx))
        if args.town:
            from data_synth import TownConfig, build_town
            from data_synth.dataset import SynthConfig, capture_path

            scene = build_town(TownConfig())
            poses, _ = capture_path(SynthConfig(scene="town", frames=300))
            rows = town_cull_fps(ctx, scene, town_views(poses[100:160]), size, group_cells=(30.0, 60.0))
            frustum = {r["group_cell"]: r for r in rows if r["cull"] == "frustum"}
            for r in rows:
                f = frustum.get(r["group_cell"])
                ratios = (f", fps this/frustum {r['fps'] / f['fps']:.2f}×, drawn frustum/this "
                          f"{f['drawn'] / max(r['drawn'], 1e-9):.1f}×" if f else "")
                print(f"town cull {r['cull']:>9} (groups of {r['group_cell']} m): {r['fps']:6.2f} fps "
                      f"(median; {r['fps_p5']:.2f} at the 95th-percentile frame time), "
                      f"{r['after_frustum']:.0f} of {r['objects']} objects after frustum, {r['drawn']:.0f} drawn, "
                      f"{r['queries']:.0f} queries, {r['depth_reads']:.0f} depth reads{ratios}")
        if model is not None:
            _print_model_fps(ctx, model, args, size)
        if isinstance(drawable, ModelSet):
            _print_paging_walk(ctx, drawable, args, size)
        return 0
    finally:
        ctx.release()


def _print_paging_walk(ctx, model_set, args, size) -> None:
    """The paging part of ``bbcity fps``: the set walked along its drive path under the budget
    (and, for comparison, without one)."""
    import numpy as np

    from render.benchmark import paging_walk
    from render.lod import LodConfig
    from render.paging import PagingConfig
    from render.paths import drive_path_for
    from render.tiled_renderer import path_model

    path = drive_path_for(path_model(model_set))
    along = np.arange(0.0, path.length, args.walk_step)
    if args.walk_frames:
        along = along[:args.walk_frames]
    poses = np.stack([path.pose(s) for s in along])
    lo, hi = model_set.bounds
    print(f"{'tiled' if model_set.tiled else 'plain'} model: {len(model_set)} tiles of {model_set.tile_size:g} m, "
          f"{model_set.num_billboards} billboards, {model_set.bytes / 2**20:.0f} MB on disk, "
          f"{(hi - lo)[0]:.0f} × {(hi - lo)[1]:.0f} m; walk: {len(poses)} frames {args.walk_step:g} m apart "
          f"along the drive path ({along[-1]:.0f} m)")
    lod = None if args.exact else LodConfig()
    budgets = [_paging(args), PagingConfig()] if args.gpu_budget is not None else [PagingConfig()]
    for paging in budgets:
        r = paging_walk(ctx, model_set, poses, size, paging, lod=lod, cull=args.cull_mode)
        budget = "no budget" if r["budget_mb"] is None else f"budget {r['budget_mb']:.0f} MB"
        print(f"paging walk, {budget}: first frame {r['first_ms']:.0f} ms (renderer made in {r['open_ms']:.0f} ms), "
              f"then {r['fps']:.1f} fps median, {r['fps_p5']:.1f} p5 ({r['ms']:.1f} ms, p95 {r['ms_p95']:.1f} ms, "
              f"max {r['ms_max']:.0f} ms); GPU peak {r['peak_mb']:.0f} MB (bounds {r['peak_reserved_mb']:.0f} MB); "
              f"{r['uploads']} uploads, {r['releases']} releases, {r['loads']} loads ({r['load_s']:.1f} s in the "
              f"loader); uploading at most {r['upload_ms_max']:.0f} ms of a frame, frames that upload "
              f"{r['ms_upload_frames']:.0f} ms median; {r['resident']:.1f} tiles resident, {r['drawn']:.1f} drawn on average; "
              f"{r['missing_frames']} of {r['frames']} frames missing a near tile")


def _fps_row(label: str, r: dict) -> str:
    """One line of ``bbcity fps``: a row of render.benchmark's decode_fps / path_fps."""
    line = (f"{label}: {r['fps']:6.1f} fps median, {r['fps_p5']:6.1f} p5 ({r['ms']:.1f} ms, p95 {r['ms_p95']:.1f} ms, "
            f"{r['frames']} frames), {r['instances']:.0f} billboards")
    if r["decode"] == "cpu":
        line += f", CPU decode {r['decode_ms']:.0f} ms" if r["decode_ms"] > 0 else ""  # not reported under culling
    else:
        line += (f" in {r['quads']:.0f} quads, {r['decoded_tiles']:.0f} tiles decoded, LOD "
                 f"{r['lod_full']:.0f}/{r['lod_reduced']:.0f}/{r['lod_mean']:.0f}")
    if r["cull"] != "none":
        line += f", cull {r['cull_ms']:.1f} ms"
    if "layers" in r:
        line += (f", overdraw {r['layers']:.2f} layers / {r['written']:.2f} written per pixel "
                 f"({r['covered']:.0%} covered)")
    return line


def _print_model_fps(ctx, model, args, size) -> None:
    """The model part of ``bbcity fps``: the views, the capture path, the culling modes."""
    import numpy as np

    from render.benchmark import cull_fps, decode_fps, path_fps
    from render.lod import LodConfig
    from render.camera import default_intrinsics
    from render.paths import capture_camera_poses, capture_walk, street_views

    capture = capture_camera_poses(model, args.dataset)  # a bad dataset fails before the timings
    gpu = "gpu exact" if args.exact else "gpu"
    lod = None if args.exact else LodConfig()
    names = {"gpu": "gpu LOD", "gpu exact": "gpu exact", "cpu": "cpu"}
    print(f"{model.num_billboards} billboards, {model.num_slots} slots, {len(model.pages)} atlas pages, "
          f"{size[0]}×{size[1]}, {args.cull_mode} culling; fps median / p5 from the median / 95th-percentile frame "
          "time; LOD: quads at full / reduced / mean detail")
    rows = decode_fps(ctx, model, street_views(), size, {gpu: args.gpu_frames, "cpu": args.cpu_frames},
                      cull=args.cull_mode, overdraw=True)
    for r in rows:
        print(_fps_row(f"{names[r['decode']]:>9} {r['view']:>12}", r))
    for view in dict.fromkeys(r["view"] for r in rows):
        by = {r["decode"]: r for r in rows if r["view"] == view}
        if gpu in by and "cpu" in by:
            print(f"GPU/CPU decode fps ratio, {view}: {by[gpu]['fps'] / by['cpu']['fps']:.1f}× median, "
                  f"{by[gpu]['fps_p5'] / by['cpu']['fps_p5']:.1f}× p5")
    if capture is None:
        print("capture path: the model records no dataset that is still there (give --dataset DIR)"
              + ("; --web walks it too, so it has nothing to time" if args.web is not None else ""))
    else:
        poses = capture_walk(capture, args.path_step, args.path_frames)
        eyes = poses[:, :3, 3]
        length = float(np.sum(np.linalg.norm(np.diff(eyes, axis=0), axis=1)))
        print(f"capture path: {len(poses)} of {len(capture)} camera-0 poses"
              + (f" walked every {args.path_step:g} m" if args.path_step > 0 else "")
              + f", {length:.0f} m from {np.round(eyes[0], 1).tolist()}")
        g = path_fps(ctx, model, poses, size, "gpu", cull=args.cull_mode, lod=lod)
        print(_fps_row(f"{names[gpu]:>9} {'capture path':>12}", g))
        pick = np.unique(np.linspace(0, len(poses) - 1, min(args.cpu_frames, len(poses))).round().astype(int))
        c = path_fps(ctx, model, poses[pick], size, "cpu", cull=args.cull_mode)
        print(_fps_row(f"{'cpu':>9} {'capture path':>12}", c))
        print(f"GPU/CPU decode fps ratio, capture path: {g['fps'] / c['fps']:.1f}× median, "
              f"{g['fps_p5'] / c['fps_p5']:.1f}× p5 (CPU on {len(pick)} poses spread along it)")
        if args.web is not None:
            rows = {names[gpu]: g}
            if not args.exact:  # the web viewer decodes every eigen image, as --exact does
                rows["gpu exact"] = path_fps(ctx, model, poses, size, "gpu", cull=args.cull_mode, lod=None)
                print(_fps_row(f"{'gpu exact':>9} {'capture path':>12}", rows["gpu exact"]))
            print_web_fps(args, model, street_views(), poses, default_intrinsics(*size), size, rows)
    if args.cull:
        for r in cull_fps(ctx, model, street_views(), size, args.gpu_frames, lod=lod):
            print(f"cull {r['cull']:>9} {r['view']:>10}: {r['fps']:6.1f} fps median, {r['fps_p5']:6.1f} p5, "
                  f"{r['after_frustum']} billboards after frustum, {r['drawn']} drawn, {r['queries']} queries, "
                  f"{r['draw_calls']:.0f} draw calls, cull {r['cull_ms']:.1f} ms")


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a billboard model along a camera path into frames or a video",
                       description="Render MODEL offscreen (EGL) along --path: capture (the capture drive), orbit "
                                   "(a circle above the model) or FILE (a dataset directory, or a JSON list of 4×4 "
                                   "world_from_cam matrices) into PNG frames (--out DIR) or a video (--out X.mp4).",
                       parents=[_size_parent((1280, 720), RENDER_BYTES_PER_PIXEL, "default 1280 720"),
                                _draw_modes_parent(), _gpu_budget_parent()])
    p.add_argument("model", type=Path, help="billboard model directory, plain or tiled (tiles.json)")
    p.add_argument("--path", default="capture", help="capture, orbit or a FILE (default capture)")
    p.add_argument("--out", type=Path, required=True, help="frames directory, or a video file (.mp4, .mkv, ...)")
    p.add_argument("--frames", type=int_range(1, MAX_FRAMES), default=300,
                   help="frames along capture/orbit paths (default 300)")
    p.add_argument("--fps", type=float_range(0.0, MAX_FPS), default=30.0, help="video frame rate (default 30)")
    p.set_defaults(func=_run_render)


def _run_render(args) -> int:
    from billboards.sky import read_sky
    from render.fly_through import render_path
    from render.paths import camera_path
    from render.tiled_renderer import path_model

    model = _load_drawable(args.model, args.gpu_budget is not None)
    poses = camera_path(path_model(model), args.path, args.frames)
    render_path(model, poses, args.out, tuple(args.size), decode=args.decode, cull=args.cull, fps=args.fps,
                sky=read_sky(args.model), paging=_paging(args))
    logger.info("wrote %s", args.out)
    return 0


def _eval_dataset(model, dataset_dir: Path):
    """The dataset to evaluate ``model`` on: with the poses the model was built with (its
    info "poses": a recon's WORK/poses.json, e.g. from SfM) instead of the dataset's own."""
    from data_synth import load_dataset

    info = model.info if isinstance(model.info, dict) else {}
    poses = info.get("poses")
    if not isinstance(poses, str):
        ds = load_dataset(dataset_dir)
        if not ds.posed.any():
            raise InputError(f"{dataset_dir}: no frame has a pose, and the model records no poses file (build it "
                             "from the WORK of `bbcity recon --poses sfm`)")
        return dataset_dir
    logger.info("poses: %s (the model's)", poses)
    return load_dataset(dataset_dir, poses=poses)


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="novel-view quality of a model against ground truth or held-out real images",
                       description="Render MODEL at capture viewpoints of DATASET (its held-out frames when built with "
                                   "--holdout). A real capture (no gt/): compare with those frames' images, PSNR and "
                                   "SSIM over the pixels each method covers and the whole image, coverage of the pixels "
                                   "below the horizon. A synthetic dataset: also at the same viewpoints moved 2 m "
                                   "sideways and 1 m up; compare with "
                                   "the ground-truth renderer: PSNR and SSIM over the image, over geometry pixels and "
                                   "over seen pixels (a surface a capture camera used for the textures saw). With "
                                   "--cloud, the fused cloud is the baseline twice: meshed by Open3D's screened "
                                   "Poisson reconstruction (ray cast, vertex colours) and projected point by point. "
                                   "Writes eval.json, eval.md, workprecision.png (bytes against seen-pixel PSNR: "
                                   "Poisson depths, the model(s), the points) and one side-by-side PNG per view.",
                       parents=[_size_parent(None, EVAL_BYTES_PER_PIXEL, "default: the camera's")])
    p.add_argument("model", type=Path, help="billboard model directory (or a tiled model's: every tile a view sees)")
    p.add_argument("dataset", type=Path,
                   help="the dataset: synthetic with gt/, or a real capture (scored against its held-out images)")
    p.add_argument("--out", type=Path, required=True,
                   help="report directory: new, or an earlier eval report (replaced whole)")
    p.add_argument("--cloud", type=Path, default=None, help="fused cloud for the Poisson-mesh and point baselines")
    p.add_argument("--billboards-only", type=Path, default=None, metavar="MODEL",
                   help="a model of the same cloud built with --layer none, scored as 'billboards only'")
    p.add_argument("--models", type=Path, nargs="+", default=[], metavar="MODEL",
                   help="more model directories (other build settings): more points of the work-precision diagram")
    p.add_argument("--views", type=int_range(1, MAX_FRAMES), default=None,
                   help="viewpoints (default: 8, each also off path; a real capture: every held-out frame)")
    p.add_argument("--training-views", type=int_range(0, MAX_FRAMES), default=None,
                   help="also this many viewpoints of frames the textures came from, scored as 'training' (the "
                        "ceiling; default EvalConfig's, 4; only when the model held frames out)")
    p.add_argument("--poisson-depth", type=int_range(1, 16), default=10,
                   help="octree depth of the Poisson-mesh baseline (10)")
    p.add_argument("--workprecision-depths", type=int_range(1, 16), nargs="*", default=[8, 9, 10, 11], metavar="D",
                   help="Poisson depths of the work-precision diagram (default 8 9 10 11; none: only --poisson-depth)")
    p.add_argument("--panel-width", type=int_range(0, MAX_PANEL_WIDTH), default=320,
                   help="width of each panel of the side-by-side images (default 320; 0: no images)")
    p.add_argument("--no-sky", action="store_true",
                   help="draw the model(s) on black like the baselines, not over their sky")
    p.set_defaults(func=_run_eval, check_options=_check_eval)


#: What an eval report directory holds (it is replaced whole by the next report).
_EVAL_REPORT_FILES = re.compile(r"eval\.json|eval\.md|workprecision\.png|view_\d+_(on_path|off_path|training)\.png")


def _check_eval(args) -> None:
    """The eval options, and an --out that is new or an earlier eval report (it is replaced whole)."""
    _eval_config(args)
    check_own_output(args.out, _EVAL_REPORT_FILES, "an eval report's", "the report replaces its directory whole")


#: What each command that writes into a directory of its own may find there from an earlier run
#: of itself (hidden names, its own and its killed runs' temporaries, are always its own).
_OWN_OUTPUT = {
    "render": (re.compile(r"frame_\d{6}\.png"), "a render's frames", "its frames replace those there"),
    "recon": (re.compile(r"cloud\.ply|cloud_tiles\.json|poses\.json|recon_report\.json|sfm|spill"),
              "a recon work directory's", "a recon writes its cloud there and resumes what it finds"),
    "texture-sweep": (re.compile(r"texture_sweep\.(json|md|png)"), "a texture sweep's",
                      "its report files replace those there"),
}


def check_own_output(out: Path, own: re.Pattern, what: str, why: str) -> None:
    """UsageError unless ``out`` is new or holds only names ``own`` matches (and hidden ones):
    a command's output mixed into a model, a dataset or anything else would damage both."""
    try:
        if out.is_symlink() or (out.exists() and not out.is_dir()):
            raise UsageError(f"--out {out} is not a directory (a link or a file); give a new directory")
        names = [p.name for p in out.iterdir()] if out.is_dir() else []
    except OSError as e:  # a name too long, a directory not readable
        raise UsageError(f"--out {out}: {e.strerror}") from None
    foreign = sorted(name for name in names if not name.startswith(".") and not own.fullmatch(name))
    if foreign:
        raise UsageError(f"--out {out} holds {foreign[0]!r}, not {what}; {why}: give a new directory")


def _eval_config(args):
    from render.evaluate import EvalConfig

    return EvalConfig(views=args.views, size=None if args.size is None else tuple(args.size),
                      poisson_depth=args.poisson_depth, workprecision_depths=tuple(args.workprecision_depths),
                      panel_width=args.panel_width, model_sky=not args.no_sky,
                      **({} if args.training_views is None else {"training_views": args.training_views}))


def _run_eval(args) -> int:
    from billboards.sky import read_sky
    from render.eval_report import write_report
    from render.evaluate import evaluate_views

    from core.fileio import atomic_dir

    config = _eval_config(args)
    labels = [m.name if [x.name for x in args.models].count(m.name) == 1 else str(m) for m in args.models]
    extra = {label: (_load_drawable(m, False), read_sky(m)) for label, m in zip(labels, args.models)}
    only = None if args.billboards_only is None else (_load_drawable(args.billboards_only, False),
                                                      read_sky(args.billboards_only))
    model = _load_drawable(args.model, False)
    with atomic_dir(args.out) as report_dir:  # a failed or interrupted run leaves no partial report
        report = evaluate_views(model, _eval_dataset(model, args.dataset), args.cloud, sky=read_sky(args.model),
                                extra_models=extra, billboards_only=only, config=config, out_dir=report_dir)
        write_report(report, report_dir)
    for name, m in report["summary"].items():
        if report.get("real"):
            logger.info("%s: PSNR %s dB over covered pixels (%s over the image), SSIM %s, %s of the pixels below "
                        "the horizon covered", name, _num(m["psnr_covered"]), _num(m["psnr"]),
                        _num(m["ssim_covered"], ".3f"), _num(m["coverage_seen"], ".1%"))
        else:
            logger.info("%s: PSNR %s dB over seen pixels (%s over the image), SSIM %s", name, _num(m["psnr_seen"]),
                        _num(m["psnr"]), _num(m["ssim_seen"], ".3f"))
    logger.info("wrote %s", args.out / "eval.md")
    return 0


def _num(value, spec: str = ".2f") -> str:
    return "n/a" if value is None else format(value, spec)


def _add_view(sub) -> None:
    try:
        from render.viewer import KEYS_HELP, WINDOWS
    except ImportError:  # the viewer's GL dependencies are missing; the command still parses
        KEYS_HELP, WINDOWS = None, None

    p = sub.add_parser(
        "view", help="open a billboard model in an interactive window (fly, drive, toggles, screenshots)",
        description="Open a billboard model in a moderngl-window window: mouse look and WASD/QE fly, a drive "
                    "mode along the capture path, GPU/CPU decode, level-of-detail, culling and view-interpolation "
                    "toggles; a HUD and the title bar show frame time and fps, draw and cull time, quads and "
                    "billboards drawn, quads per level of detail, tiles decoded, decode and cull mode. With "
                    "--script-frames it renders that many "
                    "frames along the drive path, saves a screenshot and exits (runs under xvfb-run).",
        epilog=KEYS_HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[_size_parent((1280, 720), RENDER_BYTES_PER_PIXEL, "window size (default 1280 720)"),
                 _draw_modes_parent(), _gpu_budget_parent()])
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
    p.set_defaults(func=_run_view, check_options=_check_view)


def _check_view(args) -> None:
    from render.viewer import KEY_NAMES

    if args.window == "headless" and args.script_frames == 0:
        raise UsageError("--window headless takes no input and never closes: give --script-frames N")
    keys = [k.strip().upper() for k in args.script_keys.split(",") if k.strip()]
    unknown = [k for k in keys if k not in KEY_NAMES]
    if unknown:
        raise UsageError(f"--script-keys: unknown key {unknown[0]!r}; the viewer answers {', '.join(KEY_NAMES)}")
    if "ESCAPE" in keys:
        raise UsageError("--script-keys: ESCAPE closes the viewer before its screenshot; leave it out")


def _run_view(args) -> int:
    from billboards.model_set import ModelSet
    from billboards.sky import read_sky
    from render.paging import PagingConfig
    from render.viewer import run_viewer

    model = _load_drawable(args.model, args.gpu_budget is not None)
    paging = _paging(args) or (PagingConfig() if isinstance(model, ModelSet) else None)
    out = run_viewer(model, size=tuple(args.size), decode=args.decode, cull=args.cull, window=args.window,
                     screenshot_dir=args.screenshot_dir, script_frames=args.script_frames,
                     screenshot=args.screenshot, mode=args.mode,
                     script_keys=[k for k in args.script_keys.split(",") if k.strip()], sky=read_sky(args.model),
                     lod=not args.exact, paging=paging)
    if out is not None:
        logger.info("screenshot %s", out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bbcity", description="Street captures from a camera rig to a compact billboard city model.")
    parser.add_argument("--version", action="version", version=f"bbcity {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=CommandParser)
    _add_synth(sub)
    _add_import(sub)
    _add_export(sub)
    _add_recon(sub)
    _add_build(sub)
    _add_texture_sweep(sub)
    _add_sampling_eval(sub)
    _add_stereo_sweep(sub)
    _add_check(sub)
    _add_bench(sub)
    _add_fps(sub)
    _add_view(sub)
    _add_render(sub)
    _add_eval(sub)
    add_serve(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    # Ctrl-C may land while a library is being imported (parsing already imports the viewer's),
    # where it can surface as another error (an ImportError): one line and 130 all the same
    interrupted = threading.Event()

    def on_interrupt(signum, frame):
        interrupted.set()
        raise KeyboardInterrupt

    # signals reach the main thread only; an ignored SIGINT (a background job of a shell script) stays ignored
    ours = threading.current_thread() is threading.main_thread() and \
        signal.getsignal(signal.SIGINT) is signal.default_int_handler
    previous = signal.signal(signal.SIGINT, on_interrupt) if ours else None
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")  # before parsing, so that even an early error is a log line
    try:
        return _main(argv)
    except BaseException:
        if not interrupted.is_set():
            raise
        logger.error("interrupted")
        return 130
    finally:
        if ours and previous is not None:
            signal.signal(signal.SIGINT, previous)


def _main(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    logging.getLogger().setLevel(logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO)
    from core.workdir import owned_output

    from .executor import tune_allocator

    tune_allocator()
    # SIGTERM unwinds like Ctrl-C: atomic writers clean up and pool workers are killed
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    try:
        if hasattr(args, "executor") and _executor_options(args)["kind"] == "dask":  # a contradiction: one line
            _absolute_paths(args)
        # every writing command names its output --out: one live run at a time writes it
        out = getattr(args, "out", None)
        if out is not None and not getattr(args, "writes_file", False):
            _check_output(args.command, out)
            if args.command in _OWN_OUTPUT and not _is_video(args.command, out):
                check_own_output(out, *_OWN_OUTPUT[args.command])
        with owned_output(out) if out is not None else contextlib.nullcontext():
            return args.func(args)
    # one line for the user; -v adds the traceback
    except InputError as e:  # DataFormatError and UsageError included
        logger.error("%s", e, exc_info=args.verbose)
        return 2
    except OSError as e:  # a file-system error: read-only, full, a name too long, a file where a directory goes
        logger.error("%s", os_error_line(e, getattr(args, "out", None)), exc_info=args.verbose)
        return 2
    except KeyboardInterrupt:
        logger.error("interrupted")
        return 130
    except Exception as e:
        if not worker_died(e):
            # not bad input: a bug in bbcity or a library; -v shows where
            logger.error("internal error, please report: %s: %s", type(e).__name__, e, exc_info=args.verbose)
            return 1
        logger.error("a worker process died (killed, or out of memory: try fewer --workers); what finished is kept, "
                     "and running the command again resumes (%s)", type(e).__name__, exc_info=args.verbose)
        return 1


def worker_died(error: BaseException) -> bool:
    """Whether ``error`` says a worker process died under a task: the local pool's
    BrokenProcessPool, Dask's KilledWorker (named, not imported: Dask loads only with --executor dask)."""
    from concurrent.futures.process import BrokenProcessPool

    return isinstance(error, BrokenProcessPool) or type(error).__name__ == "KilledWorker"


def _is_video(command: str, out: Path) -> bool:
    """Whether ``out`` is a video file ``render`` writes (rather than a folder of frames)."""
    from render.fly_through import VIDEO_SUFFIXES

    return command == "render" and out.suffix.lower() in VIDEO_SUFFIXES


def _check_output(command: str, out: Path) -> None:
    """Refuse a file where a command writes a directory (all but ``render`` of a video) before any work."""
    if _is_video(command, out):
        return
    if (out.exists() or out.is_symlink()) and not out.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a directory; not writing over it", str(out))


def os_error_line(error: OSError, out: Path | None = None) -> str:
    """One line naming the path(s) and the problem of a file-system error; one that names no
    file (a write through a file object) names the command's output ``out``."""
    if error.strerror is None:
        return str(error)
    paths = [str(p) for p in (error.filename, error.filename2) if p is not None]
    if paths:
        return f"{' → '.join(paths)}: {error.strerror}"
    return f"{out}: {error.strerror} (while writing it)" if out is not None else error.strerror


def entry_point() -> None:
    """The ``bbcity`` command: :func:`main`, then exit. After Ctrl-C the exit skips the libraries'
    exit handlers: one interrupted while it was being imported (Open3D) can fail in them."""
    code = main()
    if code == 130:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry_point()
