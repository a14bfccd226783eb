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

from capture.dataset import load_dataset
from core.errors import InputError
from core.fileio import atomic_path, write_bytes, write_json

logger = logging.getLogger(__name__)


PIPELINE_SETTING = "accurate (preset, recon's default)"

#: Frames the stereo sweep evaluates, spread along the path.
STEREO_FRAMES = 4


def stereo_settings() -> dict:
    """Named StereoConfig variants for the sweep (from the presets)."""
    from recon.stereo import PRESETS

    base = PRESETS["accurate"]  # what `bbcity recon` uses unless told otherwise
    return {
        "fast (preset)": PRESETS["fast"],
        "balanced (preset)": PRESETS["balanced"],
        PIPELINE_SETTING: base,
        "accurate, block 5": dataclasses.replace(base, block_size=5),
        "accurate, block 9": dataclasses.replace(base, block_size=9),
        "accurate, half scale": dataclasses.replace(base, image_scale=0.5),
        "accurate, 3 paths (sgbm_3way)": dataclasses.replace(base, mode="sgbm_3way"),
        "accurate, search from 4 m": dataclasses.replace(base, min_depth=4.0),
        "accurate + WLS": dataclasses.replace(base, wls=True),
    }


def stereo_sweep(dataset_dir: Path, out_dir: Path, num_frames: int = STEREO_FRAMES) -> dict:
    """Run the sweep; write ``stereo_sweep.json``, ``stereo_sweep.md`` and ``stereo_sweep.png``."""
    from recon.rectify import rectify_rig
    from recon.trinocular import TrinocularConfig, evaluate_depth, frame_depth, fuse_depths

    ds = load_dataset(dataset_dir)
    if not ds.has_gt_depth:
        raise InputError(f"{dataset_dir}: the stereo sweep needs a dataset with per-image ground-truth depth "
                         "(gt/depth and gt/ids)")
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


# --------------------------------------------------------------------------- textures

#: Billboards the texture sweep samples, and the texel sizes it compares (the build's is always among them).
TEXTURE_COUNT = 1024
TEXTURE_TILES = (8, 16, 32)


def texture_settings() -> dict:
    """Named PcaConfig variants: fixed ranks, contribution ratios and error bounds."""
    from billboards.pca import PcaConfig

    base = PcaConfig()
    settings = {f"rank {r}": dataclasses.replace(base, fixed_rank=r, max_rank=max(r, 1)) for r in (0, 1, 2, 4, 8, 16)}
    for ratio in (0.8, 0.9, 0.95, 0.99):
        settings[f"ratio {ratio}"] = dataclasses.replace(base, ratio=ratio, max_error=None)
    for bound in (1.0, 2.0, 4.0):
        settings[f"error ≤ {bound:g}"] = dataclasses.replace(base, ratio=None, max_error=bound)
    settings["default (build's)"] = base
    return settings


def _chunk_bytes(arrays: dict) -> int:
    """Bytes a chunk adds to the model: tiles, coefficient rows, their scales, per-billboard tables."""
    per_billboard = 3 * 4 + 4 + 1 + 4  # centre, base yaw, rank, first slot
    return int(sum(arrays[k].nbytes for k in ("tiles", "slot_scale", "slot_offset", "coef_rows", "coef_scale",
                                              "coef_offset")) + per_billboard * len(arrays["rank"]))


def texture_sweep(cloud_path: Path, dataset_dir: Path | None, out_dir: Path, count: int = TEXTURE_COUNT,
                  tiles: tuple[int, ...] = TEXTURE_TILES, source: str = "images") -> dict:
    """Bytes, decode PSNR and build time over PCA rank rules, texel sizes and quantisation.

    Samples ``count`` neighbouring billboards from the middle of the street once per
    texel size, then compresses the same samples under every setting (the rank rules and
    quantisation modes at the build's texel size, which is always swept; the build's
    defaults at the other sizes). Writes ``texture_sweep.json``, ``texture_sweep.md``
    and ``texture_sweep.png``.
    """
    from billboards.build_config import BuildConfig
    from billboards.compress import compress_chunk
    from billboards.octree import build_octree
    from billboards.placement import place_billboards
    from billboards.views import views_from_dataset
    from recon.cloud_io import read_cloud_arrays

    base = BuildConfig(error_stride=1)
    tiles = tuple(sorted(set(int(t) for t in tiles) | {base.sampling.tile}))
    points, colours = read_cloud_arrays(cloud_path)
    octree = build_octree(points, base.octree)
    views = views_from_dataset(load_dataset(dataset_dir)) if dataset_dir is not None else None
    placed = place_billboards(points, octree, views.centres if views is not None else None)
    first = max(0, octree.num_voxels // 2 - count // 2)
    ids = np.arange(first, min(octree.num_voxels, first + count))
    rows = []

    def run(label: str, rgba: np.ndarray, sample_s: float, conf) -> None:
        t0 = time.perf_counter()
        parts = [compress_chunk(rgba[s:s + conf.chunk], conf) for s in range(0, len(rgba), conf.chunk)]
        compress_s = time.perf_counter() - t0
        sq = sum(p[1]["sq_err_decoded_rgb"] for p in parts)
        n = sum(p[1]["opaque_rgb_values"] for p in parts)
        sq_all = sum(p[1]["sq_err_decoded"] for p in parts)
        n_all = sum(p[1]["values"] for p in parts)  # error_stride 1 below: every billboard
        ranks = np.concatenate([p[0]["rank"] for p in parts]).astype(float)
        model_bytes = sum(_chunk_bytes(p[0]) for p in parts)
        rows.append({"setting": label, "tile": int(rgba.shape[2]), "tile_mode": conf.tile_mode,
                     "coef_mode": conf.coef_mode, "mean_rank": float(ranks.mean()),
                     "fetches_per_texel": float(1 + ranks.mean()),
                     "bytes_per_billboard": model_bytes / len(rgba),
                     "compression": rgba.nbytes / model_bytes,
                     "psnr_rgb_db": float(10 * np.log10(n / sq)) if sq > 0 else 100.0,
                     "psnr_rgba_db": float(10 * np.log10(n_all / sq_all)) if sq_all > 0 else 100.0,
                     "sample_ms_per_billboard": 1e3 * sample_s / len(rgba),
                     "compress_ms_per_billboard": 1e3 * compress_s / len(rgba)})
        logger.info("texture sweep %s: %s", label, rows[-1])

    for tile in tiles:
        sampling = dataclasses.replace(base.sampling, tile=tile)
        sampler = (placed.image_sampler(views, sampling) if source == "images"
                   else placed.point_sampler(colours, sampling))
        t0 = time.perf_counter()
        rgba = np.concatenate([sampler.sample(ids[s:s + base.chunk]).rgba for s in range(0, len(ids), base.chunk)])
        sample_s = time.perf_counter() - t0
        if tile == base.sampling.tile:
            for name, pca in texture_settings().items():
                run(name, rgba, sample_s, dataclasses.replace(base, pca=pca))
            for tile_mode in ("u8", "f16"):
                for coef_mode in ("f32", "f16", "u8"):
                    if (tile_mode, coef_mode) != (base.tile_mode, base.coef_mode):
                        run(f"default, {tile_mode} tiles, {coef_mode} coefficients", rgba, sample_s,
                            dataclasses.replace(base, tile_mode=tile_mode, coef_mode=coef_mode))
        else:
            run(f"default, {tile}×{tile} texels", rgba, sample_s, base)
        del rgba

    result = {"cloud": str(cloud_path), "dataset": None if dataset_dir is None else str(dataset_dir),
              "billboards": int(len(ids)), "voxel_size": octree.voxel_size,
              "directions": base.sampling.directions.num_directions, "sweep": rows}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "texture_sweep.json", result)
    write_bytes(out_dir / "texture_sweep.md", _texture_markdown(result).encode())
    _texture_plot(rows, out_dir / "texture_sweep.png")
    return result


def _texture_markdown(result: dict) -> str:
    keys = ["setting", "tile", "tile_mode", "coef_mode", "mean_rank", "bytes_per_billboard", "compression",
            "psnr_rgb_db", "psnr_rgba_db", "compress_ms_per_billboard", "sample_ms_per_billboard"]
    lines = [f"# Textures: bytes and decode PSNR against build time ({result['billboards']} billboards, "
             f"{result['directions']} directions, raw = 8-bit RGBA samples)", "",
             "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in result["sweep"]:
        lines.append("| " + " | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k]) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def _texture_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), dpi=120)
    for r in rows:
        for ax, x in zip(axes, ("bytes_per_billboard", "compress_ms_per_billboard")):
            ax.scatter(r[x], r["psnr_rgb_db"])
            ax.annotate(r["setting"], (r[x], r["psnr_rgb_db"]), fontsize=6)
    axes[0].set_xscale("log")
    axes[0].set_xlabel("model bytes per billboard")
    axes[1].set_xlabel("PCA + quantisation, ms per billboard")
    for ax in axes:
        ax.set_ylabel("decode PSNR, RGB of opaque texels (dB)")
        ax.grid(True, alpha=0.3)
    fig.suptitle("Eigen-textures: work-precision")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
