"""The reconstruction stage: dataset → ``cloud.ply`` + ``recon_report.json``.

Frames are independent until the merge: each is rectified, matched by
trinocular stereo, back-projected and spilled to voxel tiles by a task that
runs on any ``concurrent.futures.Executor``. The merge then fuses the tiles
(see :mod:`recon.fusion`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from capture.dataset import Dataset, held_out_frames, load_dataset
from capture.poses import save_poses
from core.errors import InputError
from core.fileio import DataFormatError, read_json, write_json
from core.memory import available_bytes, peak_memory
from core.tasks import executor_workers, run_tasks

from .cloud_io import PlyStreamWriter, read_cloud_tiles
from .colmap_poses import DEPTH_QUANTILES, frame_depths, poses_from_colmap, read_reconstruction
from .evaluate import evaluate_cloud, evaluate_cloud_tiles, truth_scene, truth_scenes
from .fusion import FusionConfig, TileSpill, merge_tiles
from .motion_stereo import MotionStereoConfig, motion_depth, select_partners
from .points import depth_to_points
from .preflight import check_rig_pairs
from .poses import frame_passes, poses_given, poses_unknown
from .rectify import rectify_rig
from .sfm import SfmConfig, poses_sfm
from .trajectory import align_components, trajectory_rmse
from .stereo import MEMORY_SHARE, MIN_DEPTH
from .trinocular import TrinocularConfig, frame_depth
from .work import REPORT, WORK_POSES, Work, dataset_digest, file_digest
from .working_size import resize_image, scaled_rig, working_scale

logger = logging.getLogger(__name__)

POSE_SOURCES = ("given", "colmap", "sfm")


@dataclass(frozen=True)
class ReconConfig:
    trinocular: TrinocularConfig = field(default_factory=TrinocularConfig)  # stereo and pair agreement
    fusion: FusionConfig = field(default_factory=FusionConfig)  # voxel merge and outlier removal
    poses: str = "given"  # "given" (poses.json), "colmap" (import colmap_model) or "sfm" (pycolmap)
    colmap_model: str | None = None  # COLMAP model directory for poses == "colmap"
    sfm: SfmConfig = field(default_factory=SfmConfig)  # pycolmap settings for poses == "sfm"
    frame_stride: int = 1  # use every n-th frame
    pixel_stride: int = 1  # back-project every n-th pixel of each depth map
    evaluate: bool = True  # compare with ground truth when the dataset has it
    keep_spill: bool = False  # keep the voxel tiles under WORK/spill after the merge
    holdout: int = 0  # leave every n-th frame out (held out for `bbcity eval`; 0: none), as `bbcity build --holdout`
    motion: MotionStereoConfig = field(default_factory=MotionStereoConfig)  # one-camera rigs: partner frames
    max_image_size: int | None = 1600  # stereo and SfM features at most this many pixels along the longer side
    near_margin: float = 1.5  # depth range from sparse points: nearest sparse depth (2nd percentile) / this
    far_margin: float = 2.0  # … up to the farthest (98th percentile) × this

    def __post_init__(self):
        held_out_frames(0, self.holdout)  # validates
        if self.frame_stride < 1 or self.pixel_stride < 1:
            raise InputError("frame_stride and pixel_stride must be ≥ 1")
        if self.max_image_size is not None and (isinstance(self.max_image_size, bool) or self.max_image_size < 64):
            raise InputError(f"max_image_size must be at least 64 pixels, got {self.max_image_size}")
        if not (1.0 <= self.near_margin < np.inf and 1.0 <= self.far_margin < np.inf):
            raise InputError(f"near_margin and far_margin must be finite and ≥ 1, got {self.near_margin}, "
                             f"{self.far_margin}")

    def depth_range(self, depths: np.ndarray) -> tuple[float, float] | None:
        """(min_depth, max_depth) to match a frame whose sparse points lie at ``depths`` (3,)
        (near, median, far: :data:`recon.colmap_poses.DEPTH_QUANTILES`), widened by the margins;
        None (the stereo preset's range) when the frame has no sparse depths."""
        if not np.all(np.isfinite(depths)):
            return None
        return max(float(depths[0]) / self.near_margin, MIN_DEPTH), float(depths[2]) * self.far_margin


@dataclass(frozen=True)
class _FrameTask:
    dataset: str
    frame: int
    world_from_rig: list
    spill_root: str
    origin: list
    trinocular: TrinocularConfig
    fusion: FusionConfig
    pixel_stride: int
    motion: MotionStereoConfig | None = None  # one-camera rigs: motion stereo settings
    partners: tuple = ()  # one-camera rigs: (frame, world_from_rig as a list) of each partner frame
    max_image_size: int | None = None  # working resolution (recon.working_size)


_PAIRS_CACHE: dict = {}
_DATASET_CACHE: dict = {}


def _worker_dataset(path: str) -> Dataset:
    """The dataset at ``path``, opened once per worker while its rig.json, poses.json and
    dataset.json keep their size and time (a long-lived cluster worker may see a dataset
    rewritten at the same path): opening checks every image file, each frame's task reads two."""
    key = (path,) + tuple(_stamp(Path(path) / name) for name in ("rig.json", "poses.json", "dataset.json"))
    if key not in _DATASET_CACHE:
        _DATASET_CACHE.clear()
        _DATASET_CACHE[key] = load_dataset(path)
    return _DATASET_CACHE[key]


def _stamp(path: Path) -> tuple[int, int] | None:
    """(modification time ns, size) of a file, None where it cannot be read: what tells a
    rewritten file."""
    try:
        s = path.stat()
    except OSError:
        return None
    return s.st_mtime_ns, s.st_size


def _process_frame(task: _FrameTask) -> dict:
    """Stereo for one frame, then spill its points. Runs in a worker process."""
    t0 = time.perf_counter()
    ds = _worker_dataset(task.dataset)
    if ds.rig.num_cameras == 1:  # one camera: stereo with neighbouring frames
        return _process_frame_motion(task, ds, t0)
    # rectification maps: once per rig and worker (as the dataset above)
    rig = scaled_rig(ds.rig, working_scale(ds.rig.sizes[0], task.max_image_size))
    key = (task.dataset, _stamp(Path(task.dataset) / "rig.json"), rig.sizes)
    if key not in _PAIRS_CACHE:
        _PAIRS_CACHE.clear()
        _PAIRS_CACHE[key] = rectify_rig(rig)
    pairs = _PAIRS_CACHE[key]
    images = [resize_image(ds.image(task.frame, c), rig.sizes[c]) for c in range(rig.num_cameras)]
    t_read = time.perf_counter()
    fd = frame_depth(images, pairs, task.trinocular)
    t_stereo = time.perf_counter()
    world_from_rig = np.asarray(task.world_from_rig, dtype=np.float64)
    world_from_cam = world_from_rig @ np.linalg.inv(rig.cam_from_rig[0])
    points, colours, conf = depth_to_points(fd.depth, rig.intrinsics[0], world_from_cam, images[0],
                                            fd.confidence, stride=task.pixel_stride)
    spill = TileSpill(Path(task.spill_root), np.asarray(task.origin), task.fusion)
    voxels = spill.add_frame(ds.frame_names[task.frame], points, colours, conf)
    return _frame_finished(task, {"frame": task.frame, "points": int(len(points)), "voxels": voxels,
                                  "read_s": t_read - t0, "stereo_s": t_stereo - t_read,
                                  "total_s": time.perf_counter() - t0})


def _process_frame_motion(task: _FrameTask, ds, t0: float) -> dict:
    """:func:`_process_frame` for a one-camera rig: motion stereo with the partner frames."""
    frames = [task.frame] + [f for f, _ in task.partners]
    rig_poses = [task.world_from_rig] + [T for _, T in task.partners]
    rig = scaled_rig(ds.rig, working_scale(ds.rig.sizes[0], task.max_image_size))
    cam_from_rig = rig.cam_from_rig[0]
    world_from_cam = np.stack([np.asarray(T, dtype=np.float64) @ np.linalg.inv(cam_from_rig) for T in rig_poses])
    images = [resize_image(ds.image(f, 0), rig.sizes[0]) for f in frames]
    t_read = time.perf_counter()
    intrinsics = np.repeat(np.asarray(rig.intrinsics[:1], dtype=np.float64), len(frames), axis=0)
    fd = motion_depth(images, intrinsics, world_from_cam, task.motion or MotionStereoConfig(), task.trinocular)
    t_stereo = time.perf_counter()
    points, colours, conf = depth_to_points(fd.depth, rig.intrinsics[0], world_from_cam[0], images[0],
                                            fd.confidence, stride=task.pixel_stride)
    spill = TileSpill(Path(task.spill_root), np.asarray(task.origin), task.fusion)
    voxels = spill.add_frame(ds.frame_names[task.frame], points, colours, conf)
    return _frame_finished(task, {"frame": task.frame, "points": int(len(points)), "voxels": voxels,
                                  "partners": frames[1:], "read_s": t_read - t0, "stereo_s": t_stereo - t_read,
                                  "total_s": time.perf_counter() - t0})


#: Beside the spilled frames: what they were made from (a later run resumes only from the same).
SPILL_INPUTS = "inputs.json"


def _frame_done(spill_root, frame: int) -> Path:
    """The marker of a frame whose voxels are all spilled (its statistics, JSON)."""
    return Path(spill_root) / "done" / f"{frame:06d}.json"


def _frame_finished(task: _FrameTask, stats: dict) -> dict:
    """Mark the task's frame spilled (after every tile file of it is written) and return its statistics."""
    write_json(_frame_done(task.spill_root, task.frame), stats)
    return stats


def _frame_trinocular(conf: ReconConfig, depths: np.ndarray, memory_budget: float) -> TrinocularConfig:
    """The stereo settings of a frame whose sparse points lie at ``depths`` (3,): the preset's,
    with the depth range from those points when there are any (:meth:`ReconConfig.depth_range`),
    and ``memory_budget`` bytes for each pair's matcher (recon.stereo)."""
    span = conf.depth_range(depths)
    stereo = replace(conf.trinocular.stereo, memory_budget=memory_budget)
    if span is not None:
        stereo = replace(stereo, min_depth=span[0], max_depth=span[1])
    return replace(conf.trinocular, stereo=stereo)


def _spill_inputs(conf: ReconConfig, dataset_dir: Path, world_from_rig: np.ndarray, frames: list[int],
                  origin: np.ndarray, depths: np.ndarray) -> dict:
    """What the spilled frames depend on: the stereo and fusion settings, the dataset, the poses,
    sparse depths and frames used, the origin (JSON; equal inputs, equal dict)."""
    settings = {k: v for k, v in config_json(conf).items()
                if k in ("trinocular", "fusion", "pixel_stride", "motion", "poses", "colmap_model", "sfm",
                         "max_image_size", "near_margin", "far_margin")}
    manifest = Path(dataset_dir) / "dataset.json"
    return {"settings": settings, "dataset": str(Path(dataset_dir).resolve()),
            "dataset_json": hashlib.sha256(manifest.read_bytes()).hexdigest() if manifest.is_file() else None,
            "poses": hashlib.sha256(np.ascontiguousarray(world_from_rig[frames]).tobytes()).hexdigest(),
            "depths": hashlib.sha256(np.ascontiguousarray(depths[frames]).tobytes()).hexdigest(),
            "frames": [int(f) for f in frames], "origin": origin.tolist()}


def _spilled_inputs(spill_root: Path) -> dict | None:
    """The inputs an existing spill was made from (None: unknown or unreadable)."""
    try:
        return read_json(spill_root / SPILL_INPUTS)
    except (DataFormatError, OSError):
        return None


def _with_motion_partners(tasks: list, ds, world_from_rig: np.ndarray, excluded, config: MotionStereoConfig,
                          depths: np.ndarray) -> list:
    """Give each task of a one-camera rig its stereo partners among the posed frames that are
    not ``excluded`` (held out: their images stay out of the model); depths: (n, 3) float64
    sparse depths per frame (:func:`recon.colmap_poses.frame_depths`, NaN: none)."""
    world_from_cam = world_from_rig @ np.linalg.inv(ds.rig.cam_from_rig[0])
    world_from_cam[list(excluded)] = np.nan  # never a partner
    partners = select_partners(world_from_cam, ds.rig.intrinsics[0], ds.rig.sizes[0], config,
                               frames=[t.frame for t in tasks], depth=depths[:, 1])
    out = []
    for t in tasks:
        chosen = tuple((int(j), world_from_rig[j].tolist()) for j in partners[t.frame] if j >= 0)
        if not chosen:
            logger.warning("frame %d has no stereo partner (no neighbouring frame %g–%g × the scene depth away, "
                           "moving sideways to the view; see MotionStereoConfig)", t.frame,
                           config.min_baseline_ratio, config.max_baseline_ratio)
        out.append(replace(t, motion=config, partners=chosen))
    if out and not any(t.partners for t in out):
        raise InputError(f"{ds.root}: no frame of this one-camera capture has a stereo partner (neighbouring frames "
                         f"{config.min_baseline_ratio:g}–{config.max_baseline_ratio:g} × the scene depth apart, "
                         "moving sideways to the view; walking toward what is photographed gives none)")
    return out


def _model_depths(model_dirs: list[Path], ds) -> np.ndarray:
    """(n, 3) float64 sparse depths per frame (:func:`frame_depths`) from COLMAP models, the
    first model that holds a frame giving its depths; NaN where none does."""
    depths = np.full((ds.num_frames, len(DEPTH_QUANTILES)), np.nan)
    for model in model_dirs:
        found = frame_depths(read_reconstruction(Path(model)), ds)
        todo = ~np.isfinite(depths).all(axis=1)
        depths[todo] = found[todo]
    return depths


def estimate_poses(conf: ReconConfig, dataset: Dataset | os.PathLike | str,
                   work: Path) -> tuple[np.ndarray, dict, np.ndarray]:
    """world_from_rig (n, 4, 4) float64 from the configured source, a report, and the depths
    of the sparse points each frame sees ((n, 3) float64 near/median/far, :func:`frame_depths`;
    NaN where the source has none: given poses). ``dataset``: the loaded dataset or its directory."""
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    no_depths = np.full((ds.num_frames, len(DEPTH_QUANTILES)), np.nan)
    if conf.poses == "given":
        return poses_given(ds), {"source": "given"}, no_depths
    if conf.poses == "colmap":
        if not conf.colmap_model:
            raise InputError("--poses colmap needs --colmap-model DIR (a COLMAP model directory)")
        return (poses_from_colmap(Path(conf.colmap_model), ds), {"source": "colmap", "model": str(conf.colmap_model)},
                _model_depths([Path(conf.colmap_model)], ds))
    if conf.poses == "sfm":
        result = poses_sfm(ds, work / "sfm", conf.sfm, max_image_size=conf.max_image_size)
        report = {"source": "sfm", "registered_frames": result.num_registered,
                  "components": result.num_components, "points": result.num_points,
                  # NaN (nothing registered; one camera: no baseline) is no JSON number
                  "mean_reprojection_error_px": (result.mean_reprojection_error
                                                 if np.isfinite(result.mean_reprojection_error) else None),
                  "baseline_ratio": [r if np.isfinite(r) else None for r in result.baseline_ratio],
                  "seconds": result.seconds,
                  "models": [str(p) for p in result.model_dirs]}
        if poses_unknown(ds):
            # nothing to align to: SfM's own (levelled, step-scaled) frame; its components are
            # unrelated, so only the largest is kept
            report["scale_applied"] = result.scale_applied
            report["scale_from"] = result.scale_from  # "arbitrary": the model is in SfM's units, not metres
            if result.scale_from[:1] == ["arbitrary"]:
                logger.warning("SfM's scale is arbitrary (no --step-length at import, no GPS): the cloud and the "
                               "model are in SfM units, consecutive frames 1 apart")
            dropped = int(np.count_nonzero(result.component > 0))
            if dropped:
                logger.warning("%d frames registered in %d smaller SfM components are left out (no poses to "
                               "place them)", dropped, result.num_components - 1)
            return (np.where((result.component == 0)[:, None, None], result.world_from_rig, np.nan), report,
                    _model_depths(result.model_dirs[:1], ds))
        # each component aligned on its own (SE(3), no scale): SfM's frame is arbitrary
        report["trajectory_vs_dataset"] = trajectory_rmse(result.world_from_rig, ds.world_from_rig,
                                                          groups=result.component)
        for per_frame in ("position_error_m", "rotation_error_deg"):  # arrays: the report keeps the summary
            report["trajectory_vs_dataset"].pop(per_frame)
        # The passes of a street see opposite sides and share no features, so SfM
        # returns unrelated components; poses.json (GPS/IMU in a real capture)
        # places each one, SfM keeps its own relative poses.
        return (align_components(result.world_from_rig, result.component, ds.world_from_rig), report,
                _model_depths(result.model_dirs, ds))
    raise InputError(f"unknown pose source {conf.poses!r}; expected one of {POSE_SOURCES}")


def write_work_poses(work: Path, ds, world_from_rig: np.ndarray, source: str) -> Path | None:
    """Write ``work/poses.json`` (the dataset's format, frames without a pose ``null``) when
    the poses came from another ``source`` than the dataset's own ("given"); returns its
    path, else None (and an earlier run's file is removed: it would describe other poses)."""
    path = work / WORK_POSES
    if source == "given":
        path.unlink(missing_ok=True)
        return None
    return save_poses(path, world_from_rig, frame_passes(ds), names=list(ds.frame_names))


def config_json(conf: "ReconConfig") -> dict:
    """The config as JSON values: paths and other objects as strings, and the non-finite numbers
    a config may hold (``max_depth`` inf: no limit) as "Infinity"/"-Infinity"/"NaN" strings
    (strict JSON has no such numbers)."""
    return json.loads(json.dumps(asdict(conf), default=str), parse_constant=str)


def main(conf: ReconConfig, dataset_dir: os.PathLike | str, work_dir: os.PathLike | str,
         executor: Executor | None = None, progress: bool | None = None) -> Path:
    """Reconstruct ``dataset_dir`` into ``work_dir/cloud.ply``; write ``recon_report.json``.

    executor: runs frames in parallel; None runs them in this process.
    Returns the cloud's path.
    """
    dataset_dir, work = Path(dataset_dir), Path(work_dir)
    ds = load_dataset(dataset_dir)
    work.mkdir(parents=True, exist_ok=True)
    stages: dict[str, float] = {}

    t0 = time.perf_counter()
    world_from_rig, pose_report, depths = estimate_poses(conf, ds, work)  # the dataset read once
    stages["poses_s"] = time.perf_counter() - t0
    poses_file = write_work_poses(work, ds, world_from_rig, conf.poses)

    held_out = held_out_frames(ds.num_frames, conf.holdout)
    check_rig_pairs(ds, conf.max_image_size)  # here, not in the workers: one line naming rig.json
    frames = [f for f in range(0, ds.num_frames, conf.frame_stride) if f not in set(held_out)]
    frames = [f for f in frames if np.all(np.isfinite(world_from_rig[f]))]
    if not frames:
        raise InputError(f"{dataset_dir}: no frame has a pose (source {conf.poses!r}); nothing to reconstruct")
    # The model origin: float64 world coordinates stay on the CPU, everything
    # stored in voxels is relative to it (a city's UTM coordinates survive).
    origin = np.round(world_from_rig[frames, :3, 3].mean(axis=0), 3)
    spill_root = work / "spill"
    inputs = _spill_inputs(conf, dataset_dir, world_from_rig, frames, origin, depths)
    if spill_root.exists() and _spilled_inputs(spill_root) != inputs:
        TileSpill(spill_root, origin, conf.fusion).cleanup()  # never mix with another run's frames
    write_json(spill_root / SPILL_INPUTS, inputs)
    # each worker's matcher may take its share of a quarter of the memory free now (recon.stereo)
    budget = conf.trinocular.stereo.memory_budget or available_bytes() * MEMORY_SHARE / executor_workers(executor)
    tasks = [_FrameTask(str(dataset_dir), f, world_from_rig[f].tolist(), str(spill_root), origin.tolist(),
                        _frame_trinocular(conf, depths[f], budget), conf.fusion, conf.pixel_stride,
                        max_image_size=conf.max_image_size) for f in frames]
    if ds.rig.num_cameras == 1:  # one camera: each frame's stereo partners are neighbouring frames
        tasks = _with_motion_partners(tasks, ds, world_from_rig, held_out, conf.motion, depths)
    ranged = np.isfinite(depths[frames]).all(axis=1)
    if ranged.any():
        logger.info("depth ranges of %d of %d frames from their sparse points (median %.3g–%.3g)",
                    int(ranged.sum()), len(frames), np.median(depths[frames][ranged, 0]) / conf.near_margin,
                    np.median(depths[frames][ranged, 2]) * conf.far_margin)
    # a run killed before its merge left the frames it finished: they are not done again
    resumed = [read_json(p) for t in tasks if (p := _frame_done(spill_root, t.frame)).is_file()]
    tasks = [t for t in tasks if not _frame_done(spill_root, t.frame).is_file()]

    finished = False
    try:
        logger.info("stereo on %d frames × %d cameras, poses: %s%s", len(tasks), ds.rig.num_cameras, conf.poses,
                    f" ({len(resumed)} frames done by an earlier run)" if resumed else "")
        t1 = time.perf_counter()
        frame_stats = resumed + run_tasks(_process_frame, tasks, executor, desc="stereo", progress=progress)
        stages["frames_s"] = time.perf_counter() - t1

        logger.info("merging %d frames (%.1f s of stereo)", len(frame_stats), stages["frames_s"])
        t2 = time.perf_counter()
        spill = TileSpill(spill_root, origin, conf.fusion)
        centres = np.array([(world_from_rig[f] @ np.linalg.inv(ds.rig.cam_from_rig[0]))[:3, 3] for f in frames])
        cloud_path = work / "cloud.ply"
        with PlyStreamWriter(cloud_path, normals=conf.fusion.normals, tiles=spill.grid) as writer:
            num_points = merge_tiles(spill, centres, writer.append_file, executor)
            # the report, written last, marks a finished run: an earlier run's must not describe the new cloud
            (work / REPORT).unlink(missing_ok=True)
        if num_points == 0:
            logger.warning("no points reconstructed (nothing textured in view?); %s holds an empty cloud", cloud_path)
        stages["merge_s"] = time.perf_counter() - t2
        finished = True
    except (KeyboardInterrupt, SystemExit):  # killed: the next run resumes from the frames spilled
        raise
    except BaseException:  # an error (bad input, a full disk): the voxel tiles are temporaries
        if not conf.keep_spill:
            TileSpill(spill_root, origin, conf.fusion).cleanup()
        raise
    if finished and not conf.keep_spill:
        TileSpill(spill_root, origin, conf.fusion).cleanup()

    report = {
        "dataset": str(dataset_dir.resolve()),
        "dataset_from_work": os.path.relpath(dataset_dir.resolve(), work.resolve()),
        "dataset_digest": dataset_digest(dataset_dir),
        "poses_digest": None if poses_file is None else file_digest(poses_file),
        "config": config_json(conf),
        "frames": len(frames), "resumed_frames": len(resumed), "held_out_frames": held_out, "points": num_points,
        "origin": origin.tolist(),
        "poses": pose_report, "poses_file": None if poses_file is None else str(poses_file.resolve()), "stages": stages,
        "seconds_per_frame": float(np.median([s["total_s"] for s in frame_stats])) if frame_stats else None,
        "stereo_seconds_per_frame": float(np.median([s["stereo_s"] for s in frame_stats])) if frame_stats else None,
        "peak_memory": peak_memory(),
    }
    if conf.evaluate:
        t3 = time.perf_counter()
        accuracy = score_cloud(ds, cloud_path, num_points, conf.trinocular.stereo.max_depth)
        if accuracy is not None:
            report["accuracy"] = accuracy
            stages["evaluate_s"] = time.perf_counter() - t3
    write_json(work / REPORT, report)
    logger.info("cloud: %d points → %s", num_points, cloud_path)
    return cloud_path


def score_cloud(ds: Dataset, cloud_path: Path, num_points: int, max_depth: float) -> dict | None:
    """The accuracy and completeness of the cloud at ``cloud_path`` (``num_points`` points)
    against ``ds``'s ground truth, surfaces up to ``max_depth`` metres
    (:func:`~recon.evaluate.evaluate_cloud_tiles`); None for a dataset without per-image
    ground-truth depth."""
    if not ds.has_gt_depth:
        if ds.has_ground_truth:
            logger.info("%s has no per-image ground-truth depth (gt/depth, gt/ids): the cloud is not scored", ds.root)
        return None
    tiles = read_cloud_tiles(cloud_path) if num_points else None
    if tiles is not None:  # tile by tile: memory flat in the street's length
        return evaluate_cloud_tiles(tiles, ds, truth_scenes(ds), max_depth=max_depth)
    return evaluate_cloud(np.zeros((0, 3)), ds, truth_scene(ds), max_depth=max_depth)


def score_work(dataset_dir: os.PathLike | str, work_dir: os.PathLike | str) -> Path:
    """Score the finished reconstruction in ``work_dir`` (``recon --no-eval``) against the
    ground truth of ``dataset_dir``, the dataset it was made from: its ``recon_report.json``
    gains ``accuracy`` and the stage ``evaluate_s``, as a run without ``--no-eval`` writes them.
    DataFormatError naming the report when there is none or it describes another dataset;
    InputError for a dataset without per-image ground-truth depth.
    Returns the report's path."""
    path = Path(work_dir) / REPORT
    if not path.is_file():
        raise DataFormatError(path, "no finished reconstruction to score (run recon without --eval-only first)")
    work = Work.open(work_dir)
    report, max_depth = work.report, work.max_depth()
    if report.get("dataset_digest") != dataset_digest(dataset_dir):
        raise DataFormatError(path, f"describes another dataset than {dataset_dir}")
    ds = load_dataset(dataset_dir)
    if not ds.has_gt_depth:
        raise InputError(f"{dataset_dir}: no per-image ground-truth depth (gt/depth): nothing to score the cloud by")
    t0 = time.perf_counter()
    report["accuracy"] = score_cloud(ds, work.cloud, int(report.get("points", 0)), max_depth)
    report.setdefault("stages", {})["evaluate_s"] = time.perf_counter() - t0
    write_json(path, report)
    return path
