"""Work-precision sweeps: error against run time for a stage's settings.

``stereo_sweep`` runs trinocular stereo over a few frames of a dataset with
ground truth for several SGBM settings (block size, matching mode, image
scale) and reports depth error against seconds per frame, plus what the third
camera buys (each single pair against the trinocular fusion).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from data_synth import load_dataset
from data_synth.fileio import atomic_path, write_bytes, write_json

logger = logging.getLogger(__name__)


PIPELINE_SETTING = "accurate (preset, recon's default)"


def stereo_settings() -> dict:
    """Named StereoConfig variants for the sweep (from the presets)."""
    from recon.stereo import PRESETS

    base = PRESETS["accurate"]  # what `bbcity recon` uses unless told otherwise
    return {
        "fast (preset)": PRESETS["fast"],
        "default (preset)": PRESETS["default"],
        PIPELINE_SETTING: base,
        "accurate, block 5": dataclasses.replace(base, block_size=5),
        "accurate, block 9": dataclasses.replace(base, block_size=9),
        "accurate, half scale": dataclasses.replace(base, image_scale=0.5),
        "accurate, 3 paths (sgbm_3way)": dataclasses.replace(base, mode="sgbm_3way"),
        "accurate, search from 4 m": dataclasses.replace(base, min_depth=4.0),
        "accurate + WLS": dataclasses.replace(base, wls=True),
    }


def stereo_sweep(dataset_dir: Path, out_dir: Path, num_frames: int = 4) -> dict:
    """Run the sweep; write ``stereo_sweep.json``, ``stereo_sweep.md`` and ``stereo_sweep.png``."""
    from recon.rectify import rectify_rig
    from recon.trinocular import TrinocularConfig, evaluate_depth, frame_depth, fuse_depths

    ds = load_dataset(dataset_dir)
    if not ds.has_ground_truth:
        raise ValueError(f"{dataset_dir}: the stereo sweep needs a dataset with ground truth (gt/)")
    pairs = rectify_rig(ds.rig)
    wide = max(pairs.values(), key=lambda p: p.baseline)
    f, B = ds.rig.intrinsics[0][0, 0], wide.baseline
    frames = np.linspace(0, ds.num_frames - 1, min(num_frames, ds.num_frames)).round().astype(int).tolist()
    images = {fr: [ds.image(fr, c) for c in range(ds.rig.num_cameras)] for fr in frames}
    gts = {fr: ds.gt_depth(fr, 0) for fr in frames}

    rows, pair_rows = [], []
    for name, stereo in stereo_settings().items():
        cfg = TrinocularConfig(stereo=stereo)
        seconds, evals, per_pair, loose = [], [], {}, []
        for fr in frames:
            t0 = time.perf_counter()
            fd = frame_depth(images[fr], pairs, cfg)
            seconds.append(time.perf_counter() - t0)
            evals.append(evaluate_depth(fd.depth, gts[fr], f, B))
            for key, depth in fd.pair_depth.items():
                per_pair.setdefault(key, []).append(evaluate_depth(depth, gts[fr], f, B))
            keys = list(fd.pair_depth)
            two, _, _ = fuse_depths(np.stack([fd.pair_depth[k] for k in keys]),
                                    [pairs[k].focal_baseline for k in keys], dataclasses.replace(cfg, min_agree=2))
            loose.append(evaluate_depth(two, gts[fr], f, B))
        row = {"setting": name, "seconds_per_frame": float(np.median(seconds)),
               **{k: float(np.nanmean([e[k] for e in evals])) for k in evals[0]}}
        rows.append(row)
        logger.info("stereo sweep %s: %s", name, row)
        if name == PIPELINE_SETTING:
            for key, ev in per_pair.items():
                pair_rows.append({"depth from": f"pair {key[0]}-{key[1]} only",
                                  **{k: float(np.nanmean([e[k] for e in ev])) for k in ev[0]}})
            pair_rows.append({"depth from": "trinocular, 2 of 3 pairs agree",
                              **{k: float(np.nanmean([e[k] for e in loose])) for k in loose[0]}})
            pair_rows.append({"depth from": f"trinocular, {cfg.min_agree} of 3 pairs agree (recon's default)",
                              **{k: v for k, v in row.items() if k not in ("setting", "seconds_per_frame")}})

    result = {"dataset": str(dataset_dir), "frames": frames, "focal_px": f, "wide_baseline_m": B,
              "settings": {k: dataclasses.asdict(v) for k, v in stereo_settings().items()},
              "sweep": rows, "pairs_vs_trinocular": pair_rows}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "stereo_sweep.json", result)
    write_bytes(out_dir / "stereo_sweep.md", _markdown(rows, pair_rows).encode())
    _plot(rows, out_dir / "stereo_sweep.png")
    return result


def _markdown(rows: list[dict], pair_rows: list[dict]) -> str:
    def table(rs):
        keys = list(dict.fromkeys(k for r in rs for k in r))
        lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
        lines += ["| " + " | ".join(f"{r[k]:.4g}" if isinstance(r.get(k), float) else str(r.get(k, ""))
                                    for k in keys) + " |" for r in rs]
        return "\n".join(lines)

    return ("# Stereo: error against run time\n\n" + table(rows)
            + "\n\n# What the third camera buys (default settings)\n\n" + table(pair_rows) + "\n")


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    key = "median_abs_error_m" if "median_abs_error_m" in rows[0] else next(k for k in rows[0] if "error" in k)
    for r in rows:
        ax.scatter(r["seconds_per_frame"], r[key])
        ax.annotate(r["setting"], (r["seconds_per_frame"], r[key]), fontsize=7)
    ax.set_xlabel("seconds per frame (3 pairs)")
    ax.set_ylabel(key.replace("_", " "))
    ax.set_title("Trinocular stereo: work-precision")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
