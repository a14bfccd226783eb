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
from typing import Callable, Iterator

import numpy as np

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BenchConfig:
    quick: bool = False  # small inputs for a smoke run (under 3 minutes)
    repeats: int = 3  # each timing is the median of this many runs
    workers: int = 2  # process pool size for the parallel-render comparison


@dataclass
class Measurement:
    """wall and cpu seconds, and the peak resident memory above the start, bytes."""

    wall: float = 0.0
    cpu: float = 0.0
    peak_rss: int = 0


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@contextmanager
def measure() -> Iterator[Measurement]:
    """Time a block (wall, CPU) and sample its peak RSS every 5 ms."""
    m = Measurement()
    base = _rss_bytes()
    peak = [base]
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.005):
            peak[0] = max(peak[0], _rss_bytes())

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
        m.peak_rss = max(peak[0], _rss_bytes()) - base


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
        from data_synth.fileio import write_bytes, write_json

        import cv2
        import open3d

        machine = {"python": platform.python_version(), "platform": platform.platform(),
                   "cpus": os.cpu_count(), "numpy": np.__version__, "open3d": open3d.__version__,
                   "opencv": cv2.__version__}
        write_json(out / "report.json", {"machine": machine, "settings": self.settings,
                                         "sections": self.sections, "notes": self.notes})
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
        return f"{value:.4g}"
    return str(value)


def bench_synthesis(cfg: BenchConfig, report: Report) -> None:
    """Scene generation, the renderer against bare ray casting, serial vs parallel frames."""
    import open3d as o3d

    from data_synth import RigConfig, StreetConfig, SynthConfig, TownConfig, build_street, build_town, make_rig
    from data_synth.dataset import capture_path, write_dataset
    from data_synth.raycast import Renderer

    from .executor import make_executor

    street_cfg = StreetConfig(length=60.0 if cfg.quick else 300.0)
    for name, fn in (("street", lambda: build_street(street_cfg)), ("town", lambda: build_town(TownConfig()))):
        scene = fn()
        m = median_of(fn, cfg.repeats)
        report.add("Scene generation", {"scene": name, "objects": scene.num_objects,
                                        "triangles": len(scene.triangles), "wall s": m.wall, "cpu s": m.cpu,
                                        "peak MB": m.peak_rss / 1e6, "objects/s": scene.num_objects / m.wall})

    width, height = (320, 240) if cfg.quick else (640, 480)
    synth = SynthConfig(street=street_cfg, rig=RigConfig(width=width, height=height), frames=4 if cfg.quick else 10)
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


def run_bench(cfg: BenchConfig, out: Path) -> Path:
    """Run every benchmark section and write the report to ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = Report(settings=asdict(cfg))
    start = time.perf_counter()
    bench_synthesis(cfg, report)
    report.settings["total_seconds"] = time.perf_counter() - start
    report.write(out)
    logger.info("wrote %s", out / "report.md")
    return out
