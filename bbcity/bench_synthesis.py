"""``bbcity bench`` section: scene generation, the ground-truth renderer against bare ray
casting, and dataset writing in one process against a process pool."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from .bench_config import BenchConfig
from .bench_measure import median_of
from .bench_report import Report
from .executor import make_executor


def bench_synthesis(cfg: BenchConfig, report: Report) -> None:
    """Scene generation, the renderer against bare ray casting, serial vs parallel frames."""
    import open3d as o3d

    from data_synth import StreetConfig, SynthConfig, TownConfig, build_street, build_town, make_rig
    from data_synth.dataset import capture_path, write_dataset
    from data_synth.raycast import Renderer

    street_cfg = StreetConfig(length=30.0) if cfg.quick else StreetConfig()
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
