"""A site opened in a real browser: Debian's Chromium, headless, driven by Playwright.

Chromium draws WebGL2 in software here (:data:`BROWSER_GL`), as on a machine without a GPU;
Playwright starts the system's Chromium (``executable_path``) and downloads no browser.
:func:`open_site` serves the site on a free loopback port and opens its viewer at a fixed
canvas size; :func:`page_image` reads the last frame back; :func:`browser_fps` times a walk;
:func:`browser_memory` is what the browser's processes hold.
"""

from __future__ import annotations

import base64
import contextlib
import os
import shutil
from pathlib import Path
from typing import Iterator

import numpy as np
import psutil

from core.errors import InputError

from .serve import serve_in_background

#: Software WebGL2 backends of Chromium on a machine without a GPU: Mesa's llvmpipe under ANGLE's
#: OpenGL ES backend (the rasterizer bbcity's moderngl renderer draws with), or SwiftShader under
#: ANGLE's Vulkan backend (what Chrome falls back to on a machine whose GPU it refuses).
BROWSER_GL = {"llvmpipe": ("--use-angle=gl-egl",),
              "swiftshader": ("--use-angle=swiftshader", "--enable-unsafe-swiftshader")}
READY_TIMEOUT_MS = 120_000  # the first frame of a large site in software WebGL


class BrowserError(RuntimeError):
    """No browser to drive, or the viewer failed (the message says which)."""


def chromium_path() -> str:
    """The system Chromium (``$BBCITY_CHROMIUM``, else ``chromium`` on PATH); BrowserError if none."""
    path = os.environ.get("BBCITY_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not path:
        raise BrowserError("no Chromium: install Debian's chromium package (make test does), or set BBCITY_CHROMIUM")
    return path


@contextlib.contextmanager
def open_site(site: Path, size=(1280, 720), view=None, query: str = "", gl: str = "llvmpipe") -> Iterator:
    """A Playwright page showing ``site``'s viewer at canvas ``size`` (w, h), from ``view``
    (x, y, z, yaw°, pitch°[, fov°]; None: the site's start), after its first frame, drawn with
    the software WebGL2 of ``gl`` (:data:`BROWSER_GL`). ``query``: more URL parameters
    (``&filter=nearest``). The page's ``first_frame_ms`` attribute is the first frame's time
    from navigation start."""
    if gl not in BROWSER_GL:
        raise InputError(f"gl must be one of {list(BROWSER_GL)}, got {gl!r}")
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    server, url = serve_in_background(site)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path(),
                                        args=[*BROWSER_GL[gl], "--ignore-gpu-blocklist"])
            try:
                page = browser.new_page(viewport={"width": int(size[0]), "height": int(size[1])})
                page.set_default_timeout(READY_TIMEOUT_MS)
                fragment = "" if view is None else "#" + ",".join(f"{float(v):.6f}" for v in view)
                page.goto(f"{url}index.html?size={int(size[0])}x{int(size[1])}{query}{fragment}")
                try:
                    page.first_frame_ms = float(page.evaluate("window.bbcity.ready"))
                except PlaywrightError as e:
                    raise BrowserError(f"the viewer of {site} did not draw: {e.message.splitlines()[0]}") from None
                yield page
            finally:
                browser.close()
    finally:
        server.shutdown()
        server.server_close()


def page_image(page, size, pose=None, K=None) -> np.ndarray:
    """(h, w, 3) uint8 of the viewer's frame drawn now (row 0 at the top); from the OpenCV camera
    ``pose`` (4, 4) world_from_cam with intrinsics ``K`` (3, 3) when given (it stays until the
    next view is set)."""
    if pose is not None:
        page.evaluate("([row, K]) => window.bbcity.setCamera(row, K)", [pose_rows(pose)[0], _k(K)])
    raw = base64.b64decode(page.evaluate("window.bbcity.pixels()"))
    w, h = int(size[0]), int(size[1])
    return np.frombuffer(raw, np.uint8).reshape(h, w, 4)[::-1, :, :3].copy()


def pose_rows(poses: np.ndarray) -> list[list[float]]:
    """Poses (n, 4, 4) world_from_cam as the viewer takes them: rotation row by row, then the eye."""
    p = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    return np.concatenate([p[:, :3, :3].reshape(-1, 9), p[:, :3, 3]], 1).tolist()


def browser_fps(page, poses: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n,) float64 seconds of each frame along ``poses`` (n, 4, 4) with intrinsics ``K`` (3, 3),
    drawn and read back one by one in the page (after one untimed frame at the first pose)."""
    ms = page.evaluate("([rows, K]) => window.bbcity.benchmark(rows, K)", [pose_rows(poses), _k(K)])
    return np.asarray(ms, np.float64) / 1000.0


def _k(K) -> list[float]:
    K = np.asarray(K, np.float64)
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]


def web_walk(site: Path, poses: np.ndarray, K: np.ndarray, size, gl: str = "llvmpipe") -> dict:
    """Open ``site`` at the first of ``poses`` (n, 4, 4) and let the viewer show each in turn, its
    tiles streaming in the background as they do for a user: {first_frame_s (from page load),
    frames, ms (median between frames), ms_max, peak_mb and budget_mb (the tiles' GPU bytes),
    resident, loads, releases, browser_mb (:func:`browser_memory`, at the end)}."""
    with open_site(site, size, gl=gl, view=None) as page:
        first = page.first_frame_ms
        page.evaluate("([row, K]) => window.bbcity.setCamera(row, K)", [pose_rows(poses[:1])[0], _k(K)])
        ms = np.asarray(page.evaluate("([rows, K]) => window.bbcity.walk(rows, K)", [pose_rows(poses), _k(K)]))
        stats = page.evaluate("window.bbcity.stats()")
        memory = browser_memory()
    return {"first_frame_s": first / 1000.0, "frames": len(ms), "ms": float(np.median(ms)) if len(ms) else float("nan"),
            "ms_max": float(ms.max()) if len(ms) else float("nan"), "peak_mb": stats["peakMB"],
            "budget_mb": stats["budgetMB"], "resident": stats["resident"], "loads": stats["loads"],
            "releases": stats["releases"], "browser_mb": memory / 1e6}


def browser_memory() -> int:
    """Bytes the browser processes under this one hold (proportional set size, so shared
    pages count once across them)."""
    total = 0
    for child in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            if "chrom" in child.name().lower():
                info = child.memory_full_info()
                total += getattr(info, "pss", info.rss)
    return total
