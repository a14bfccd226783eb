"""Novel-view quality of a billboard model against the ground-truth renderer (``bbcity eval``).

Viewpoints: capture viewpoints (camera 0 of frames spread along the path; the
frames the model was built without, ``bbcity build --holdout N``, when it has them) and
off-path viewpoints (the same cameras moved 2 m sideways, away from the facade
they look at, and 1 m up). Each is rendered three ways and compared with
:func:`data_synth.render_view`: the billboard model (GPU decode), and the
baseline, the fused cloud projected with Open3D's
``PointCloud.project_to_rgbd_image`` (one pixel per point, nearest wins).
PSNR and SSIM over the whole image and over the pixels where the ground truth
has geometry. Bytes: the model's (GPU) bytes and the cloud's (float32 xyz + RGB).
"""

from __future__ import annotations

import logging
import os
import time

import cv2
import numpy as np

from data_synth import load_dataset, load_scene, render_view as truth_view
from recon.cloud_io import read_cloud_arrays

from .offscreen import render_view

logger = logging.getLogger(__name__)

BACKGROUND = (0.0, 0.0, 0.0)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of uint8 images (h, w, 3) over ``mask`` (h, w) bool (all pixels if None);
    NaN without pixels, 100 for identical ones."""
    diff = a.astype(np.float64) - b.astype(np.float64)
    if mask is not None:
        diff = diff[mask]
    if diff.size == 0:
        return float("nan")
    mse = float(np.mean(diff ** 2))
    return 100.0 if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse))


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM (Wang et al. 2004: 11×11 Gaussian window, σ 1.5, K1 0.01, K2 0.03) of the
    luminance of uint8 RGB images, averaged over ``mask`` (all pixels if None)."""
    def grey(x):
        return cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float64)

    x, y = grey(a), grey(b)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(z):
        return cv2.GaussianBlur(z, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    values = s if mask is None else s[mask]
    return float(values.mean()) if values.size else float("nan")


def off_path(world_from_cam: np.ndarray, sideways: float = 2.0, up: float = 1.0) -> np.ndarray:
    """The camera moved ``sideways`` metres back along its horizontal viewing direction
    (away from what it looks at, toward the middle of the street) and ``up`` metres up."""
    pose = np.array(world_from_cam, dtype=np.float64)
    forward = pose[:3, 2].copy()
    forward[2] = 0.0
    norm = np.linalg.norm(forward)
    if norm > 1e-9:
        pose[:3, 3] -= sideways * forward / norm
    pose[2, 3] += up
    return pose


class PointProjector:
    """The baseline: a coloured cloud projected to images with Open3D (float32 points
    relative to an origin, so city coordinates keep their centimetres)."""

    def __init__(self, points: np.ndarray, colours: np.ndarray):
        import open3d as o3d

        self._o3d = o3d
        self.origin = points.mean(axis=0) if len(points) else np.zeros(3)
        self.cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor((points - self.origin).astype(np.float32)))
        self.cloud.point.colors = o3d.core.Tensor(colours.astype(np.float32) / 255.0)
        self.nbytes = len(points) * (3 * 4 + 3)

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, size) -> np.ndarray:
        """(h, w, 3) uint8: nearest point per pixel, background black."""
        o3d = self._o3d
        local = np.array(world_from_cam, dtype=np.float64)
        local[:3, 3] -= self.origin
        image = self.cloud.project_to_rgbd_image(int(size[0]), int(size[1]), o3d.core.Tensor(np.asarray(K, np.float64)),
                                                 o3d.core.Tensor(np.linalg.inv(local)), depth_scale=1.0,
                                                 depth_max=1000.0)
        colour = image.color.as_tensor().numpy()
        return np.clip(np.rint(colour * 255), 0, 255).astype(np.uint8)


def evaluate_views(model, dataset_dir: os.PathLike | str, cloud_path: os.PathLike | str | None,
                   views: int = 8, size: tuple[int, int] | None = None) -> dict:
    """PSNR/SSIM of the model (and of the point projection when a cloud is given) on
    ``views`` capture viewpoints and their off-path variants; a JSON-ready dict."""
    t0 = time.perf_counter()
    ds = load_dataset(dataset_dir)
    if not ds.has_ground_truth:
        raise ValueError(f"{dataset_dir}: evaluation needs a dataset with ground truth (gt/)")
    scene = load_scene(dataset_dir)
    K = ds.rig.intrinsics[0]
    size = tuple(ds.rig.sizes[0]) if size is None else tuple(size)
    if size != tuple(ds.rig.sizes[0]):
        scale = np.diag([size[0] / ds.rig.sizes[0][0], size[1] / ds.rig.sizes[0][1], 1.0])
        K = scale @ K
    baseline = None
    if cloud_path is not None:
        points, colours = read_cloud_arrays(cloud_path)
        baseline = PointProjector(points, colours)
        del points, colours
    held_out = [int(f) for f in (model.info or {}).get("held_out_frames", []) if 0 <= int(f) < ds.num_frames]
    pool = np.asarray(held_out) if held_out else np.arange(ds.num_frames)
    frames = np.unique(pool[np.linspace(0, len(pool) - 1, max(1, views)).round().astype(int)])
    rows = []
    for f in frames:
        for kind, pose in (("on path", ds.world_from_cam(int(f), 0)), ("off path", off_path(ds.world_from_cam(int(f), 0)))):
            truth, depth = truth_view(scene, K, pose, size)
            geometry = np.isfinite(depth)
            renders = {"billboards": render_view(model, K, pose, size, background=BACKGROUND)}
            if baseline is not None:
                renders["point projection"] = baseline.render(K, pose, size)
            for method, image in renders.items():
                rows.append({"frame": int(f), "view": kind, "method": method,
                             "psnr": psnr(image, truth), "psnr_geometry": psnr(image, truth, geometry),
                             "ssim": ssim(image, truth), "ssim_geometry": ssim(image, truth, geometry)})
    summary = {}
    for kind in ("on path", "off path"):
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["view"] == kind and r["method"] == method]
            summary[f"{method}, {kind}"] = {k: float(np.nanmean([r[k] for r in sel]))
                                            for k in ("psnr", "psnr_geometry", "ssim", "ssim_geometry")}
    return {"dataset": str(dataset_dir), "views": len(frames), "size": list(size),
            "held_out": bool(held_out), "frames": frames.tolist(),
            "bytes": {"billboards": int(model.nbytes()["total"]),
                      **({"point projection": int(baseline.nbytes)} if baseline is not None else {})},
            "summary": summary, "per_view": rows, "seconds": time.perf_counter() - t0}


def markdown(report: dict) -> str:
    """The summary as a Markdown table."""
    kind = "held-out" if report.get("held_out") else "capture (used for the textures)"
    lines = [f"# Novel views against ground truth ({report['views']} {kind} viewpoints, each also moved "
             f"2 m sideways and 1 m up; {report['size'][0]}×{report['size'][1]})", "",
             "| method, viewpoints | PSNR (dB) | PSNR on geometry (dB) | SSIM | SSIM on geometry | bytes |",
             "|---|---|---|---|---|---|"]
    for name, m in report["summary"].items():
        method = name.split(",")[0]
        lines.append(f"| {name} | {m['psnr']:.2f} | {m['psnr_geometry']:.2f} | {m['ssim']:.3f} | "
                     f"{m['ssim_geometry']:.3f} | {report['bytes'].get(method, 0):,} |")
    return "\n".join(lines) + "\n"
