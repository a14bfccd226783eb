"""``bbcity import KIND``: a capture of one's own (KITTI sequence, COLMAP model, photos, video,
nerfstudio) → a dataset directory that recon, build and eval read like a synthetic one."""

from __future__ import annotations

from pathlib import Path

from ..options import nonnegative_float, nonnegative_int, positive_float, positive_int
from .common import io_parser, logger

#: What an import writes at --out.
NEW_DATASET = "new dataset directory"


def add(sub) -> None:
    """The ``import`` command and its kinds on the subcommands ``sub``."""
    p = sub.add_parser(
        "import", help="a capture of your own (KITTI sequence, COLMAP model, photos, video, nerfstudio) → a dataset",
        description="""Turn a capture into a dataset directory (rig.json, poses.json, images/) that recon, build and
                       eval read like a synthetic one. The new directory is written whole or not at all.""")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    _add_kitti(kinds)
    _add_colmap(kinds)
    _add_photos(kinds)
    _add_video(kinds)
    _add_nerfstudio(kinds)


def _imported(out: Path, posed: bool = True) -> int:
    """Log the dataset an import wrote (one without poses: how to find them); exit code 0."""
    if posed:
        logger.info("wrote %s", out)
    else:
        logger.info("wrote %s; its poses are unknown: bbcity recon %s --poses sfm", out, out)
    return 0


def _add_kitti(kinds) -> None:
    from recon.importers.kitti import KittiConfig

    k = io_parser(kinds, "kitti", "sequence", "sequence directory", NEW_DATASET,
                  help="a KITTI odometry sequence (calib.txt, poses.txt, a stereo pair of image folders)",
                  description="""Import a KITTI odometry sequence: calib.txt (P0..P3), poses.txt (world_from_cam0 per
                                 frame) and image_0/1 (grey), image_2/3 (colour) or image_l/r.""")
    k.add_argument("--cameras", choices=("auto", "grey", "colour", "lr"), default=KittiConfig.cameras,
                   help=f"which stereo pair (default {KittiConfig.cameras}: colour, else grey, else image_l/r)")
    k.add_argument("--camera-height", type=nonnegative_float, default=KittiConfig.camera_height,
                   help="height of KITTI's cam0 (the left grey camera, whose poses poses.txt holds) above the road "
                        f"in metres (default {KittiConfig.camera_height:g}, KITTI's car)")
    k.add_argument("--first", type=nonnegative_int, default=KittiConfig.first,
                   help=f"first frame (default {KittiConfig.first})")
    k.add_argument("--count", type=positive_int, default=KittiConfig.count, help="frames to import (default: all)")
    k.add_argument("--step", type=positive_int, default=KittiConfig.step,
                   help=f"every n-th frame (default {KittiConfig.step})")
    k.set_defaults(func=_run_kitti, check_options=_kitti_config)


def _kitti_config(args):
    from recon.importers.kitti import KittiConfig

    return KittiConfig(cameras=args.cameras, camera_height=args.camera_height, first=args.first, count=args.count,
                       step=args.step)


def _run_kitti(args) -> int:
    from recon.importers.kitti import import_kitti

    return _imported(import_kitti(args.sequence, args.out, _kitti_config(args)))


def _add_colmap(kinds) -> None:
    c = kinds.add_parser("colmap", help="a COLMAP sparse model (text or binary) and its image folder",
                         description="""Import a COLMAP model: its cameras (pinhole, radtan and fisheye models kept,
                                        other lenses undistorted here), a rig of several cameras or one camera, and
                                        the registered poses, turned so that z points up (cameras held roughly level).
                                        The model's scale is kept.""")
    c.add_argument("model", type=Path, help="COLMAP model directory (cameras, images[, rigs, frames] .txt or .bin)")
    c.add_argument("--images", type=Path, required=True, help="folder that the model's image names are relative to")
    c.add_argument("--out", type=Path, required=True, help=NEW_DATASET)
    c.add_argument("--metric", action="store_true", help="the model is in metres (recorded in dataset.json)")
    c.set_defaults(func=_run_colmap)


def _run_colmap(args) -> int:
    from recon.importers.colmap import ColmapImportConfig, import_colmap

    return _imported(import_colmap(args.model, args.images, args.out, ColmapImportConfig(metric=args.metric)))


#: The format of an ``--intrinsics`` file.
K_FILE = ('3 lines of a 3×3 matrix or one line "fx fy cx cy" (OpenCV pixel centres), optionally followed by '
          '"k1 k2 p1 p2 [k3]"')


def _unposed(p, step_help: str, run, config) -> None:
    """The end of the parser of a kind whose poses are unknown (photos, video): ``--step-length``,
    the scale SfM takes, and the kind's run and config."""
    p.add_argument("--step-length", type=positive_float, default=None, help=step_help)
    p.set_defaults(func=run, check_options=config)


def _add_photos(kinds) -> None:
    f = io_parser(kinds, "photos", "folder", "folder of photos", NEW_DATASET,
                  help="a folder of one camera's photos (poses unknown: recon --poses sfm)",
                  description="""Import a folder of JPEG/PNG photos of one camera, all the same size, in file-name
                                 order, stored upright (EXIF orientation). Intrinsics from --intrinsics (of the
                                 upright image) or the photos' EXIF focal length. The poses are unknown: reconstruct
                                 with `bbcity recon DATASET --poses sfm`, which scales the result to --step-length
                                 metres between consecutive photos, else to the photos' EXIF GPS positions.""")
    f.add_argument("--intrinsics", type=Path, default=None, help=f"K file: {K_FILE} (default: EXIF)")
    f.add_argument("--sensor-width", type=positive_float, default=None,
                   help="sensor width in mm, with EXIF FocalLength when the photos lack a 35 mm equivalent")
    _unposed(f, "metres between consecutive photos, SfM's scale (default: none; SfM then takes it from the photos' "
                "EXIF GPS positions when every photo has one, else its units are arbitrary)",
             _run_photos, _photos_config)


def _photos_config(args):
    from recon.importers.photos import PhotosConfig

    return PhotosConfig(intrinsics=args.intrinsics, sensor_width_mm=args.sensor_width, step_length=args.step_length)


def _run_photos(args) -> int:
    from recon.importers.photos import import_photos

    return _imported(import_photos(args.folder, args.out, _photos_config(args)), posed=False)


def _add_video(kinds) -> None:
    from recon.importers.video_config import DEFAULT_FPS, VideoConfig  # light: no OpenCV, no Open3D

    v = io_parser(kinds, "video", "video", "video file", NEW_DATASET,
                  help="a video of one camera (frames sampled, blurred ones dropped; poses unknown: recon --poses sfm)",
                  description=f"""Import a video of one camera (any format ffmpeg reads): frames sampled at --fps
                               per second (default {DEFAULT_FPS:g}) or --frames spread over the video, the sharpest
                               of each {VideoConfig.sharpest_of} consecutive frames kept and blurred ones dropped
                               (variance of the Laplacian), named frame_NNNNNN by their index in the video.
                               Intrinsics from --intrinsics (a video has no EXIF). The poses are unknown:
                               reconstruct with `bbcity recon DATASET --poses sfm`.""")
    v.add_argument("--intrinsics", type=Path, default=None, help=f"K file of the upright frames (required): {K_FILE}")
    rate = v.add_mutually_exclusive_group()
    rate.add_argument("--fps", type=positive_float, default=None,
                      help=f"frames kept per second of video (default {DEFAULT_FPS:g})")
    rate.add_argument("--frames", type=positive_int, default=None,
                      help="instead of --fps: this many frames spread evenly over the whole video")
    _unposed(v, "metres between consecutive kept frames (walking speed ÷ --fps), SfM's scale (default: none, "
                "arbitrary units)", _run_video, _video_config)


def _video_config(args):
    from recon.importers.video_config import VideoConfig

    given = {"intrinsics": args.intrinsics, "fps": args.fps, "frames": args.frames, "step_length": args.step_length}
    return VideoConfig(**{k: v for k, v in given.items() if v is not None})


def _run_video(args) -> int:
    from recon.importers.video import import_video

    return _imported(import_video(args.video, args.out, _video_config(args)), posed=False)


def _add_nerfstudio(kinds) -> None:
    from recon.importers.nerfstudio import NerfstudioImportConfig

    n = io_parser(kinds, "nerfstudio", "transforms", "transforms.json, or the folder holding it", NEW_DATASET,
                  help="a nerfstudio transforms.json (one camera, given poses) and its images",
                  description="""Import a nerfstudio dataset: transforms.json (intrinsics fl_x fl_y cx cy w h,
                                 camera_model PINHOLE/OPENCV/OPENCV_FISHEYE with k1..k4 p1 p2, frames of file_path and
                                 camera-to-world transform_matrix in OpenGL axes) and the images it names. Every frame
                                 must share one camera. A z-up world (nerfstudio's convention) is kept as it is; its
                                 scale is kept.""")
    n.add_argument("--metric", action="store_true", help="the poses are in metres (recorded in dataset.json)")
    n.add_argument("--world", choices=("auto", "keep", "level"), default=NerfstudioImportConfig.world,
                   help=f"{NerfstudioImportConfig.world} (default): keep the world when the cameras' up is near +z "
                        "(nerfstudio's convention), else turn it z-up; keep: never turn it; level: always turn it "
                        "(origin at the first camera)")
    n.set_defaults(func=_run_nerfstudio, check_options=_nerfstudio_config)


def _nerfstudio_config(args):
    from recon.importers.nerfstudio import NerfstudioImportConfig

    return NerfstudioImportConfig(metric=args.metric, world=args.world)


def _run_nerfstudio(args) -> int:
    from recon.importers.nerfstudio import import_nerfstudio

    return _imported(import_nerfstudio(args.transforms, args.out, _nerfstudio_config(args)))
