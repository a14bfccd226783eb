"""Rig poses by structure from motion with pycolmap on the CPU: :func:`poses_sfm`.

SIFT, sequential matching across the rig, the rig as a *known* rig (calibrated
intrinsics and ``sensor_from_rig`` kept fixed), a global-SfM seed grown by
incremental mapping, so the reconstruction comes out in metres. Its world frame is
arbitrary, one per connected component (a street's two passes see opposite
sides and share nothing): :func:`recon.trajectory.align_components` places them.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from capture.colmap import colmap_camera_model, to_rigid3d
from capture.dataset import Dataset
from capture.native import pycolmap
from capture.poses import posed, unknown_poses
from core.errors import InputError
from core.fileio import atomic_dir
from core.rigid import rigid_inverse

from .capture_scale import CaptureScale, capture_scale, scale_factor
from .colmap_log import colmap_log_to_logging
from .colmap_poses import image_index, poses_from_reconstruction
from .ground_plane import ground_up
from .poses import frame_passes, poses_unknown
from .trajectory import level_from_world, rig_baseline_ratio, up_direction

logger = logging.getLogger(__name__)

__all__ = ["SfmConfig", "SfmResult", "poses_sfm"]


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
            raise InputError(f"mapper must be \"seeded\", \"global\" or \"incremental\", got {self.mapper!r}")
        if self.overlap < 1 or self.max_num_features < 1 or self.min_model_frames < 1:
            raise InputError("overlap, max_num_features and min_model_frames must be positive")


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
    scale_from: list[str]  # per component: "rig" (a known rig's baseline), "step_length", "gps" or "arbitrary"
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
    with atomic_dir(out_dir) as tmp:
        rec.write_binary(str(tmp))
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


def _extract(db: Path, dataset: Dataset, image_names: list[str], cfg: SfmConfig,
             max_image_size: int | None = None) -> None:
    model, params = _raw_camera(dataset, 0)
    reader = pycolmap.ImageReaderOptions(
        camera_model=model,
        # replaced per camera by the rig config; given here so COLMAP marks the focal length as known
        camera_params=",".join(repr(float(v)) for v in params))
    sift = pycolmap.SiftExtractionOptions(max_num_features=cfg.max_num_features, first_octave=cfg.first_octave,
                                          peak_threshold=cfg.peak_threshold)
    extraction = pycolmap.FeatureExtractionOptions(
        # COLMAP reads each image at most max_image_size pixels along its longer side and scales
        # the keypoints back to the full image
        num_threads=cfg.num_threads, use_gpu=False,
        max_image_size=min(max(max(s) for s in dataset.rig.sizes), max_image_size or np.inf),
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
            where = image_index(image.name, frame_index, dataset.rig.num_cameras)
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
            where = image_index(image.name, frame_index, dataset.rig.num_cameras)
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


def _level_and_scale(rec: pycolmap.Reconstruction, world_from_rig: np.ndarray, world_from_cam: np.ndarray,
                     scale: CaptureScale) -> tuple[float, str]:
    """Move an SfM component of a dataset without poses into a z-up world whose origin and
    heading (+x) are its first registered frame's rig, scaled as ``scale`` says (:func:`scale_factor`).
    world_from_rig: (n, 4, 4), world_from_cam: (n, c, 4, 4) float64 of ``rec`` (NaN = not
    registered). Transforms ``rec`` in place; returns the factor applied and the scale's kind."""
    ok = np.flatnonzero(posed(world_from_rig))
    positions = world_from_rig[ok, :3, 3]
    factor, kind = scale_factor(scale, positions, ok)
    cams = world_from_cam.reshape(-1, 4, 4)
    up = up_direction(cams, positions)
    points = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    ground = ground_up(points, cams[posed(cams), :3, 3], up)  # a pitched camera tilts the cameras' up
    up = up if ground is None else ground
    L = level_from_world(up, world_from_rig[ok[0], :3, 0], positions[0])
    rec.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(np.ascontiguousarray(L[:3, :3])),
                                 np.ascontiguousarray(factor * L[:3, 3])))
    logger.info("SfM without known poses: world levelled (z up) and scaled by %.4g (%s)", factor,
                {"step_length": f"{scale.step:.3g} m between consecutive frames", "gps": "the photos' GPS positions",
                 "arbitrary": "arbitrary units: 1 between consecutive frames"}[kind])
    return factor, kind


def poses_sfm(dataset: Dataset, work_dir: os.PathLike | str, config: SfmConfig | None = None,
              progress: bool | None = None, max_image_size: int | None = None) -> SfmResult:
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
    and no up: each component is then moved to a z-up world (from its sparse points' largest
    ground or wall plane, :func:`recon.ground_plane.ground_up`, else :func:`up_direction`
    from cameras held roughly level; origin and heading from its first registered frame)
    and scaled as
    :func:`capture_scale` says: the median distance between consecutive frames becomes the
    dataset's step length (metres), or the distances between frames far apart become those
    of their GPS positions, or consecutive frames end up 1 apart in arbitrary units (the
    result's ``scale_from`` says which).

    max_image_size: SIFT reads each image at most this many pixels along its longer side
    (None: whole; recon's working resolution).

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
            _extract(db, dataset, image_names, cfg, max_image_size)
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
    world_from_rig = unknown_poses(n)
    component = np.full(n, -1, dtype=np.int32)
    ratios, scales, scale_from, model_dirs = [], [], [], []
    num_points, err_sum, obs_sum = 0, 0.0, 0
    sparse = work / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    for k, rec in enumerate(models):
        poses, cams = poses_from_reconstruction(rec, dataset, f"SfM model {k}")
        ratio = rig_baseline_ratio(cams, dataset.rig.cam_from_rig)
        scale, source = 1.0, "rig"
        if cfg.refine_rig and np.isfinite(ratio) and ratio > 0:
            scale = 1.0 / ratio
            rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(), np.zeros(3)))
            poses, cams = poses_from_reconstruction(rec, dataset, f"SfM model {k}")
        elif abs(ratio - 1.0) > 1e-6:
            logger.warning("SfM model %d: camera spacing is %.6g × the calibrated baseline with a fixed rig",
                           k, ratio)
        if unknown:
            scale, source = _level_and_scale(rec, poses, cams, capture_scale(dataset))
            poses, cams = poses_from_reconstruction(rec, dataset, f"SfM model {k}")
        ratios.append(ratio)
        scales.append(scale)
        scale_from.append(source)
        new = posed(poses) & (component < 0)
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
                       ratios, scales, scale_from, seconds, model_dirs, db if cfg.keep_database else None)
    logger.info("SfM: %d of %d frames registered in %d component(s), %d points, %.1f s "
                "(extract %.1f, match %.1f, map %.1f)", result.num_registered, n, result.num_components,
                num_points, seconds["total"], seconds["extract"], seconds["match"], seconds["map"])
    return result
