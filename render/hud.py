"""The viewer's on-screen heads-up display: lines of text over the frame's top-left corner.

Text is rasterised with OpenCV (``cv2.putText``) into an RGBA8 image on a translucent
dark band, uploaded only when it changes, and blended over the frame with one quad
(``hud.glsl``); depth test off, so it is always on top.
"""

from __future__ import annotations

import cv2
import moderngl
import numpy as np

from .screen_pass import ScreenPass

LINE_PX = 20  # text line height in pixels
FONT = cv2.FONT_HERSHEY_SIMPLEX
FONT_SCALE = 0.5


def text_image(lines: list[str], width: int | None = None) -> np.ndarray:
    """(h, w, 4) uint8 RGBA: white text lines on a translucent black band, row 0 at the top."""
    lines = [str(line) for line in lines] or [""]
    if width is None:
        width = max(cv2.getTextSize(line, FONT, FONT_SCALE, 1)[0][0] for line in lines) + 12
    image = np.zeros((LINE_PX * len(lines) + 6, max(int(width), 1), 4), np.uint8)
    image[..., 3] = 150
    for i, line in enumerate(lines):
        cv2.putText(image, line, (6, LINE_PX * (i + 1) - 4), FONT, FONT_SCALE, (255, 255, 255, 255), 1, cv2.LINE_AA)
    return image


class HudOverlay(ScreenPass):
    """Draws text lines over the bound framebuffer; :meth:`release` is idempotent."""

    def __init__(self, ctx: moderngl.Context):
        self._lines: list[str] | None = None
        super().__init__(ctx, "hud.glsl")

    def _upload(self, lines: list[str]) -> None:
        image = text_image(lines)  # row 0 at the top: the quad maps v = 0 to its top edge
        h, w = image.shape[:2]
        self.texture_of_size((w, h), 4).write(image.tobytes())
        self._lines = list(lines)

    def draw(self, lines: list[str], viewport_size) -> None:
        """Blend ``lines`` over the top-left corner of the bound framebuffer of ``viewport_size`` (w, h)."""
        if self.released:
            raise RuntimeError("HudOverlay used after release()")
        if lines != self._lines:
            self._upload(lines)
        w, h = viewport_size
        tw, th = self.texture.size
        x1, y0 = -1.0 + 2.0 * min(tw, w) / w, 1.0 - 2.0 * min(th, h) / h
        self.program["u_rect"].value = (-1.0, y0, x1, 1.0)
        self.program["u_text"].value = 0
        self.texture.use(0)
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        try:
            self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4)
        finally:
            self.ctx.disable(moderngl.BLEND)
