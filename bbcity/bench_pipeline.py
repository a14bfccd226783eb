"""The whole pipeline on a benchmark street: the stage table and the scaling runs.

:func:`run_pipeline` synthesises a street of a given length, reconstructs it and builds
its billboard model, timing each stage (wall, CPU of this process and of its worker
processes, peak memory) and reading the finer stages (stereo per frame, fusion, octree,
sampling, PCA, atlas packing) from the stage reports. :func:`bench_pipeline` runs it at
1×, 2× and 4× the base length: time should grow linearly with length, memory stay flat.
"""

from __future__ import annotations

import io
import json
import logging
import resource
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from .bench import BenchConfig, Report, measure

logger = logging.getLogger(__name__)


@dataclass
class StageTime:
    """wall s, CPU s (this process + reaped workers), peak MB of this process and of the largest worker."""

    wall: float = 0.0
    cpu: float = 0.0
    peak_mb: float = 0.0
    worker_peak_mb: float = float("nan")


@contextmanager
def stage_time() -> Iterator[StageTime]:
    """Time a stage whose worker processes are shut down inside the block (so that
    their CPU time is counted in RUSAGE_CHILDREN when it ends)."""
    out = StageTime()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with measure() as m:
        yield out
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    out.wall = m.wall
    out.cpu = m.cpu + (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    out.peak_mb = m.peak_rss / 1e6
    if after.ru_maxrss > before.ru_maxrss:  # max over every reaped child so far: only a rise is this stage's
        out.worker_peak_mb = after.ru_maxrss / 1e3


@dataclass
class PipelineRun:
    """One pass of the pipeline: its paths, its stage rows and totals."""

    length: float
    frames: int
    dataset: Path
    work: Path
    model: Path
    rows: list[dict] = field(default_factory=list)
    totals: dict = field(default_factory=dict)


def street_config(cfg: BenchConfig, length: float):
    """The benchmark street: ``length`` m at the default frame spacing (3 m per frame and pass)."""
    from data_synth import RigConfig, StreetConfig, SynthConfig

    width, height = (320, 240) if cfg.quick else (640, 480)
    frames = max(3, int(round(length / 3.0)))
    return SynthConfig(street=StreetConfig(length=float(length)), rig=RigConfig(width=width, height=height),
                       frames=frames, spp=1 if cfg.quick else 2)


def run_pipeline(cfg: BenchConfig, length: float, out: Path, holdout: int = 0) -> PipelineRun:
    """Synthesise, reconstruct and build a ``length`` m street under ``out``; time every stage."""
    from billboards.build import BuildConfig, main as build_main
    from data_synth import write_dataset
    from recon.pipeline import ReconConfig, main as recon_main

    from .executor import executor_scope

    synth = street_config(cfg, length)
    run = PipelineRun(length, 0, out / "street", out / "work", out / "model")

    def row(stage, t: StageTime | None = None, wall=None, items=None, unit="", note=""):
        r = {"length m": length, "stage": stage, "wall s": t.wall if t else wall,
             "cpu s": t.cpu if t else float("nan"), "peak MB": t.peak_mb if t else float("nan"),
             "worker peak MB": t.worker_peak_mb if t else float("nan")}
        if items:
            r["items"] = f"{items} {unit}"
            r["items/s"] = items / r["wall s"] if r["wall s"] else float("nan")
        if note:
            r["note"] = note
        run.rows.append(r)

    with stage_time() as t, executor_scope(cfg.workers) as ex:
        write_dataset(synth, run.dataset, executor=ex, progress=False)
    ds = json.loads((run.dataset / "dataset.json").read_text())
    run.frames = int(ds["frames"])
    row("synthesis", t, items=3 * run.frames, unit="images")

    with stage_time() as t, executor_scope(cfg.workers) as ex:
        recon_main(ReconConfig(), run.dataset, run.work, executor=ex, progress=False)
    rr = json.loads((run.work / "recon_report.json").read_text())
    row("reconstruction (total)", t, items=run.frames, unit="frames")
    row("  stereo, per frame", wall=rr["stages"]["frames_s"], items=run.frames, unit="frames",
        note=f"{rr['stereo_seconds_per_frame']:.2f} s stereo per frame in a worker")
    row("  fusion", wall=rr["stages"]["merge_s"], items=rr["points"], unit="points")

    with stage_time() as t, executor_scope(cfg.workers) as ex:
        result = build_main(BuildConfig(holdout=holdout), run.work / "cloud.ply", run.dataset, run.model,
                            executor=ex, workers=cfg.workers)
    br = result.report
    row("billboard build (total)", t, items=br["voxels"], unit="billboards")
    row("  octree", wall=br["stages"]["octree_s"], items=rr["points"], unit="points")
    for name, key in (("sampling", "sampling_s"), ("PCA", "pca_s"), ("atlas packing (quantise)", "quantize_s")):
        row(f"  {name}", wall=br["worker_seconds"][key], items=br["voxels"], unit="billboards",
            note="worker CPU s, summed over workers")
    row("  atlas packing (write)", wall=br["stages"]["write_s"], items=br["pages"], unit="pages")

    with stage_time() as t:
        load_seconds = model_load(run.model)
    row("model load + GPU upload", t, note=f"load {load_seconds[0]:.3f} s, upload {load_seconds[1]:.3f} s")
    run.totals = {"frames": run.frames, "points": int(rr["points"]), "billboards": int(br["voxels"]),
                  "model_mb": br["bytes"]["model"] / 1e6,
                  "build_main_peak_mb": br["peak_memory"]["main_mb"],
                  "build_worker_peak_mb": br["peak_memory"]["largest_worker_mb"],
                  "recon_peak_mb": rr.get("peak_rss_mb", float("nan"))}
    return run


def model_load(model_dir: Path) -> tuple[float, float]:
    """Seconds to load a model (memory-mapped) and to upload it to the GPU (NaN without EGL)."""
    from billboards.model import load

    t0 = time.perf_counter()
    model = load(model_dir)
    t1 = time.perf_counter()
    try:
        from render.context import create_context
        from render.resources import ModelResources

        ctx = create_context()
    except Exception as e:  # no OpenGL here: the load still counts
        logger.warning("no GL context for the upload timing: %s", e)
        return t1 - t0, float("nan")
    try:
        t2 = time.perf_counter()
        with_resources = ModelResources(ctx, model)
        ctx.finish()
        upload = time.perf_counter() - t2
        with_resources.release()
    finally:
        ctx.release()
    return t1 - t0, upload


def bench_pipeline(cfg: BenchConfig, report: Report, out: Path) -> PipelineRun:
    """Stage table at 1× (kept for the later sections) and the scaling runs at 2× and 4×.
    Returns the 1× run (built with every 4th frame held out for the novel-view section)."""
    base = cfg.street_length
    runs = []
    for scale in cfg.scales:
        root = out / f"pipeline_{scale}x"
        run = run_pipeline(cfg, base * scale, root, holdout=4 if scale == cfg.scales[0] else 0)
        runs.append((scale, run))
        if scale == cfg.scales[0]:
            for r in run.rows:
                report.add("Pipeline stages", r)
    report.notes["Pipeline stages"] = (
        f"A {base:g} m street at {street_config(cfg, base).rig.width}×{street_config(cfg, base).rig.height}, "
        f"3 m between frames, both lanes, {cfg.workers} worker processes. CPU s counts this process and its "
        "reaped workers; indented stages come from the stage reports (worker CPU where noted). The build "
        "holds every 4th frame out of the textures for the novel-view section.")
    first = runs[0][1]
    for scale, run in runs:
        totals = {r["stage"]: r for r in run.rows}
        row = {"scale": f"{scale}×", "length m": run.length, "frames": run.frames, "points": run.totals["points"],
               "billboards": run.totals["billboards"]}
        for stage in ("synthesis", "reconstruction (total)", "billboard build (total)"):
            name = stage.replace(" (total)", "")
            row[f"{name} s"] = totals[stage]["wall s"]
            row[f"{name} s per m, vs 1×"] = (totals[stage]["wall s"] / run.length) / (
                {r["stage"]: r for r in first.rows}[stage]["wall s"] / first.length)
        row["recon peak MB"] = run.totals["recon_peak_mb"]
        row["build peak MB (main)"] = run.totals["build_main_peak_mb"]
        row["build peak MB (worker)"] = run.totals["build_worker_peak_mb"]
        report.add("Scaling", row)
    report.notes["Scaling"] = ("Time per metre relative to the 1× street (1.0 = linear) and peak memory per "
                               "stage; plot: scaling.png.")
    _scaling_plot([r for _, r in runs], out / "scaling.png")
    return first


def _scaling_plot(runs: list[PipelineRun], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from data_synth.fileio import write_bytes

    lengths = [r.length for r in runs]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 4))
    for stage in ("synthesis", "reconstruction (total)", "billboard build (total)"):
        ax_t.plot(lengths, [{x["stage"]: x for x in r.rows}[stage]["wall s"] for r in runs], "o-",
                  label=stage.replace(" (total)", ""))
    ax_t.plot(lengths, np.array(lengths) / lengths[0] * {x["stage"]: x for x in runs[0].rows}["synthesis"]["wall s"],
              "k:", label="linear from 1×")
    ax_t.set(xlabel="street length (m)", ylabel="wall time (s)", title="time per stage")
    ax_t.legend()
    for key, label in (("recon_peak_mb", "reconstruction"), ("build_main_peak_mb", "build, main"),
                       ("build_worker_peak_mb", "build, largest worker")):
        ax_m.plot(lengths, [r.totals[key] for r in runs], "o-", label=label)
    ax_m.set(xlabel="street length (m)", ylabel="peak memory (MB)", title="peak memory", ylim=(0, None))
    ax_m.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    write_bytes(path, buf.getvalue())
