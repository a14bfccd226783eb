"""``bbcity bench``: stage timings paired with baselines measured in the same run.

Shared machines are noisy, so every figure is the median of several runs and
every speed is reported as a ratio against a baseline timed in this process.
The later stages (recon, billboards, render) add their sections here.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import statistics
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np

from core.errors import InputError
from core.memory import rss_bytes

if TYPE_CHECKING:
    from data_synth import RigConfig

logger = logging.getLogger(__name__)


SCENES = ("all", "street", "town", "executor", "city")


@dataclass(frozen=True)
class BenchConfig:
    quick: bool = False  # small inputs for a smoke run (under 3 minutes; "all" leaves the executors out)
    scene: str = "all"  # "street" (the pipeline and everything on its model), "town" (culling), "executor" or "all"
    repeats: int = 3  # each timing is the median of this many runs
    workers: int = 2  # process pool size
    work: str | None = None  # a recon work directory (e.g. the default street's): the billboard sections use it
    street_length: float = 30.0  # metres: the 1× street of the pipeline runs
    scales: tuple[int, ...] = (1, 2, 4)  # street lengths of the scaling runs, in multiples of street_length
    city_scales: tuple[int, ...] = (1, 4, 16)  # the city-scale runs (scene "city", tile by tile), likewise
    city_gpu_budget_mb: int = 256  # the city runs' viewer: its GPU budget (the 1× street should fill it)
    city_lazy: bool = False  # the city runs' datasets cast on demand (no images stored, no ground-truth depth)

    def __post_init__(self):
        if self.scene not in SCENES:
            raise InputError(f"scene must be one of {SCENES}, got {self.scene!r}")
        if not (0 < self.street_length < float("inf") and self.scales and all(int(s) >= 1 for s in self.scales)
                and self.repeats >= 1 and self.workers >= 1 and self.city_gpu_budget_mb >= 1):
            raise InputError(f"invalid BenchConfig: {self}")

    @classmethod
    def quick_config(cls, **overrides) -> "BenchConfig":
        """The smoke run's settings: a 6 m street at 1× and 2×, one repeat."""
        return cls(**{"quick": True, "repeats": 1, "street_length": 6.0, "scales": (1, 2), **overrides})

    def rig(self) -> "RigConfig":
        """The capture rig of the street runs: the default rig (:class:`data_synth.RigConfig`,
        what ``make demo`` builds), at half its width and height for quick runs (the same
        aspect ratio, field of view and pitch)."""
        from dataclasses import replace

        from data_synth import RigConfig

        rig = RigConfig()
        return replace(rig, width=rig.width // 2, height=rig.height // 2) if self.quick else rig


@dataclass
class Measurement:
    """wall and cpu seconds, and the peak resident memory above the start, bytes."""

    wall: float = 0.0
    cpu: float = 0.0
    peak_rss: int = 0


@contextmanager
def measure() -> Iterator[Measurement]:
    """Time a block (wall, CPU) and sample its peak RSS every 5 ms."""
    m = Measurement()
    base = rss_bytes()
    peak = [base]
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.005):
            peak[0] = max(peak[0], rss_bytes())

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    w0, c0 = time.perf_counter(), time.process_time()
    try:
        yield m
    finally:
        m.wall = time.perf_counter() - w0
        m.cpu = time.process_time() - c0
        stop.set()
        sampler.join()
        m.peak_rss = max(peak[0], rss_bytes()) - base


def median_of(fn: Callable[[], object], repeats: int) -> Measurement:
    """Run ``fn`` ``repeats`` times; the median wall/cpu and the largest peak."""
    runs = []
    for _ in range(repeats):
        with measure() as m:
            fn()
        runs.append(m)
    return Measurement(statistics.median(r.wall for r in runs), statistics.median(r.cpu for r in runs),
                       max(r.peak_rss for r in runs))


@dataclass
class Report:
    """Sections of rows; each row a dict. Serialised to report.json and report.md."""

    settings: dict
    sections: dict[str, list[dict]] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)

    def add(self, section: str, row: dict) -> None:
        self.sections.setdefault(section, []).append(row)
        logger.info("%s: %s", section, row)

    def write(self, out: Path) -> None:
        from core.fileio import write_bytes, write_json

        import cv2
        import open3d

        machine = {"python": platform.python_version(), "platform": platform.platform(),
                   "cpus": os.cpu_count(), "numpy": np.__version__, "open3d": open3d.__version__,
                   "opencv": cv2.__version__}
        write_json(out / "report.json", _json_ready({"machine": machine, "settings": self.settings,
                                                     "sections": self.sections, "notes": self.notes}))
        lines = ["# bbcity benchmark", "", "Machine: " + ", ".join(f"{k} {v}" for k, v in machine.items()),
                 "", "Settings: " + json.dumps(self.settings), ""]
        for name, rows in self.sections.items():
            lines += [f"## {name}", ""]
            if name in self.notes:
                lines += [self.notes[name], ""]
            keys = list(dict.fromkeys(k for r in rows for k in r))
            lines += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
            for r in rows:
                lines.append("| " + " | ".join(_fmt(r.get(k, "")) for k in keys) + " |")
            lines.append("")
        write_bytes(out / "report.md", "\n".join(lines).encode())


def _fmt(value) -> str:
    if isinstance(value, float):
        return "n/a" if not np.isfinite(value) else f"{value:.4g}"
    return str(value)


def _json_ready(value):
    """``value`` with non-finite floats as None (JSON null = no measurement) and numpy scalars as Python's."""
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def bench_synthesis(cfg: BenchConfig, report: Report) -> None:
    """Scene generation, the renderer against bare ray casting, serial vs parallel frames."""
    import open3d as o3d

    from data_synth import StreetConfig, SynthConfig, TownConfig, build_street, build_town, make_rig
    from data_synth.dataset import capture_path, write_dataset
    from data_synth.raycast import Renderer

    from .executor import make_executor

    street_cfg = StreetConfig(length=30.0 if cfg.quick else 300.0)
    for name, fn in (("street", lambda: build_street(street_cfg)), ("town", lambda: build_town(TownConfig()))):
        scene = fn()
        m = median_of(fn, cfg.repeats)
        report.add("Scene generation", {"scene": name, "objects": scene.num_objects,
                                        "triangles": len(scene.triangles), "wall s": m.wall, "cpu s": m.cpu,
                                        "peak MB": m.peak_rss / 1e6, "objects/s": scene.num_objects / m.wall})

    rig_cfg = cfg.rig()
    width, height = rig_cfg.width, rig_cfg.height
    synth = SynthConfig(street=street_cfg, rig=rig_cfg, frames=4 if cfg.quick else 10)
    rig = make_rig(synth.rig)
    poses, _ = capture_path(synth)
    pose = rig.world_from_cam(poses[len(poses) // 4], 0)
    scene = build_street(street_cfg)
    renderer = Renderer(scene)
    K = rig.intrinsics[0]

    # Baseline: bare Open3D ray casting of the same number of rays, no shading.
    spp = synth.spp
    n_rays = width * height * (spp * spp + 1)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    dirs = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], -1) @ (pose[:3, :3] @ np.linalg.inv(K)).T
    rays = np.empty((len(dirs), 6), np.float32)
    rays[:, :3], rays[:, 3:] = pose[:3, 3], dirs
    rays = o3d.core.Tensor(np.tile(rays, (spp * spp + 1, 1)))
    base = median_of(lambda: renderer._raycaster.cast_rays(rays), cfg.repeats)
    ours = median_of(lambda: renderer.render(K, pose, (width, height), spp=spp), cfg.repeats)
    report.add("Ground-truth renderer", {"what": "Open3D cast_rays only (baseline)", "image": f"{width}x{height}",
                                         "rays": n_rays, "wall s": base.wall, "Mrays/s": n_rays / base.wall / 1e6,
                                         "ratio to baseline": 1.0})
    report.add("Ground-truth renderer", {"what": f"render, spp {spp} (cast + shade)", "image": f"{width}x{height}",
                                         "rays": n_rays, "wall s": ours.wall, "Mrays/s": n_rays / ours.wall / 1e6,
                                         "ratio to baseline": ours.wall / base.wall, "peak MB": ours.peak_rss / 1e6})
    report.notes["Ground-truth renderer"] = ("One camera image; the ratio is the cost of procedural shading "
                                             "and supersampling over bare ray casting.")

    # Whole dataset: one process vs a process pool, same frames.
    timings = {}
    for workers in (1, cfg.workers):
        def run(workers=workers):
            with tempfile.TemporaryDirectory() as tmp, make_executor(workers) as ex:
                write_dataset(synth, Path(tmp) / "d", executor=ex, progress=False)
        timings[workers] = median_of(run, 1)  # long enough that one run is stable
    n_frames = len(poses)
    for workers, m in timings.items():
        report.add("Dataset writing", {"workers": workers, "frames": n_frames, "images": 3 * n_frames,
                                       "wall s": m.wall, "frames/s": n_frames / m.wall,
                                       "speed-up vs 1 worker": timings[1].wall / m.wall})
    report.notes["Dataset writing"] = "Includes process start-up and scene set-up in each worker."


def street_surface_points(count: int, length: float = 300.0, seed: int = 0) -> np.ndarray:
    """(count, 3) float64 points spread uniformly over the default street's surfaces
    (a stand-in for a fused cloud when none is given)."""
    from data_synth import StreetConfig, build_street

    scene = build_street(StreetConfig(length=length))
    tri = scene.vertices[scene.triangles]                                  # (m, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tri), count, p=area / area.sum())
    a, b = rng.random((2, count))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[pick]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def bench_octree(cfg: BenchConfig, report: Report) -> None:
    """Our vectorised octree against Open3D's ``Octree.convert_from_point_cloud`` at the same depth."""
    from billboards.octree import OctreeConfig, build_octree, open3d_octree

    if cfg.work is not None:
        from recon.cloud_io import read_cloud_arrays

        points, _ = read_cloud_arrays(Path(cfg.work) / "cloud.ply")
        source = f"{cfg.work}/cloud.ply"
    else:
        points = street_surface_points(500_000 if cfg.quick else 15_000_000)
        source = "points on the default street's surfaces"
    voxel = build_octree(points, OctreeConfig(voxel_size=0.5, min_points=10))
    depth = voxel.depth
    same = OctreeConfig(voxel_size=None, depth=depth, min_points=1)
    ours = median_of(lambda: build_octree(points, same), cfg.repeats)
    leaves = build_octree(points, same).num_voxels
    bb = median_of(lambda: build_octree(points, OctreeConfig(voxel_size=0.5, min_points=10)), cfg.repeats)
    base_points = points[:: -(-len(points) // 4_000_000)]  # Open3D is slow: every n-th point, at most 4 M
    o3d_leaves = open3d_octree(base_points, depth)
    o3d = median_of(lambda: open3d_octree(base_points, depth), 1)
    o3d_rate = len(base_points) / o3d.wall
    report.add("Octree", {"what": "Open3D convert_from_point_cloud (baseline)", "points": len(base_points),
                          "depth": depth, "leaves": o3d_leaves, "wall s": o3d.wall, "Mpoints/s": o3d_rate / 1e6,
                          "ratio to baseline": 1.0})
    report.add("Octree", {"what": "build_octree, same depth, every occupied leaf", "points": len(points),
                          "depth": depth, "leaves": leaves, "wall s": ours.wall, "Mpoints/s": len(points) / ours.wall / 1e6,
                          "ratio to baseline": len(points) / ours.wall / o3d_rate, "peak MB": ours.peak_rss / 1e6})
    report.add("Octree", {"what": "build_octree, 0.5 m voxels, ≥ 10 points (the build's)", "points": len(points),
                          "depth": depth, "leaves": voxel.num_voxels, "wall s": bb.wall,
                          "Mpoints/s": len(points) / bb.wall / 1e6, "ratio to baseline": len(points) / bb.wall / o3d_rate})
    report.notes["Octree"] = (f"Cloud: {source}. Ratios compare points per second (Open3D on at most 4 M of the "
                              "points: it is slow). Ours is single-threaded numpy. Leaf counts differ because "
                              "Open3D centres its root cube on the bounding box.")


def bench_billboards(cfg: BenchConfig, report: Report, out: Path, work: Path, build: bool) -> None:
    """On a recon work directory: the billboard build (stages, compression and PSNR) when
    ``build``, the texture sweep, and occlusion-aware vs naive sampling against ground truth."""
    from billboards.build import BuildConfig, main as build_main
    from billboards.evaluate import compare_sampling
    from data_synth import load_dataset
    from recon.work import Work

    from .executor import executor_scope
    from .sweeps import texture_sweep

    work = Path(work)
    dataset = Work.open(work).dataset()
    conf = BuildConfig()
    if build:
        with executor_scope(cfg.workers) as ex, measure() as m:
            build_main(conf, work / "cloud.ply", dataset, out / "model", executor=ex)
        _build_rows(report, json.loads((out / "model" / "build_report.json").read_text()), m)
    sweep = texture_sweep(work / "cloud.ply", dataset, out, count=32 if cfg.quick else 512,
                          tiles=(conf.sampling.tile,) if cfg.quick else (8, 16, 32))
    for row in sweep["sweep"]:
        report.add("Texture sweep", {k: row[k] for k in ("setting", "tile", "tile_mode", "coef_mode", "mean_rank",
                                                          "compression", "psnr_rgb_db", "psnr_rgba_db",
                                                          "compress_ms_per_billboard")})
    report.notes["Texture sweep"] = "Work-precision plot: texture_sweep.png."
    if load_dataset(dataset).has_ground_truth:
        ev = compare_sampling(dataset, work / "cloud.ply", conf.octree, count=20 if cfg.quick else 100)
        for name in ("near_occluders", "random"):
            for method in ("occlusion_aware", "naive"):
                report.add("Sampling against ground truth", {
                    "billboards": name.replace("_", " "),
                    "sampling": method.replace("_", "-") + (" (baseline)" if method == "naive" else ""),
                    "samples": ev[name]["samples"], "PSNR RGB dB": ev[name][method]["psnr_rgb"],
                    "alpha agreement": ev[name][method]["alpha_agreement"],
                    "PSNR behind occluders dB": ev[name][method + "_behind_occluders"]["psnr_rgb"],
                    "texels behind occluders": ev[name]["texels_behind_occluders"]})


def _number(value: float | None) -> float:
    """A report's figure as a table number: NaN for "no measurement" (None)."""
    return float("nan") if value is None else float(value)


def _build_rows(report: Report, r: dict, m: Measurement | None = None) -> None:
    """The "Billboard build" and "Billboard model" rows of a build report."""
    for stage, seconds in r["stages"].items():
        report.add("Billboard build", {"stage": stage.removesuffix("_s"), "wall s": seconds})
    for stage, seconds in r["worker_seconds"].items():
        report.add("Billboard build", {"stage": f"{stage.removesuffix('_s')} (worker CPU s)", "wall s": seconds,
                                       "ms per billboard": 1e3 * seconds / r["voxels"]})
    report.add("Billboard build", {"stage": "total", "wall s": r["total_s"] if m is None else m.wall,
                                   "cpu s (main)": float("nan") if m is None else m.cpu,
                                   "peak MB (main)": r["peak_memory"]["main_mb"],
                                   "peak MB (largest worker)": _number(r["peak_memory"]["largest_worker_mb"]),
                                   "billboards": r["voxels"],
                                   "billboards/s": r["voxels"] / (r["total_s"] if m is None else m.wall)})
    report.add("Billboard model", {"billboards": r["voxels"], "mean rank": r["mean_rank"], "slots": r["slots"],
                                   "pages": r["pages"], "raw MB": r["bytes"]["raw_samples"] / 1e6,
                                   "model MB": r["bytes"]["model"] / 1e6, "compression": r["compression_ratio"],
                                   "PSNR RGB opaque dB": r["psnr"]["decoded_rgb_opaque_db"],
                                   "PSNR RGBA dB": r["psnr"]["decoded_rgba_db"],
                                   "PCA only, RGBA dB": r["psnr"]["pca_rgba_db"]})
    report.notes["Billboard model"] = ("Raw = the sampled 8-bit RGBA textures (d × t × t × 4 bytes per billboard); "
                                       "PSNR of the decoded (quantised) model against them.")


def bench_stereo(cfg: BenchConfig, report: Report, dataset: Path, out: Path) -> None:
    """Accuracy against seconds per frame over SGBM settings; trinocular vs the best single pair."""
    from .sweeps import stereo_sweep

    result = stereo_sweep(dataset, out, num_frames=2 if cfg.quick else 4)
    for row in result["sweep"]:
        report.add("Stereo sweep", row)
    for row in result["pairs_vs_trinocular"]:
        report.add("Stereo: trinocular vs single pairs", row)
    report.notes["Stereo sweep"] = "Work-precision plot: stereo_sweep.png (accuracy against seconds per frame)."


def run_bench(cfg: BenchConfig, out: Path) -> Path:
    """Run the benchmark sections of ``cfg.scene`` and write the report to ``out``.

    The street sections run the pipeline on a ``street_length`` street at each scale
    (:mod:`bbcity.bench_pipeline`), then measure stereo, textures, rendering and novel
    views on the 1× run (the billboard sections on ``cfg.work`` instead when given).
    """
    from recon.work import Work

    from .bench_pipeline import bench_pipeline
    from .bench_render import bench_decode_and_cull, bench_novel_views, bench_town

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = Report(settings={**asdict(cfg), "rig": asdict(cfg.rig())})
    start = time.perf_counter()
    timings = report.settings.setdefault("section_seconds", {})

    def section(name: str, fn, *args) -> None:
        t0 = time.perf_counter()
        fn(*args)
        timings[name] = time.perf_counter() - t0
        logger.info("bench: %s took %.0f s", name, timings[name])

    if cfg.scene in ("all", "street"):
        section("synthesis", bench_synthesis, cfg, report)
        runs: list = []
        section("pipeline", lambda: runs.append(bench_pipeline(cfg, report, out)))
        run = runs[0]
        section("octree", bench_octree, cfg, report)
        section("stereo", bench_stereo, cfg, report, run.dataset, out)
        work = Path(cfg.work) if cfg.work is not None else run.work
        section("textures", bench_billboards, cfg, report, out, work, cfg.work is not None)
        if cfg.work is None:
            _build_rows(report, json.loads((run.model / "build_report.json").read_text()))
        model = out / "model" if cfg.work is not None else run.model
        dataset = Work.open(work).dataset()
        length = json.loads((dataset / "dataset.json").read_text())["synth"]["street"]["length"]
        section("rendering", bench_decode_and_cull, cfg, report, model, float(length), dataset)
        section("novel views", bench_novel_views, cfg, report, run.dataset, run.work, run.model, out, 4)
    if cfg.scene in ("all", "town"):
        section("town", bench_town, cfg, report)
    if cfg.scene == "city":  # not in "all": an hour on this machine
        from .bench_city import bench_city

        section("city", bench_city, cfg, report, out, cfg.city_scales)
    if cfg.scene == "executor" or (cfg.scene == "all" and not cfg.quick):
        # (a quick run of everything leaves it out: two more recons and builds, whose outputs'
        # byte identity the executor's own tests check; --scene executor --quick runs it)
        from .bench_executor import bench_executor

        section("executor", bench_executor, cfg, report, out)
    report.settings["total_seconds"] = time.perf_counter() - start
    report.write(out)
    logger.info("wrote %s", out / "report.md")
    return out
