"""The report of ``bbcity eval``: eval.json, eval.md (a table per view kind, the work-precision
table) and workprecision.png (bytes against seen-pixel PSNR), from :func:`render.evaluate.evaluate_views`'s
report."""

from __future__ import annotations

import io
import math
import os
from pathlib import Path

import numpy as np

from core.fileio import write_bytes, write_json

from .eval_config import WHERE


def work_precision_plot(report: dict, path: os.PathLike | str, title: str = "Novel views: bytes against quality") -> Path:
    """Write the work-precision diagram of ``report["work_precision"]``: bytes (log) against
    seen-pixel PSNR, on path and off path side by side, one series per family (Poisson
    depths joined by a line, each point labelled)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    points = [p for p in report.get("work_precision", []) if p.get("bytes")]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    markers = {"model": "o", "Poisson mesh": "s", "point projection": "^"}
    for ax, where in zip(axes, WHERE):
        key = f"psnr_seen_{where.replace(' ', '_')}"
        families = dict.fromkeys(p["family"] for p in points)
        for i, family in enumerate(families):
            sel = sorted((p for p in points if p["family"] == family and p.get(key) is not None
                          and np.isfinite(p[key])), key=lambda p: p["bytes"])
            if not sel:
                continue
            x, y = [p["bytes"] / 1e6 for p in sel], [p[key] for p in sel]
            style = "-" if family == "Poisson mesh" and len(sel) > 1 else ""
            ax.plot(x, y, style + markers.get(family, "D"), color=f"C{i}", label=family)
            for p, xi, yi in zip(sel, x, y):
                if p["label"] != family:
                    ax.annotate(p["label"], (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set(xlabel="bytes (MB)", title=where)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("PSNR over seen pixels (dB)")
    for ax in axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
            break
    fig.suptitle(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return write_bytes(path, buf.getvalue())


def _f(value, spec: str) -> str:
    return "n/a" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, spec)


def _rows(summary: dict, columns: tuple[tuple[str, str], ...], held_out: bool = False,
          nbytes: dict | None = None) -> list[str]:
    """A Markdown table row per "method, viewpoints" of ``summary``: the name (", on path" as
    ", held out" when ``held_out``), each of ``columns`` (metric, format spec; n/a when missing or
    not finite) and, with ``nbytes`` (method → bytes), the method's bytes."""
    lines = []
    for name, m in summary.items():
        cells = [name.replace(", on path", ", held out") if held_out else name]
        cells += [_f(m.get(key), spec) for key, spec in columns]
        if nbytes is not None:
            cells.append(_f(nbytes.get(name.rsplit(", ", 1)[0]), ","))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def markdown_real(report: dict) -> str:
    """The report of a real capture as Markdown: scores over covered pixels, coverage of the
    pixels below the horizon, whole-image scores."""
    kind = "held-out" if report.get("held_out") else "capture (used for the textures; build with --holdout)"
    training = len(report.get("training_frames") or [])
    lines = [f"# Novel views of a real capture ({report['views']} {kind} frames"
             + (f" and {training} training frames" if training else "") + "; "
             f"{report['size'][0]}×{report['size'][1]}, {report['texture_frames']} frames made the textures)", "",
             "Each method's render at a held-out frame's pose against that frame's image (rows 'training': at "
             "frames the textures came from, the ceiling). Covered pixels: those the "
             "method draws. Coverage: the share of the pixels below the horizon (rays pointing down) drawn. "
             + ("The model is drawn over its sky; the baselines' background is black." if report.get("sky")
                else "Backgrounds are black."), "",
             "Exposure matched: the render times the per-channel gain that best fits the real image over the "
             "covered pixels (the held-out frame's own exposure and white balance).", "",
             "| method, frames | PSNR covered (dB) | exposure matched (dB) | SSIM covered | coverage below horizon | "
             "PSNR below horizon (dB) | PSNR image (dB) | SSIM image | bytes |",
             "|---|---|---|---|---|---|---|---|---|"]
    lines += _rows(report["summary"], (("psnr_covered", ".2f"), ("psnr_covered_exposure", ".2f"),
                                       ("ssim_covered", ".3f"), ("coverage_seen", ".1%"), ("psnr_seen", ".2f"),
                                       ("psnr", ".2f"), ("ssim", ".3f")), held_out=True, nbytes=report["bytes"])
    lines += ["", "## Above and below the horizon (PSNR over covered pixels, dB)", "",
              "| method, frames | above the horizon | below the horizon |", "|---|---|---|"]
    lines += _rows(report["summary"], (("psnr_covered_above", ".2f"), ("psnr_covered_below", ".2f")), held_out=True)
    if report.get("images"):
        panels = " | ".join(report.get("image_panels", ["real", "model", "Poisson mesh"]))
        lines += ["", f"Images ({panels}): " + ", ".join(report["images"])]
    return "\n".join(lines) + "\n"


def markdown(report: dict) -> str:
    """The report as Markdown: the scores per method and viewpoints, the work-precision points."""
    if report.get("real"):
        return markdown_real(report)
    kind = "held-out" if report.get("held_out") else "capture (used for the textures)"
    cfg = report.get("config", {})
    training = len(report.get("training_frames") or [])
    lines = [f"# Novel views against ground truth ({report['views']} {kind} viewpoints, each also moved "
             f"{cfg.get('sideways', 2.0):g} m sideways and {cfg.get('up', 1.0):g} m up"
             + (f"; {training} training viewpoints, frames the textures came from: the ceiling" if training else "")
             + f"; {report['size'][0]}×{report['size'][1]})", "",
             "Seen pixels: the ground-truth surface was seen by a capture camera whose images made the "
             "textures (depth agreeing within 2 cm + 1 %). Geometry pixels: the ground truth hits a surface. "
             + ("The model is drawn over its sky; the baselines' background is black." if report.get("sky")
                else "Backgrounds are black."), "",
             "| method, viewpoints | PSNR seen (dB) | SSIM seen | PSNR (dB) | SSIM | PSNR geometry (dB) | "
             "SSIM geometry | seen pixels | seen pixels drawn | bytes |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += _rows(report["summary"], (("psnr_seen", ".2f"), ("ssim_seen", ".3f"), ("psnr", ".2f"), ("ssim", ".3f"),
                                       ("psnr_geometry", ".2f"), ("ssim_geometry", ".3f"), ("seen_fraction", ".0%"),
                                       ("coverage_seen", ".1%")), nbytes=report["bytes"])
    split = {name: m for name, m in report["summary"].items()
             if any(m.get(f"psnr_seen_{k}") is not None for k in ("facade", "ground", "billboard", "plane"))}
    if split:
        lines += ["", "## The model's error by the kind of quad drawing a pixel (PSNR over seen pixels, dB)", "",
                  "Synthesised ground: blocks no camera of the capture saw, textured from ground nearby; "
                  "PSNR over the pixels with geometry it draws, and their share.", "",
                  "| method, viewpoints | facade blocks | ground blocks | billboards | planes | synthesised ground | "
                  "its share |", "|---|---|---|---|---|---|---|"]
        lines += _rows(split, (("psnr_seen_facade", ".2f"), ("psnr_seen_ground", ".2f"), ("psnr_seen_billboard", ".2f"),
                               ("psnr_seen_plane", ".2f"), ("psnr_geometry_synthesised", ".2f"),
                               ("synthesised_fraction", ".1%")))
    near = {name: m["psnr_seen_near"] for name, m in report["summary"].items()
            if isinstance(m.get("psnr_seen_near"), float) and math.isfinite(m["psnr_seen_near"])}
    if near:
        lines += ["", f"## The near field: seen pixels nearer than {report.get('config', {}).get('near', 5.0):g} m "
                  "(PSNR, dB)", "", "| method, viewpoints | PSNR |", "|---|---|"]
        lines += [f"| {name} | {value:.2f} |" for name, value in near.items()]
    wp = report.get("work_precision", [])
    if wp:
        lines += ["", "## Work-precision (workprecision.png)", "",
                  "| method | bytes | PSNR seen, on path (dB) | PSNR seen, off path (dB) | build (s) |",
                  "|---|---|---|---|---|"]
        for p in sorted(wp, key=lambda p: (p["family"], p["bytes"] or 0)):
            build = report.get("methods", {}).get(p["method"], {}).get("build_s")
            lines.append(f"| {p['method']} | {_f(p['bytes'], ',')} | {_f(p['psnr_seen_on_path'], '.2f')} | "
                         f"{_f(p['psnr_seen_off_path'], '.2f')} | {_f(build, '.1f')} |")
    if report.get("images"):
        panels = " | ".join(report.get("image_panels", ["ground truth", "model", "Poisson mesh"]))
        lines += ["", f"Images ({panels}): " + ", ".join(report["images"])]
    return "\n".join(lines) + "\n"


def write_report(report: dict, out_dir: os.PathLike | str) -> Path:
    """Write ``eval.json``, ``eval.md`` and ``workprecision.png`` into ``out_dir``; returns eval.md's path."""
    out = Path(out_dir)
    write_json(out / "eval.json", report)
    if report.get("work_precision"):
        work_precision_plot(report, out / "workprecision.png")
    return write_bytes(out / "eval.md", markdown(report).encode())
