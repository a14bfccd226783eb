"""Offscreen render targets shared by the renderers: one framebuffer per image size.

Each target is an RGBA8 colour and a 24-bit depth renderbuffer, no MSAA, created on
first use; :meth:`OffscreenTargets.begin` binds and clears one, :meth:`read` returns
its colour as an image with row 0 at the top.
"""

from __future__ import annotations

import moderngl
import numpy as np

from core.errors import InputError

from .resources import release_all


def background_rgb(colour) -> tuple[float, float, float]:
    """An RGB background in [0, 1] from a triple in [0, 1] or 0–255 (values above 1 mean 0–255)."""
    c = np.asarray(colour, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise InputError(f"background must be an RGB triple, got {colour!r}")
    if c.max() > 1:  # given as 0..255
        c = c / 255
    return tuple(float(v) for v in np.clip(c, 0, 1))


class OffscreenTargets:
    """Framebuffers by size (w, h); :meth:`release` is idempotent."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._targets: dict[tuple[int, int], moderngl.Framebuffer] = {}

    def framebuffer(self, size) -> moderngl.Framebuffer:
        """The framebuffer for ``size`` = (w, h), created on first use."""
        size = (int(size[0]), int(size[1]))
        fbo = self._targets.get(size)
        if fbo is None:
            fbo = self._targets[size] = self.ctx.framebuffer(
                color_attachments=[self.ctx.renderbuffer(size, 4, samples=0)],
                depth_attachment=self.ctx.depth_renderbuffer(size, samples=0))
        return fbo

    def begin(self, size, background) -> moderngl.Framebuffer:
        """Bind the framebuffer for ``size`` with a full viewport, cleared to ``background`` and depth 1."""
        fbo = self.framebuffer(size)
        fbo.use()
        fbo.viewport = (0, 0, *fbo.size)
        fbo.clear(*background, 1.0, depth=1.0)
        return fbo

    def read(self, size) -> np.ndarray:
        """(h, w, 3) uint8 colour of the framebuffer for ``size``, row 0 at the top."""
        fbo = self.framebuffer(size)
        w, h = fbo.size
        return np.frombuffer(fbo.read(components=3, alignment=1), np.uint8).reshape(h, w, 3)[::-1].copy()

    def release(self) -> None:
        for fbo in self._targets.values():
            attachments = [*fbo.color_attachments, fbo.depth_attachment]
            fbo.release()
            release_all(attachments)
        self._targets = {}
