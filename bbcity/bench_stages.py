"""``bbcity bench`` sections on single stages: the octree against Open3D's, the stereo sweep,
and on a recon work directory the billboard build, the texture sweep and occlusion-aware
against naive sampling."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .bench_config import BenchConfig
from .bench_measure import Measurement, measure, median_of
from .bench_report import Report
from .executor import executor_scope
from .sweeps import STEREO_FRAMES, TEXTURE_TILES, stereo_sweep, texture_sweep


def street_surface_points(count: int, length: float | None = None, seed: int = 0) -> np.ndarray:
    """(count, 3) float64 points spread uniformly over the surfaces of the default street
    (``length`` m long; None: its default length), a stand-in for a fused cloud when none is given."""
    from data_synth import StreetConfig, build_street

    scene = build_street(StreetConfig() if length is None else StreetConfig(length=length))
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
    from billboards.build_config import BuildConfig
    from billboards.octree import OctreeConfig, build_octree, open3d_octree

    if cfg.work is not None:
        from recon.cloud_io import read_cloud_arrays

        points, _ = read_cloud_arrays(Path(cfg.work) / "cloud.ply")
        source = f"{cfg.work}/cloud.ply"
    else:
        points = street_surface_points(500_000 if cfg.quick else 15_000_000)
        source = "points on the default street's surfaces"
    build = BuildConfig().octree
    voxel = build_octree(points, build)
    depth = voxel.depth
    same = OctreeConfig(voxel_size=None, depth=depth, min_points=1)
    ours = median_of(lambda: build_octree(points, same), cfg.repeats)
    leaves = build_octree(points, same).num_voxels
    bb = median_of(lambda: build_octree(points, build), cfg.repeats)
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
    report.add("Octree", {"what": f"build_octree, {build.voxel_size:g} m voxels, ≥ {build.min_points} points "
                                  "(the build's)", "points": len(points),
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
    from capture.dataset import load_dataset
    from recon.work import Work

    work = Path(work)
    dataset = Work.open(work).dataset()
    conf = BuildConfig()
    if build:
        with executor_scope(cfg.workers) as ex, measure() as m:
            build_main(conf, work / "cloud.ply", dataset, out / "model", executor=ex)
        build_rows(report, json.loads((out / "model" / "build_report.json").read_text()), m)
    sweep = texture_sweep(work / "cloud.ply", dataset, out, count=32 if cfg.quick else 512,
                          tiles=(conf.sampling.tile,) if cfg.quick else TEXTURE_TILES)
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


def build_rows(report: Report, r: dict, m: Measurement | None = None) -> None:
    """The "Billboard build" and "Billboard model" rows of a build report ``r`` (``build_report.json``),
    with the build's total timed as ``m`` when it ran here."""
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
    result = stereo_sweep(dataset, out, num_frames=2 if cfg.quick else STEREO_FRAMES)
    for row in result["sweep"]:
        report.add("Stereo sweep", row)
    for row in result["pairs_vs_trinocular"]:
        report.add("Stereo: trinocular vs single pairs", row)
    report.notes["Stereo sweep"] = "Work-precision plot: stereo_sweep.png (accuracy against seconds per frame)."
