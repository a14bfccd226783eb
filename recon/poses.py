"""Pose sources for the rig and their evaluation.

Three sources, all returning ``world_from_rig`` (n, 4, 4) float64 in the
order of ``dataset.frame_names`` (rig frame: x forward, y left, z up; see
``data_synth.rig``), with NaN matrices for frames that have no pose:

* :func:`poses_given` — the dataset's ``poses.json`` (GPS/IMU in a real capture).
* :func:`poses_from_colmap` — a COLMAP model the user already has (text or
  binary; with rigs and frames, COLMAP ≥ 3.12, or one image per camera).
* :func:`poses_sfm` — structure from motion with pycolmap on the CPU: SIFT,
  sequential matching across the rig, the rig as a *known* rig (calibrated
  intrinsics and ``sensor_from_rig`` kept fixed), a global-SfM seed grown by
  incremental mapping, so the reconstruction comes out in metres. Its world frame is
  arbitrary, one per connected component (a street's two passes see opposite
  sides and share nothing).

Evaluation: :func:`align_trajectory` (Umeyama, SE(3) or Sim(3)),
:func:`trajectory_rmse` (position and rotation errors after alignment) and
:func:`align_components` (each SfM component placed on reference poses,
e.g. GPS).

COLMAP conventions bridged here (see ``data_synth/colmap_export.py``): COLMAP
cameras use OpenCV's axes but put the top-left pixel centre at (0.5, 0.5), so
``cx_colmap = cx + 0.5``; a COLMAP rig frame *is* its reference sensor's
camera frame, so ``world_from_rig = inv(rig_from_world) @ cam_from_rig[ref]``
with our calibrated ``cam_from_rig`` of the reference camera.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Iterator

import numpy as np
from tqdm import tqdm

# data_synth loads open3d and OpenCV, which must be loaded before pycolmap: with
# pycolmap first, OpenCV's PNG writer crashes (their bundled libpng builds clash).
from data_synth import DataFormatError, Dataset
from data_synth.colmap_export import colmap_camera_model, to_rigid3d
from data_synth.rigid import rigid_inverse
from data_synth.fileio import read_json

import pycolmap  # noqa: E402  (after data_synth, see above)

logger = logging.getLogger(__name__)

__all__ = [
    "MissingFramesError", "SfmConfig", "SfmResult", "align_components", "align_trajectory",
    "colmap_log_to_logging", "frame_passes", "poses_from_colmap", "poses_from_reconstruction", "poses_given",
    "poses_sfm", "poses_unknown", "rig_baseline_ratio", "trajectory_rmse", "level_from_world", "up_direction",
]

COLMAP_PIXEL_OFFSET = 0.5  # cx_colmap = cx_opencv + 0.5 (and the same for cy)
COLLINEAR_RATIO = 1e-4  # align_trajectory: positions are one line when singular values 2nd/1st fall below this


class MissingFramesError(DataFormatError):
    """A pose source has no pose for some frames; ``missing`` lists their names."""

    def __init__(self, path: os.PathLike | str, missing: list[str], total: int, hint: str = ""):
        self.missing = list(missing)
        shown = ", ".join(missing[:20]) + (f", … ({len(missing) - 20} more)" if len(missing) > 20 else "")
        super().__init__(path, f"{len(missing)} of {total} frames have no pose: {shown}{hint}")


# --------------------------------------------------------------------------- small helpers


def _nan_poses(n: int) -> np.ndarray:
    return np.full((n, 4, 4), np.nan)


def _to_4x4(rigid: pycolmap.Rigid3d) -> np.ndarray:
    """pycolmap.Rigid3d → (4, 4) float64."""
    T = np.eye(4)
    T[:3, :4] = rigid.matrix()
    return T


def _valid(T: np.ndarray) -> np.ndarray:
    """(n,) bool: which poses of T (n, 4, 4) are fully finite."""
    return np.isfinite(T).all(axis=(1, 2))


#: up_direction: the trajectory's main direction counts as level (its component along the
#: estimated up is removed) when it lies within this many degrees of horizontal.
LEVEL_TRAVEL_DEG = 30.0


def up_direction(world_from_cam: np.ndarray, positions: np.ndarray | None = None) -> np.ndarray:
    """(3,) float64 unit vector: the world's up, estimated from cameras held roughly level.

    world_from_cam: (m, 4, 4) float64 camera poses (OpenCV axes; NaN poses are ignored).
    positions: optional (k, 3) float64 rig positions along the capture.
    Up is minus the mean of the cameras' image-down (y) axes. A camera pitched up or down
    tilts that estimate about its own x axis; when the positions run along one main
    direction within LEVEL_TRAVEL_DEG of that horizontal (a street is nearly level), the
    estimate is made perpendicular to it, which removes the pitch of forward-looking
    cameras (sideways-looking ones pitch about the travel direction and cannot be corrected).
    """
    T = np.asarray(world_from_cam, dtype=np.float64)
    T = T[_valid(T)]
    if len(T) == 0:
        raise ValueError("no camera pose to estimate the up direction from")
    up = -T[:, :3, 1].mean(axis=0)
    if np.linalg.norm(up) < 1e-6:
        raise ValueError("the cameras' down axes cancel out: no up direction")
    up /= np.linalg.norm(up)
    if positions is not None:
        P = np.asarray(positions, dtype=np.float64)
        P = P[np.isfinite(P).all(axis=1)]
        if len(P) >= 2:
            _, sv, Vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
            d = Vt[0]
            if sv[0] > 1e-9 and abs(d @ up) < np.sin(np.radians(LEVEL_TRAVEL_DEG)):
                up = up - (d @ up) * d
                up /= np.linalg.norm(up)
    return up


def level_from_world(up: np.ndarray, heading: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4, 4) float64 rigid transform to a z-up world: ``up`` (3,) becomes +z, the horizontal
    part of ``heading`` (3,) becomes +x (any horizontal direction when it is vertical) and
    ``origin`` (3,) the origin. All in the old world's coordinates."""
    z = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    x = np.asarray(heading, dtype=np.float64) - (np.asarray(heading) @ z) * z
    if np.linalg.norm(x) < 1e-6:  # heading straight up or down: any horizontal axis will do
        x = np.eye(3)[np.argmin(np.abs(z))]
        x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: the new axes in old coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.asarray(origin, dtype=np.float64)
    return T


def poses_unknown(dataset: Dataset) -> bool:
    """Whether no frame of the dataset has a pose (``poses.json`` of a photo folder)."""
    return not _valid(dataset.world_from_rig).any()


# --------------------------------------------------------------------------- 1. given poses


def poses_given(dataset: Dataset) -> np.ndarray:
    """The dataset's own poses (``poses.json``; GPS/IMU in a real capture).

    Returns world_from_rig (n, 4, 4) float64, a copy, in ``dataset.frame_names`` order.
    A dataset with no known pose (a photo folder) raises DataFormatError.
    """
    if poses_unknown(dataset):
        raise DataFormatError(dataset.root / "poses.json", "poses unknown: use --poses sfm")
    return np.array(dataset.world_from_rig, dtype=np.float64, copy=True)


# --------------------------------------------------------------------------- 2. COLMAP import

_CAM_DIR = re.compile(r"^cam(\d+)$")


def _image_index(name: str, frame_index: dict[str, int], num_cameras: int) -> tuple[int, int] | None:
    """(frame, camera) of a COLMAP image name, or None when it is not one of the dataset's images.

    Accepted: ``cam{c}/{frame}.{ext}``, the same under extra leading folders
    (``images/cam1/000003.png``), and a bare ``{frame}.{ext}`` when the rig has
    a single camera (the only unambiguous case).
    """
    parts = PurePosixPath(name.replace("\\", "/")).parts
    if not parts:
        return None
    f = frame_index.get(PurePosixPath(parts[-1]).stem)
    if f is None:
        return None
    if len(parts) >= 2:
        m = _CAM_DIR.match(parts[-2])
        if m and int(m.group(1)) < num_cameras:
            return f, int(m.group(1))
        return None
    return (f, 0) if num_cameras == 1 else None


def rig_baseline_ratio(world_from_cam: np.ndarray, cam_from_rig: np.ndarray) -> float:
    """Median over frames of (reconstructed / calibrated) distance between camera centres.

    world_from_cam: (n, c, 4, 4) float64 per frame and camera, NaN where unknown.
    cam_from_rig: (c, 4, 4) float64 calibration.
    Uses every frame with at least two cameras and every camera pair whose
    calibrated distance exceeds 1 mm. Returns NaN when no frame qualifies.
    A metric reconstruction gives 1.
    """
    centres = world_from_cam[:, :, :3, 3]  # (n, c, 3)
    calib = rigid_inverse(cam_from_rig)[:, :3, 3]  # (c, 3) camera centres in the rig
    c = cam_from_rig.shape[0]
    ratios = []
    for i in range(c):
        for j in range(i + 1, c):
            d_cal = np.linalg.norm(calib[i] - calib[j])
            if d_cal < 1e-3:
                continue
            d = np.linalg.norm(centres[:, i] - centres[:, j], axis=1)
            ratios.append(d[np.isfinite(d)] / d_cal)
    ratios = np.concatenate(ratios) if ratios else np.empty(0)
    return float(np.median(ratios)) if ratios.size else float("nan")


def poses_from_reconstruction(rec: pycolmap.Reconstruction, dataset: Dataset,
                              source: os.PathLike | str = "<reconstruction>") -> tuple[np.ndarray, np.ndarray]:
    """Rig poses from a pycolmap.Reconstruction, matched to the dataset's frames by image name.

    For each dataset frame, the pose comes from its registered image of the
    model rig's reference sensor when there is one (``world_from_rig =
    inv(rig_from_world) @ cam_from_rig[ref]``), otherwise from the registered
    image with the lowest camera index (``inv(cam_from_world) @
    cam_from_rig[c]``). Both reduce to the same matrix when the model's rig
    calibration equals the dataset's. Images whose names match no dataset
    image are ignored (logged).

    Returns world_from_rig (n, 4, 4) float64, NaN for frames without a
    registered image, and world_from_cam (n, c, 4, 4) float64, NaN where that
    camera's image is not registered.
    """
    n, c = dataset.num_frames, dataset.rig.num_cameras
    frame_index = {name: i for i, name in enumerate(dataset.frame_names)}
    cam_from_rig = dataset.rig.cam_from_rig
    world_from_cam = np.full((n, c, 4, 4), np.nan)
    is_ref = np.zeros((n, c), dtype=bool)
    ignored: list[str] = []
    rigs = rec.rigs
    for image in rec.images.values():
        where = _image_index(image.name, frame_index, c)
        if where is None:
            ignored.append(image.name)
            continue
        if not image.has_pose:
            continue
        f, cam = where
        world_from_cam[f, cam] = rigid_inverse(_to_4x4(image.cam_from_world()))
        frame = rec.frames[image.frame_id]
        is_ref[f, cam] = rigs[frame.rig_id].ref_sensor_id == image.data_id.sensor_id
    if ignored:
        logger.warning("%s: %d images match no image of the dataset (e.g. %s); ignored",
                       source, len(ignored), ignored[0])

    have = _valid(world_from_cam.reshape(n * c, 4, 4)).reshape(n, c)
    # preferred camera per frame: a reference-sensor image first, then the lowest index
    rank = np.where(have, np.where(is_ref, 0, 1 + np.arange(c)), c + 1)
    best = np.argmin(rank, axis=1)
    world_from_rig = _nan_poses(n)
    rows = np.flatnonzero(have.any(axis=1))
    world_from_rig[rows] = world_from_cam[rows, best[rows]] @ cam_from_rig[best[rows]]
    return world_from_rig, world_from_cam


_LOG_LOCK = threading.Lock()
_log_depth = 0  # nesting depth of colmap_log_to_logging (only the outermost block redirects)


@contextlib.contextmanager
def colmap_log_to_logging(log: logging.Logger = logger) -> Iterator[None]:
    """Route COLMAP's (glog) messages through Python logging while the block runs.

    COLMAP writes to stderr from C++; inside this block its messages go to a
    temporary log file that a thread forwards line by line: I → ``log.debug``,
    W → ``log.warning``, E/F → ``log.error``. glog is process-global: after
    the block COLMAP logs to stderr again as before (and no longer writes its
    default log files to /tmp). Nested blocks forward through the outermost.
    """
    global _log_depth
    with _LOG_LOCK:
        _log_depth += 1
        outermost = _log_depth == 1
    if not outermost:
        try:
            yield
        finally:
            with _LOG_LOCK:
                _log_depth -= 1
        return

    L = pycolmap.logging
    folder = Path(tempfile.mkdtemp(prefix="bbcity-colmap-log-"))
    prefix = folder / "colmap."
    saved = (L.logtostderr, L.alsologtostderr, L.stderrthreshold)
    levels = {"I": logging.DEBUG, "W": logging.WARNING, "E": logging.ERROR, "F": logging.ERROR}
    stop = threading.Event()
    state = {"offset": 0, "rest": b""}

    def pump(final: bool = False) -> None:
        files = sorted(folder.glob(prefix.name + "*"))
        chunk = b""
        if files:
            with open(files[-1], "rb") as fh:
                fh.seek(state["offset"])
                chunk = fh.read()
                state["offset"] = fh.tell()
        lines = (state["rest"] + chunk).split(b"\n")
        state["rest"] = b"" if final else lines.pop()
        for raw in lines:
            line = raw.decode("utf-8", errors="replace")
            if not line or line[0] not in levels or "] " not in line:
                continue  # the file's header
            log.log(levels[line[0]], "colmap: %s", line.split("] ", 1)[1])

    def run() -> None:
        while not stop.wait(0.2):
            pump()

    L.logtostderr = False
    L.alsologtostderr = False
    L.stderrthreshold = 3  # FATAL only; errors reach the caller through `log`
    L.set_log_destination(L.INFO, str(prefix))
    for level in (L.WARNING, L.ERROR, L.FATAL):
        L.set_log_destination(level, "")  # the INFO file holds every severity
    thread = threading.Thread(target=run, name="colmap-log", daemon=True)
    thread.start()
    try:
        yield
    finally:
        L.set_log_destination(L.INFO, "")  # closes (flushes) the file
        L.logtostderr, L.alsologtostderr, L.stderrthreshold = saved
        stop.set()
        thread.join()
        pump(final=True)
        shutil.rmtree(folder, ignore_errors=True)
        with _LOG_LOCK:
            _log_depth -= 1


def _read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    if not model_dir.is_dir():
        raise DataFormatError(model_dir, "COLMAP model directory does not exist")
    names = {p.name for p in model_dir.iterdir()}
    if not ({"cameras.bin", "images.bin"} <= names or {"cameras.txt", "images.txt"} <= names):
        raise DataFormatError(model_dir, "not a COLMAP model (needs cameras and images as .bin or .txt)")
    try:
        with colmap_log_to_logging():
            return pycolmap.Reconstruction(model_dir)
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with C++ messages
        raise DataFormatError(model_dir, f"cannot read the COLMAP model ({e})") from None


def poses_from_colmap(model_dir: os.PathLike | str, dataset: Dataset, allow_missing: bool = False,
                      metric_tolerance: float = 0.01) -> np.ndarray:
    """Rig poses from an existing COLMAP model (text or binary, with or without rigs).

    Image names are matched to ``cam{c}/{frame}.png`` (any extension; extra
    leading folders allowed; bare ``{frame}.png`` only for a one-camera rig).
    With rigs and frames (COLMAP ≥ 3.12) a frame's pose is its
    ``rig_from_world`` mapped to our rig frame through ``cam_from_rig`` of the
    model's reference camera; without, each frame's cam0 image gives the pose
    (another camera's image when cam0's is not registered).

    The model's units are kept. When two cameras of a frame are registered,
    the model's camera spacing is compared with the calibrated baseline and a
    warning is logged if they differ by more than ``metric_tolerance`` (the
    model is not in metres).

    Returns world_from_rig (n, 4, 4) float64 in ``dataset.frame_names`` order.
    Raises DataFormatError naming ``model_dir`` when it is missing or
    unreadable, and MissingFramesError (a DataFormatError) listing the frames
    without a registered image unless ``allow_missing`` (then they are NaN).
    """
    model_dir = Path(model_dir)
    rec = _read_reconstruction(model_dir)
    world_from_rig, world_from_cam = poses_from_reconstruction(rec, dataset, model_dir)
    ratio = rig_baseline_ratio(world_from_cam, dataset.rig.cam_from_rig)
    if np.isfinite(ratio) and abs(ratio - 1.0) > metric_tolerance:
        logger.warning("%s: camera spacing is %.4g × the calibrated baseline; the model is not metric "
                       "(poses are returned in the model's units)", model_dir, ratio)
    missing = [dataset.frame_names[i] for i in np.flatnonzero(~_valid(world_from_rig))]
    if missing and not allow_missing:
        raise MissingFramesError(model_dir, missing, dataset.num_frames,
                                 " (not registered in the model; allow_missing=True gives NaN poses)")
    logger.info("imported %d of %d frame poses from %s (%d images, %d rigs)",
                dataset.num_frames - len(missing), dataset.num_frames, model_dir,
                rec.num_images(), rec.num_rigs())
    return world_from_rig


# --------------------------------------------------------------------------- 3. structure from motion


@dataclass(frozen=True)
class SfmConfig:
    max_num_features: int = 4096  # SIFT features kept per image
    first_octave: int = -1  # SIFT first octave; -1 upsamples once (more features on small images)
    peak_threshold: float = 0.02 / 3  # SIFT detection threshold (COLMAP's default)
    overlap: int = 3  # sequential matching: each frame is matched with the next `overlap` frames (all rig images)
    quadratic_overlap: bool = False  # also match frames 2^k apart (helps loops, costs pairs)
    max_ratio: float = 0.8  # Lowe ratio test of SIFT matching
    split_passes: bool = True  # never match frames of different passes (poses.json "pass"): opposite sides
    rig_verification: bool = False  # verify whole frame pairs with the known rig (metric; 5-10x slower matching)
    ransac_max_trials: int = 10000  # RANSAC iterations at most per verified image (or frame) pair
    mapper: str = "seeded"  # "seeded" (global SfM seed grown incrementally), "global" or "incremental"
    seed_frames: int = 8  # seeded mapper: frames in the seed window (the best-connected run of a pass)
    max_seeds: int = 10  # seeded mapper: seeds tried at most (a pass broken by a featureless gap needs more)
    refine_rig: bool = False  # bundle adjustment refines sensor_from_rig (scale then restored from the baseline)
    min_model_frames: int = 3  # smallest reconstruction kept, in frames
    min_num_inliers: int = 15  # geometric verification: inlier matches needed to keep an image pair
    min_num_matches: int = 15  # verified matches needed to use an image pair in mapping
    num_threads: int = -1  # CPU threads for COLMAP (-1: all cores)
    seed: int = 0  # COLMAP's random seed (RANSAC, mapping)
    keep_database: bool = True  # keep work_dir/database.db (features and matches) after the run

    def __post_init__(self):
        if self.mapper not in ("seeded", "global", "incremental"):
            raise ValueError(f"mapper must be \"seeded\", \"global\" or \"incremental\", got {self.mapper!r}")
        if self.overlap < 1 or self.max_num_features < 1 or self.min_model_frames < 1:
            raise ValueError("overlap, max_num_features and min_model_frames must be positive")


@dataclass
class SfmResult:
    """Outcome of :func:`poses_sfm`.

    world_from_rig: (n, 4, 4) float64 in ``dataset.frame_names`` order, NaN
        for frames not registered. Metric, in COLMAP's arbitrary world frame;
        frames of different components (disconnected reconstructions, e.g. the
        two passes of a street, which see opposite sides) are in *unrelated*
        frames — align them one component at a time (``trajectory_rmse(...,
        groups=component)``).
    component: (n,) int32, the reconstruction each frame belongs to (0 is the
        largest), −1 when not registered.
    """

    world_from_rig: np.ndarray
    component: np.ndarray
    num_points: int  # 3D points over all components
    mean_reprojection_error: float  # pixels, over all observations
    baseline_ratio: list[float]  # per component: reconstructed / calibrated camera spacing before any rescaling
    scale_applied: list[float]  # per component: factor applied to make it metric (1.0 with a fixed rig)
    seconds: dict[str, float]  # wall time per stage: extract, match, map, total
    model_dirs: list[Path]  # per component: the written COLMAP model (binary)
    database: Path | None  # features and matches (None when not kept)

    @property
    def num_registered(self) -> int:
        return int(np.count_nonzero(self.component >= 0))

    @property
    def num_components(self) -> int:
        return len(self.model_dirs)


def _write_model(rec: pycolmap.Reconstruction, out_dir: Path) -> Path:
    """Write ``rec`` as a binary COLMAP model to out_dir via a temporary sibling and a rename."""
    tmp = out_dir.with_name(f".{out_dir.name}.tmp-{uuid.uuid4().hex}")
    tmp.mkdir(parents=True)
    try:
        rec.write_binary(str(tmp))
        if out_dir.exists():
            shutil.rmtree(out_dir)
        tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def _raw_camera(dataset: Dataset, c: int) -> tuple[str, list[float]]:
    """COLMAP model name and parameters of camera ``c``'s raw image files (what SIFT reads):
    PINHOLE, or the raw K with the lens (OPENCV, FULL_OPENCV, OPENCV_FISHEYE). Undistorting
    does not move a camera, so the poses COLMAP finds are those of the undistorted cameras."""
    return colmap_camera_model(dataset.rig.raw_K(c), dataset.rig.distortion(c))


def _rig_config(dataset: Dataset) -> pycolmap.RigConfig:
    """Known rig for COLMAP: cam0 is the reference sensor, sensor_from_rig = cam_c_from_cam0, fixed
    intrinsics of the raw images (:func:`_raw_camera`)."""
    rig = dataset.rig
    cam0_from_rig_inv = rigid_inverse(rig.cam_from_rig[0])
    cameras = []
    for c in range(rig.num_cameras):
        (w, h), (model, params) = rig.sizes[c], _raw_camera(dataset, c)
        camera = pycolmap.Camera(model=model, width=w, height=h, params=params)
        camera.has_prior_focal_length = True
        cameras.append(pycolmap.RigConfigCamera(
            ref_sensor=c == 0, image_prefix=f"cam{c}/", camera=camera,
            cam_from_rig=None if c == 0 else to_rigid3d(rig.cam_from_rig[c] @ cam0_from_rig_inv)))
    return pycolmap.RigConfig(cameras=cameras)


def _extract(db: Path, dataset: Dataset, image_names: list[str], cfg: SfmConfig) -> None:
    model, params = _raw_camera(dataset, 0)
    reader = pycolmap.ImageReaderOptions(
        camera_model=model,
        # replaced per camera by the rig config; given here so COLMAP marks the focal length as known
        camera_params=",".join(repr(float(v)) for v in params))
    sift = pycolmap.SiftExtractionOptions(max_num_features=cfg.max_num_features, first_octave=cfg.first_octave,
                                          peak_threshold=cfg.peak_threshold)
    extraction = pycolmap.FeatureExtractionOptions(
        num_threads=cfg.num_threads, use_gpu=False, max_image_size=max(max(s) for s in dataset.rig.sizes),
        sift=sift)
    pycolmap.extract_features(db, dataset.root / "images", image_names=image_names,
                              camera_mode=pycolmap.CameraMode.PER_FOLDER, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(db) as database:
        pycolmap.apply_rig_config([_rig_config(dataset)], database)
        for camera in database.read_all_cameras():
            # apply_rig_config copies model and params but not this flag; with it set, two-view
            # geometry is verified with essential matrices (calibrated) rather than fundamental ones
            camera.has_prior_focal_length = True
            database.update_camera(camera)
        n_img, n_kp = database.num_images(), database.num_keypoints()
        n_frames, n_rigs = database.num_frames(), database.num_rigs()
    if n_img != len(image_names):
        raise RuntimeError(f"{db}: COLMAP read {n_img} of {len(image_names)} images")
    logger.info("features: %d images, %.0f SIFT keypoints per image; %d rig frames in %d rig(s)",
                n_img, n_kp / max(n_img, 1), n_frames, n_rigs)


def frame_passes(dataset: Dataset) -> np.ndarray:
    """(n,) int64 pass of each frame from ``poses.json`` (``"pass"``; 0 where absent).

    A pass is one continuous drive; frames of different passes are different
    sequences (the return pass of a street looks at the other side).
    """
    path = dataset.root / "poses.json"
    frames = read_json(path).get("frames", [])
    by_name = {fr.get("name"): fr.get("pass", 0) for fr in frames if isinstance(fr, dict)}
    passes = np.zeros(dataset.num_frames, dtype=np.int64)
    for i, name in enumerate(dataset.frame_names):
        p = by_name.get(name, 0)
        if not isinstance(p, int) or isinstance(p, bool):
            raise DataFormatError(path, f"frame {name}: \"pass\" must be an integer, got {p!r}")
        passes[i] = p
    return passes


def _drop_cross_pass_pairs(db: Path, dataset: Dataset) -> int:
    """Delete matches between images of different passes; returns the number of pairs removed."""
    passes = frame_passes(dataset)
    if len(np.unique(passes)) < 2:
        return 0
    frame_index = {name: i for i, name in enumerate(dataset.frame_names)}
    removed = 0
    with pycolmap.Database.open(db) as database:
        image_pass = {}
        for image in database.read_all_images():
            where = _image_index(image.name, frame_index, dataset.rig.num_cameras)
            image_pass[image.image_id] = passes[where[0]] if where else -1
        pair_ids, _ = database.read_two_view_geometry_num_inliers()
        for pair_id in pair_ids:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if image_pass[a] != image_pass[b]:
                database.delete_two_view_geometry(a, b)
                database.delete_matches(a, b)
                removed += 1
    return removed


def _match(db: Path, dataset: Dataset, cfg: SfmConfig) -> None:
    matching = pycolmap.FeatureMatchingOptions(
        num_threads=cfg.num_threads, use_gpu=False, rig_verification=cfg.rig_verification,
        sift=pycolmap.SiftMatchingOptions(max_ratio=cfg.max_ratio))
    pairing = pycolmap.SequentialPairingOptions(overlap=cfg.overlap, quadratic_overlap=cfg.quadratic_overlap,
                                                expand_rig_images=True, loop_detection=False)
    verification = pycolmap.TwoViewGeometryOptions(min_num_inliers=cfg.min_num_inliers)
    verification.ransac.random_seed = cfg.seed
    verification.ransac.max_num_trials = cfg.ransac_max_trials
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                              verification_options=verification, device=pycolmap.Device.cpu)
    if cfg.split_passes:
        removed = _drop_cross_pass_pairs(db, dataset)
        if removed:
            logger.info("matching: dropped %d image pairs between different passes", removed)
    with pycolmap.Database.open(db) as database:
        logger.info("matching: %d image pairs matched, %d verified",
                    database.num_matched_image_pairs(), database.num_verified_image_pairs())


def _incremental_options(cfg: SfmConfig, image_names: list[str], multiple_models: bool
                         ) -> pycolmap.IncrementalPipelineOptions:
    options = pycolmap.IncrementalPipelineOptions(
        num_threads=cfg.num_threads, random_seed=cfg.seed, min_num_matches=cfg.min_num_matches,
        multiple_models=multiple_models, min_model_size=cfg.min_model_frames, extract_colors=False,
        image_names=image_names, ba_refine_sensor_from_rig=cfg.refine_rig, ba_refine_focal_length=False,
        ba_refine_principal_point=False, ba_refine_extra_params=False)
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    return options


def _global_options(cfg: SfmConfig, image_names: list[str]) -> pycolmap.GlobalPipelineOptions:
    options = pycolmap.GlobalPipelineOptions(
        num_threads=cfg.num_threads, random_seed=cfg.seed, min_num_matches=cfg.min_num_matches,
        multiple_models=True, min_model_size=cfg.min_model_frames, image_names=image_names)
    mapper = options.mapper
    mapper.num_threads, mapper.random_seed = cfg.num_threads, cfg.seed
    mapper.refine_sensor_from_rig = cfg.refine_rig
    mapper.rotation_averaging.refine_sensor_from_rig = cfg.refine_rig
    mapper.rotation_averaging.random_seed = cfg.seed
    mapper.global_positioning.refine_sensor_from_rig = cfg.refine_rig
    mapper.global_positioning.use_gpu = False
    mapper.global_positioning.random_seed = cfg.seed
    ba = mapper.bundle_adjustment
    ba.refine_focal_length = ba.refine_principal_point = ba.refine_extra_params = False
    ba.refine_sensor_from_rig = cfg.refine_rig
    ba.ceres.use_gpu = False
    return options


def _incremental(db: Path, dataset: Dataset, out: Path, options: pycolmap.IncrementalPipelineOptions,
                 bar: tqdm, input_path: Path | None = None) -> list[pycolmap.Reconstruction]:
    out.mkdir(parents=True, exist_ok=True)
    # with a rig, COLMAP registers whole frames: the initial pair, then one frame per callback
    recs = pycolmap.incremental_mapping(
        db, dataset.root / "images", out, options, input_path="" if input_path is None else input_path,
        initial_image_pair_callback=lambda: bar.update(2), next_image_callback=lambda: bar.update(1))
    return list(recs.values())


def _global(db: Path, dataset: Dataset, out: Path, options: pycolmap.GlobalPipelineOptions
            ) -> list[pycolmap.Reconstruction]:
    out.mkdir(parents=True, exist_ok=True)
    return list(pycolmap.global_mapping(db, dataset.root / "images", out, options).values())


def _frame_links(db: Path, dataset: Dataset) -> np.ndarray:
    """(n - 1,) int64: verified inlier matches between frame i and frame i + 1, over all their image pairs."""
    frame_index = {name: i for i, name in enumerate(dataset.frame_names)}
    links = np.zeros(max(dataset.num_frames - 1, 0), dtype=np.int64)
    with pycolmap.Database.open(db) as database:
        frame_of = {}
        for image in database.read_all_images():
            where = _image_index(image.name, frame_index, dataset.rig.num_cameras)
            frame_of[image.image_id] = where[0] if where else -1
        pair_ids, counts = database.read_two_view_geometry_num_inliers()
    for pair_id, count in zip(pair_ids, counts):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        fa, fb = sorted((frame_of[a], frame_of[b]))
        if fa >= 0 and fb == fa + 1:
            links[fa] += count
    return links


def _seed_window(candidates: np.ndarray, links: np.ndarray, size: int) -> np.ndarray | None:
    """The best seed among candidate frames (m,) int, sorted: ``size`` consecutive frames (fewer when
    no run of candidates is that long) whose weakest link (``links`` (n - 1,), see _frame_links) is
    strongest. Returns (k,) int64 frames, or None without candidates."""
    best, best_score = None, (0, -1)
    runs = np.split(candidates, np.flatnonzero(np.diff(candidates) != 1) + 1) if candidates.size else []
    for run in runs:
        k = min(size, len(run))
        for start in range(len(run) - k + 1):
            window = run[start:start + k]
            score = (k, int(links[window[:-1]].min()) if k > 1 else 0)
            if best is None or score > best_score:
                best, best_score = window.astype(np.int64), score
    return best


def _map_seeded(db: Path, dataset: Dataset, out: Path, cfg: SfmConfig, bar: tqdm
                ) -> list[pycolmap.Reconstruction]:
    """Per pass: global SfM on a short, well-connected window (metric through the rig), then the
    incremental mapper grows that seed over the pass; repeated on frames left over."""
    c = dataset.rig.num_cameras
    names = np.array([[f"cam{cam}/{f}.png" for cam in range(c)] for f in dataset.frame_names])
    links = _frame_links(db, dataset)
    passes = frame_passes(dataset) if cfg.split_passes else np.zeros(dataset.num_frames, dtype=np.int64)
    models: list[pycolmap.Reconstruction] = []
    attempt = 0
    for p in np.unique(passes):
        todo = np.flatnonzero(passes == p)
        tried: set[int] = set()
        while todo.size >= cfg.min_model_frames and attempt < cfg.max_seeds:
            seed = _seed_window(np.array([f for f in todo if f not in tried]), links, cfg.seed_frames)
            if seed is None or seed.size < cfg.min_model_frames:
                break
            attempt += 1
            tried.update(seed.tolist())
            seeds = _global(db, dataset, out / f"seed{attempt}",
                            _global_options(cfg, names[seed].ravel().tolist()))
            if not seeds:
                logger.info("SfM seed %d (frames %s–%s) did not reconstruct", attempt,
                            dataset.frame_names[seed[0]], dataset.frame_names[seed[-1]])
                continue
            seed_rec = max(seeds, key=lambda r: r.num_reg_frames())
            seed_dir = out / f"seed{attempt}" / "best"
            seed_dir.mkdir(parents=True, exist_ok=True)
            seed_rec.write_binary(str(seed_dir))
            bar.update(seed_rec.num_reg_frames())
            logger.info("SfM seed %d: %d frames (%s–%s) by global SfM; growing it over %d frames", attempt,
                        seed_rec.num_reg_frames(), dataset.frame_names[seed[0]], dataset.frame_names[seed[-1]],
                        todo.size)
            grown = _incremental(db, dataset, out / f"grow{attempt}",
                                 _incremental_options(cfg, names[todo].ravel().tolist(), multiple_models=False),
                                 bar, input_path=seed_dir)
            if not grown:
                continue
            rec = max(grown, key=lambda r: r.num_reg_frames())
            models.append(rec)
            done, _ = poses_from_reconstruction(rec, dataset, "SfM")
            todo = np.array([f for f in todo if not np.isfinite(done[f]).all()], dtype=np.int64)
    return models


def step_length(dataset: Dataset) -> float:
    """Metres between consecutive frames that a dataset without poses asks SfM to scale to:
    ``dataset.json`` "source" "step_length" (the photos importer's ``--step-length``), else 1.0."""
    path = dataset.root / "dataset.json"
    source = read_json(path).get("source", {}) if path.is_file() else {}
    value = source.get("step_length", 1.0) if isinstance(source, dict) else 1.0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise DataFormatError(path, f"source.step_length must be a positive number of metres, got {value!r}")
    return float(value)


def _level_and_scale(rec: pycolmap.Reconstruction, world_from_rig: np.ndarray, world_from_cam: np.ndarray,
                     step: float) -> float:
    """Move an SfM component of a dataset without poses into a z-up world whose origin and
    heading (+x) are its first registered frame's rig, scaled so that the median distance
    between consecutive registered frames is ``step`` metres. world_from_rig: (n, 4, 4),
    world_from_cam: (n, c, 4, 4) float64 of ``rec`` (NaN = not registered). Transforms
    ``rec`` in place; returns the scale applied."""
    ok = np.flatnonzero(_valid(world_from_rig))
    positions = world_from_rig[ok, :3, 3]
    gaps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    adjacent = gaps[np.diff(ok) == 1]  # frames next to each other in the capture, where there are any
    median = float(np.median(adjacent if adjacent.size else gaps)) if gaps.size else 0.0
    scale = step / median if median > 1e-12 else 1.0
    up = up_direction(world_from_cam.reshape(-1, 4, 4), positions)
    L = level_from_world(up, world_from_rig[ok[0], :3, 0], positions[0])
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(np.ascontiguousarray(L[:3, :3])),
                                 np.ascontiguousarray(scale * L[:3, 3])))
    logger.info("SfM without known poses: world levelled (z up) and scaled by %.4g to %.3g m per frame",
                scale, step)
    return scale


def poses_sfm(dataset: Dataset, work_dir: os.PathLike | str, config: SfmConfig | None = None,
              progress: bool | None = None) -> SfmResult:
    """Rig poses by structure from motion (pycolmap, CPU), metric through the known rig.

    Steps: SIFT on every raw image (one camera per rig camera, calibrated
    intrinsics: PINHOLE, or the raw K and lens of a distorted camera); the rig applied as a known COLMAP rig (cam0 the reference
    sensor, ``sensor_from_rig`` from ``cam_from_rig``; one frame per
    ``frame_names`` entry); sequential matching of each frame's images with
    each other and with all images of the next ``overlap`` frames (pairs
    between different passes dropped, see ``split_passes``); then mapping
    with intrinsics fixed and, unless ``config.refine_rig``,
    ``sensor_from_rig`` fixed — which makes the reconstruction metric. The
    reconstructed camera spacing over the calibrated baseline is checked (1
    with a fixed rig) and returned; with ``refine_rig`` each model is rescaled
    by its inverse.

    Mappers (``config.mapper``): COLMAP's incremental mapper starts from a
    two-view pair of unit baseline while the fixed rig is metric, and on
    planar facades that start can settle in a wrong minimum (a block of
    frames rotated by tens of degrees). COLMAP 4's global mapper avoids it but
    on a long straight drive places parts of the street tens of metres apart
    at weak links (repetitive, low-texture facades). The default "seeded"
    mapper takes the best of both: per pass, global SfM on the
    ``seed_frames`` best-connected consecutive frames, grown over the pass by
    the incremental mapper (new seeds for frames left over).

    work_dir receives ``database.db`` (replaced if present) and the models in
    ``sparse/{k}`` (binary COLMAP, k = component). COLMAP's messages are
    forwarded to logging; incremental mapping shows a tqdm bar of registered
    frames (``progress``: None = only on a terminal).

    A dataset with no known poses (:func:`poses_unknown`, e.g. a photo folder) has no scale
    and no up: each component is then moved to a z-up world (:func:`up_direction`, cameras
    held roughly level; origin and heading from its first registered frame) and scaled so
    that the median distance between consecutive frames is the dataset's step length
    (``dataset.json`` "source" "step_length", metres; 1.0 when absent).

    Returns an :class:`SfmResult`; frames that do not register are NaN.
    """
    cfg = config or SfmConfig()
    unknown = poses_unknown(dataset)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    for p in (db, work / "database.db-wal", work / "database.db-shm"):
        p.unlink(missing_ok=True)
    n, c = dataset.num_frames, dataset.rig.num_cameras
    image_names = [f"cam{cam}/{name}.png" for name in dataset.frame_names for cam in range(c)]
    pycolmap.set_random_seed(cfg.seed)
    seconds: dict[str, float] = {}
    t_all = time.perf_counter()
    tmp_out = work / f".sparse.tmp-{uuid.uuid4().hex}"
    tmp_out.mkdir()
    try:
        with colmap_log_to_logging():
            t = time.perf_counter()
            _extract(db, dataset, image_names, cfg)
            seconds["extract"] = time.perf_counter() - t
            t = time.perf_counter()
            _match(db, dataset, cfg)
            seconds["match"] = time.perf_counter() - t
            t = time.perf_counter()
            bar = tqdm(total=n, desc="sfm", unit="frame", disable=None if progress is None else not progress)
            try:
                if cfg.mapper == "seeded":
                    recs = _map_seeded(db, dataset, tmp_out, cfg, bar)
                elif cfg.mapper == "global":
                    recs = _global(db, dataset, tmp_out, _global_options(cfg, []))
                else:
                    recs = _incremental(db, dataset, tmp_out, _incremental_options(cfg, [], True), bar)
            finally:
                bar.close()
            seconds["map"] = time.perf_counter() - t
    finally:
        shutil.rmtree(tmp_out, ignore_errors=True)

    # components, largest first; a frame in two models (COLMAP allows small overlaps) goes to the larger
    models = sorted(recs, key=lambda r: r.num_reg_frames(), reverse=True)
    world_from_rig = _nan_poses(n)
    component = np.full(n, -1, dtype=np.int32)
    ratios, scales, model_dirs = [], [], []
    num_points, err_sum, obs_sum = 0, 0.0, 0
    sparse = work / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    for k, rec in enumerate(models):
        poses, cams = poses_from_reconstruction(rec, dataset, f"SfM model {k}")
        ratio = rig_baseline_ratio(cams, dataset.rig.cam_from_rig)
        scale = 1.0
        if cfg.refine_rig and np.isfinite(ratio) and ratio > 0:
            scale = 1.0 / ratio
            rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(), np.zeros(3)))
            poses, cams = poses_from_reconstruction(rec, dataset, f"SfM model {k}")
        elif abs(ratio - 1.0) > 1e-6:
            logger.warning("SfM model %d: camera spacing is %.6g × the calibrated baseline with a fixed rig",
                           k, ratio)
        if unknown:
            scale = _level_and_scale(rec, poses, cams, step_length(dataset))
            poses, cams = poses_from_reconstruction(rec, dataset, f"SfM model {k}")
        ratios.append(ratio)
        scales.append(scale)
        new = _valid(poses) & (component < 0)
        world_from_rig[new] = poses[new]
        component[new] = k
        num_points += rec.num_points3D()
        obs = rec.compute_num_observations()
        err_sum += rec.compute_mean_reprojection_error() * obs
        obs_sum += obs
        model_dirs.append(_write_model(rec, sparse / str(k)))
        logger.info("SfM model %d: %d frames, %d images, %d points, reprojection error %.3f px, "
                    "baseline ratio %.6f", k, rec.num_reg_frames(), rec.num_reg_images(), rec.num_points3D(),
                    rec.compute_mean_reprojection_error(), ratio)
    seconds["total"] = time.perf_counter() - t_all
    if not cfg.keep_database:
        db.unlink(missing_ok=True)
    result = SfmResult(world_from_rig, component, num_points, err_sum / obs_sum if obs_sum else float("nan"),
                       ratios, scales, seconds, model_dirs, db if cfg.keep_database else None)
    logger.info("SfM: %d of %d frames registered in %d component(s), %d points, %.1f s "
                "(extract %.1f, match %.1f, map %.1f)", result.num_registered, n, result.num_components,
                num_points, seconds["total"], seconds["extract"], seconds["match"], seconds["map"])
    return result


# --------------------------------------------------------------------------- evaluation


def _kabsch(H: np.ndarray) -> np.ndarray:
    """Rotation R (3, 3) maximising trace(R @ H) for H (3, 3) = Σ x_est ⊗ x_ref (proper, det +1)."""
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    return Vt.T @ D @ U.T


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about the unit vector ``axis`` (3,)."""
    K = _skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking unit vector u (3,) to unit vector v (3,)."""
    w = np.cross(u, v)
    s, c = np.linalg.norm(w), float(u @ v)
    if s > 1e-15:
        return _axis_angle(w / s, np.arctan2(s, c))
    if c > 0:
        return np.eye(3)
    a = np.cross(u, np.eye(3)[np.argmin(np.abs(u))])  # any axis perpendicular to u: half a turn
    a /= np.linalg.norm(a)
    return 2.0 * np.outer(a, a) - np.eye(3)


def _similarity(est: np.ndarray, ref: np.ndarray, with_scale: bool) -> tuple[np.ndarray, float, np.ndarray]:
    """R (3, 3), s, t (3,) minimising Σ|ref_p − (s R est_p + t)|² over valid poses (m, 4, 4) each.

    Umeyama on positions. Where positions leave the rotation free — all on one
    line (a straight drive: the roll about the line) or all at one point —
    the free part maximises the agreement of orientations, Σ trace(R_ref^T R R_est).
    """
    pe, pr = est[:, :3, 3], ref[:, :3, 3]
    me, mr = pe.mean(axis=0), pr.mean(axis=0)
    xe, xr = pe - me, pr - mr
    H = xe.T @ xr  # (3, 3): trace(R @ H) = Σ xr · R xe
    A = np.einsum("mij,mkj->ik", est[:, :3, :3], ref[:, :3, :3])  # trace(R @ A) = Σ trace(R_ref^T R R_est)
    U, sv, Vt = np.linalg.svd(H)
    scale_h = max(np.sqrt((xe ** 2).sum() * (xr ** 2).sum()), 1e-300)
    if sv[0] <= 1e-12 * scale_h:  # one point: orientations alone
        R = _kabsch(A)
    elif sv[1] <= COLLINEAR_RATIO * sv[0]:  # one line: align it, then roll about it by orientations
        d = Vt[0]
        R0 = _rotation_between(U[:, 0], d)
        B = R0 @ A
        R = _axis_angle(d, np.arctan2(np.trace(_skew(d) @ B), np.trace(B) - d @ B @ d)) @ R0
    else:
        R = _kabsch(H)
    s = 1.0
    if with_scale:
        s = float(np.einsum("mi,mi->", xr, xe @ R.T) / (xe ** 2).sum()) if (xe ** 2).sum() > 0 else float("nan")
    return R, s, mr - s * R @ me


def align_trajectory(estimated: np.ndarray, reference: np.ndarray,
                     with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Align an estimated trajectory to a reference (Umeyama on rig positions).

    estimated, reference: (n, 4, 4) float64 world_from_rig of the same frames;
    frames with any NaN in either are ignored. Rotation and translation (and
    with ``with_scale`` a scale) minimise the squared position error
    (Umeyama); orientations decide only what positions leave free: the roll
    about the line when all positions are on one line (a straight drive;
    perpendicular spread below about 1 % of the extent, see
    ``COLLINEAR_RATIO``), the whole rotation for a single position. Needs ≥ 1
    valid frame (≥ 2 for a scale).

    Returns aligned (n, 4, 4) float64 = the estimated poses moved into the
    reference frame (rotation R @ R_est, position s R p + t; NaN frames stay
    NaN), transform (4, 4) float64 reference_from_estimated with ``s R`` in
    its upper-left block, and the scale s (1.0 without ``with_scale``).
    """
    est = np.asarray(estimated, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"estimated {est.shape} and reference {ref.shape} must both be (n, 4, 4)")
    ok = _valid(est) & _valid(ref)
    if not ok.any():
        raise ValueError("no frame has a pose in both trajectories")
    if with_scale and ok.sum() < 2:
        raise ValueError("a scale needs at least two frames with poses in both trajectories")
    R, s, t = _similarity(est[ok], ref[ok], with_scale)
    transform = np.eye(4)
    transform[:3, :3] = s * R
    transform[:3, 3] = t
    aligned = _nan_poses(len(est))
    aligned[ok, :3, :3] = R @ est[ok, :3, :3]
    aligned[ok, :3, 3] = s * est[ok, :3, 3] @ R.T + t
    aligned[ok, 3] = [0.0, 0.0, 0.0, 1.0]
    return aligned, transform, s


def align_components(world_from_rig: np.ndarray, component: np.ndarray, reference: np.ndarray,
                     with_scale: bool = False) -> np.ndarray:
    """Place each component of an SfM trajectory onto reference poses (e.g. GPS/IMU).

    world_from_rig: (n, 4, 4) float64, each component in its own frame (NaN = no pose).
    component: (n,) int, component per frame (negative = none), e.g. ``SfmResult.component``.
    reference: (n, 4, 4) float64 poses in the target frame; NaN frames are not used.
    Each component is moved by the SE(3) (Sim(3) with ``with_scale``) that
    best fits its frames to the reference (:func:`align_trajectory`); a
    component with no reference frame stays NaN.
    Returns (n, 4, 4) float64 in the reference frame.
    """
    est = np.asarray(world_from_rig, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    comp = np.asarray(component)
    out = _nan_poses(len(est))
    for label in np.unique(comp[comp >= 0]):
        sel = (comp == label) & _valid(est)
        usable = sel & _valid(ref)
        if not usable.any() or (with_scale and usable.sum() < 2):
            continue
        # fit on frames with both poses, then move every frame of the component
        _, T, s = align_trajectory(np.where(usable[:, None, None], est, np.nan),
                                   np.where(usable[:, None, None], ref, np.nan), with_scale)
        R = T[:3, :3] / s
        out[sel, :3, :3] = R @ est[sel, :3, :3]
        out[sel, :3, 3] = est[sel, :3, 3] @ T[:3, :3].T + T[:3, 3]
        out[sel, 3] = [0.0, 0.0, 0.0, 1.0]
    return out


def _rotation_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(m,) float64 angle in degrees of A_i^T B_i for rotations A, B (m, 3, 3)."""
    tr = np.einsum("mij,mij->m", A, B)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def trajectory_rmse(estimated: np.ndarray, reference: np.ndarray, with_scale: bool = False,
                    groups: np.ndarray | None = None) -> dict:
    """Trajectory errors after aligning the estimate to the reference.

    estimated, reference: (n, 4, 4) float64 world_from_rig; NaN = no pose.
    with_scale: align with Sim(3) for the main errors (default SE(3): a metric
        estimate is judged with its own scale).
    groups: optional (n,) int, frames aligned separately per group value
        (e.g. ``SfmResult.component``); negative = no pose.

    Returns a dict: ``frames``, ``valid`` (frames with both poses),
    ``missing`` (frames of the reference with no estimate); position errors in
    metres ``rmse_m``, ``mean_m``, ``median_m``, ``max_m``; rotation errors
    in degrees ``rot_rmse_deg``, ``rot_max_deg``; ``scale`` — the Sim(3)
    scale (reference units per estimated unit; of the largest group) —,
    ``scale_error`` = scale − 1, ``sim3_rmse_m`` (RMSE after Sim(3));
    ``path_length_m`` of the reference over valid frames; per frame
    ``position_error_m`` and ``rotation_error_deg`` (n,) float64, NaN where
    a pose is missing. Statistics are NaN when no frame is valid.
    """
    est = np.asarray(estimated, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"estimated {est.shape} and reference {ref.shape} must both be (n, 4, 4)")
    n = len(est)
    g = np.zeros(n, dtype=np.int64) if groups is None else np.asarray(groups).astype(np.int64)
    if g.shape != (n,):
        raise ValueError(f"groups must have shape ({n},), got {g.shape}")
    ok = _valid(est) & _valid(ref) & (g >= 0)
    pos_err = np.full(n, np.nan)
    rot_err = np.full(n, np.nan)
    sim3_err = np.full(n, np.nan)
    best_scale, best_size = float("nan"), 0
    for label in np.unique(g[ok]):
        sel = ok & (g == label)
        e, r = np.where(sel[:, None, None], est, np.nan), np.where(sel[:, None, None], ref, np.nan)
        aligned, _, _ = align_trajectory(e, r, with_scale=with_scale)
        pos_err[sel] = np.linalg.norm(aligned[sel, :3, 3] - ref[sel, :3, 3], axis=1)
        rot_err[sel] = _rotation_deg(aligned[sel, :3, :3], ref[sel, :3, :3])
        if sel.sum() >= 2:
            aligned_s, _, s = align_trajectory(e, r, with_scale=True)
            sim3_err[sel] = np.linalg.norm(aligned_s[sel, :3, 3] - ref[sel, :3, 3], axis=1)
            if sel.sum() > best_size:
                best_scale, best_size = s, int(sel.sum())
    v = pos_err[ok]
    steps = np.linalg.norm(np.diff(ref[ok, :3, 3], axis=0), axis=1) if ok.sum() > 1 else np.empty(0)

    def stat(fn, a):
        return float(fn(a)) if a.size else float("nan")

    return {
        "frames": n,
        "valid": int(ok.sum()),
        "missing": int((_valid(ref) & ~ok).sum()),
        "rmse_m": stat(lambda a: np.sqrt(np.mean(a ** 2)), v),
        "mean_m": stat(np.mean, v),
        "median_m": stat(np.median, v),
        "max_m": stat(np.max, v),
        "rot_rmse_deg": stat(lambda a: np.sqrt(np.mean(a ** 2)), rot_err[ok]),
        "rot_max_deg": stat(np.max, rot_err[ok]),
        "scale": best_scale,
        "scale_error": best_scale - 1.0,
        "sim3_rmse_m": stat(lambda a: np.sqrt(np.mean(a ** 2)), sim3_err[np.isfinite(sim3_err)]),
        "path_length_m": float(steps.sum()),
        "position_error_m": pos_err,
        "rotation_error_deg": rot_err,
    }
