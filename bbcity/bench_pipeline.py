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
import os
import resource
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.memory import child_pids, rss_bytes
from recon.work import Work

from .bench_config import FRAME_SPACING, BenchConfig
from .bench_report import Report
from .executor import executor_scope

logger = logging.getLogger(__name__)

#: The 1× build holds every HOLDOUT-th frame out of its textures, for the novel-view section.
HOLDOUT = 4


@dataclass
class StageTime:
    """wall s, CPU s (the stage's process and its workers), peak MB of the stage's process
    and of its largest worker (NaN: it had none)."""

    wall: float = 0.0
    cpu: float = 0.0
    peak_mb: float = 0.0
    worker_peak_mb: float = float("nan")


def _rss_mb(pid: int | str = "self") -> float:
    return rss_bytes(pid) / 1e6


def _run_stage(stage, args: tuple) -> dict:
    """In a fresh process: run one stage (a name in _STAGES, or a module-level function) and
    return its resource use (and a small result).

    Peak memory is sampled from /proc every 50 ms (this process, and each of its worker
    processes): ``ru_maxrss`` would not do, as Linux carries it over from the parent
    through fork and exec."""
    peaks = {"own": _rss_mb(), "worker": float("nan")}
    stop = threading.Event()

    def sample() -> None:
        me = os.getpid()
        while not stop.wait(0.05):
            peaks["own"] = max(peaks["own"], _rss_mb())
            for child in child_pids(me):
                peaks["worker"] = np.nanmax([peaks["worker"], _rss_mb(child)])

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    try:
        result = (_STAGES[stage] if isinstance(stage, str) else stage)(*args)
    finally:
        stop.set()
        sampler.join()
    wall = time.perf_counter() - t0
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall": wall, "cpu": own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime,
            "peak_mb": max(peaks["own"], _rss_mb()), "worker_peak_mb": float(peaks["worker"]), "result": result}


def _synthesis(synth, dataset: Path, workers: int):
    from data_synth import write_dataset

    with executor_scope(workers) as ex:
        write_dataset(synth, dataset, executor=ex, progress=False)


def _reconstruction(dataset: Path, work: Path, workers: int):
    from recon.pipeline import ReconConfig, main as recon_main

    with executor_scope(workers) as ex:
        recon_main(ReconConfig(), dataset, work, executor=ex, progress=False)


def _build(work: Path, dataset: Path, model: Path, workers: int, holdout: int):
    from billboards.build import BuildConfig, main as build_main

    with executor_scope(workers) as ex:
        build_main(BuildConfig(holdout=holdout), work / "cloud.ply", dataset, model, executor=ex)


_STAGES = {"synthesis": _synthesis, "reconstruction": _reconstruction, "build": _build,
           "load": lambda model: model_load(model)}


def stage_in_fresh_process(stage, *args) -> tuple[StageTime, object]:
    """Run ``stage`` (a name in _STAGES, or a module-level function) in a new (spawned)
    process; its StageTime (wall timed here, so the process start-up is included) and its result."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    t0 = time.perf_counter()
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as ex:
        out = ex.submit(_run_stage, stage, args).result()
    return StageTime(time.perf_counter() - t0, out["cpu"], out["peak_mb"], out["worker_peak_mb"]), out["result"]


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
    fit: dict = field(default_factory=dict)   # the build report's "fit"


def street_config(cfg: BenchConfig, length: float):
    """The benchmark street: ``length`` m, :data:`~bbcity.bench_config.FRAME_SPACING` m per frame and
    pass, seen by :meth:`BenchConfig.rig` (the default rig; half its resolution when quick)."""
    from data_synth import StreetConfig, SynthConfig

    frames = max(3, int(round(length / FRAME_SPACING)))
    return SynthConfig(street=StreetConfig(length=float(length)), rig=cfg.rig(), frames=frames,
                       spp=1 if cfg.quick else SynthConfig.spp)


def run_pipeline(cfg: BenchConfig, length: float, out: Path, holdout: int = 0) -> PipelineRun:
    """Synthesise, reconstruct and build a ``length`` m street under ``out``, each stage in a
    fresh process; time every stage."""
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

    t, _ = stage_in_fresh_process("synthesis", synth, run.dataset, cfg.workers)
    run.frames = int(json.loads((run.dataset / "dataset.json").read_text())["frames"])
    row("synthesis", t, items=3 * run.frames, unit="images")

    t, _ = stage_in_fresh_process("reconstruction", run.dataset, run.work, cfg.workers)
    rr = Work.open(run.work).report
    row("reconstruction (total)", t, items=run.frames, unit="frames")
    row("  stereo, per frame", wall=rr["stages"]["frames_s"], items=run.frames, unit="frames",
        note=f"{rr['stereo_seconds_per_frame']:.2f} s stereo per frame in a worker")
    row("  fusion", wall=rr["stages"]["merge_s"], items=rr["points"], unit="points")
    recon = t

    t, _ = stage_in_fresh_process("build", run.work, run.dataset, run.model, cfg.workers, holdout)
    br = json.loads((run.model / "build_report.json").read_text())
    row("billboard build (total)", t, items=br["voxels"], unit="billboards")
    row("  octree", wall=br["stages"]["octree_s"], items=rr["points"], unit="points")
    for name, key in (("sampling", "sampling_s"), ("PCA", "pca_s"), ("atlas packing (quantise)", "quantize_s")):
        row(f"  {name}", wall=br["worker_seconds"][key], items=br["voxels"], unit="billboards",
            note="worker CPU s, summed over workers")
    row("  atlas packing (write)", wall=br["stages"]["write_s"], items=br["pages"], unit="pages")
    fit = br.get("fit", {})
    if fit.get("enabled"):
        row("  fit: training views cast", wall=br["stages"]["fit_cast_s"], items=fit["views"], unit="views")
        row("  fit: solve + compress", wall=br["stages"]["fit_solve_compress_s"], items=fit["measurements"],
            unit="measurements", note=f"training pixels {fit['psnr_all_before_db']:.2f} → "
                                      f"{fit['psnr_all_after_db']:.2f} dB in the fit's rendering")
    run.fit = fit
    build = t

    t, (load_s, upload_s) = stage_in_fresh_process("load", run.model)
    row("model load + GPU upload", t, note=f"load {load_s:.3f} s, upload {upload_s:.3f} s, the rest is "
                                          "process start-up")
    run.totals = {"frames": run.frames, "points": int(rr["points"]), "billboards": int(br["voxels"]),
                  "model_mb": br["bytes"]["model"] / 1e6,
                  "recon_peak_mb": recon.peak_mb, "recon_worker_peak_mb": recon.worker_peak_mb,
                  "build_main_peak_mb": build.peak_mb, "build_worker_peak_mb": build.worker_peak_mb}
    return run


def model_load(model_dir: Path) -> tuple[float, float]:
    """Seconds to load a model (memory-mapped) and to upload it to the GPU (NaN without EGL)."""
    from billboards.model_reader import load

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
    Returns the 1× run (built with every :data:`HOLDOUT`-th frame held out for the novel-view section)."""
    base = cfg.street_length
    runs = []
    for scale in cfg.scales:
        root = out / f"pipeline_{scale}x"
        run = run_pipeline(cfg, base * scale, root, holdout=HOLDOUT if scale == cfg.scales[0] else 0)
        runs.append((scale, run))
        if scale == cfg.scales[0]:
            for r in run.rows:
                report.add("Pipeline stages", r)
    rig = cfg.rig()
    report.notes["Pipeline stages"] = (
        f"A {base:g} m street seen by the default rig at {rig.width}×{rig.height} ({rig.hfov_deg:g}° horizontal "
        f"field of view, pitched up {rig.pitch_deg:g}°), "
        f"{FRAME_SPACING:g} m between frames, both lanes, {cfg.workers} worker processes. Each stage runs in a "
        "fresh process (its start-up, 2–3 s of imports, is in the wall time); CPU s and peak MB are that process's and its "
        "workers'. Indented stages come from the stage reports (worker CPU where noted). The build holds every "
        f"{HOLDOUT}th frame out of the textures for the novel-view section.")
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
        row["recon peak MB (main)"] = run.totals["recon_peak_mb"]
        row["recon peak MB (worker)"] = run.totals["recon_worker_peak_mb"]
        row["build peak MB (main)"] = run.totals["build_main_peak_mb"]
        row["build peak MB (worker)"] = run.totals["build_worker_peak_mb"]
        report.add("Scaling", row)
    report.notes["Scaling"] = ("Time per metre relative to the 1× street (1.0 = linear) and peak memory per "
                               "stage; plot: scaling.png.")
    if first.fit.get("enabled"):
        for it in first.fit["iterations"]:
            report.add("Fit", {"iteration": it["iteration"], "worker s": it["worker_s"],
                               "training pixels RMS": it["rms"], "training pixels PSNR dB": it["psnr_db"]})
        report.notes["Fit"] = ("The 1× build's fit (billboards.fit): the training pixels' error in the fit's own "
                               "rendering of the stored model (the transients left out) before the first iteration "
                               "and after each, against the worker CPU seconds "
                               "spent by then (summed over the tasks, set-up included); plot: fit.png. The rendered "
                               "ceiling and held-out views are in the novel-view section.")
        _fit_plot(first.fit, out / "fit.png")
    _scaling_plot([r for _, r in runs], out / "scaling.png")
    return first


def _fit_plot(fit: dict, path: Path) -> None:
    """Training-pixel PSNR against worker seconds, one point per iteration of the fit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from core.fileio import write_bytes

    its = fit["iterations"]
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot([i["worker_s"] for i in its], [i["psnr_db"] for i in its], "o-")
    ax.set(xlabel="worker CPU seconds", ylabel="training pixels PSNR (dB)", title="fit: error against time")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    write_bytes(path, buf.getvalue())


def _scaling_plot(runs: list[PipelineRun], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from core.fileio import write_bytes

    lengths = [r.length for r in runs]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 4))
    for stage in ("synthesis", "reconstruction (total)", "billboard build (total)"):
        ax_t.plot(lengths, [{x["stage"]: x for x in r.rows}[stage]["wall s"] for r in runs], "o-",
                  label=stage.replace(" (total)", ""))
    ax_t.plot(lengths, np.array(lengths) / lengths[0] * {x["stage"]: x for x in runs[0].rows}["synthesis"]["wall s"],
              "k:", label="linear from 1×")
    ax_t.set(xlabel="street length (m)", ylabel="wall time (s)", title="time per stage")
    ax_t.legend()
    for key, label in (("recon_peak_mb", "reconstruction, main"), ("recon_worker_peak_mb", "reconstruction, worker"),
                       ("build_main_peak_mb", "build, main"), ("build_worker_peak_mb", "build, largest worker")):
        ax_m.plot(lengths, [r.totals[key] for r in runs], "o-", label=label)
    ax_m.set(xlabel="street length (m)", ylabel="peak memory (MB)", title="peak memory", ylim=(0, None))
    ax_m.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    write_bytes(path, buf.getvalue())
