"""Axis-aligned boxes as a flat-coloured scene: the occluders and occludees of the occlusion
culling tests (the shader's BOXES program in render/shaders/occlusion_box.glsl)."""

from __future__ import annotations

import moderngl
import numpy as np

from render.culling import ranges_to_indices
from render.occlusion import SHADER
from render.program import load_program


class BoxRenderer:
    """Axis-aligned boxes drawn as flat-coloured, depth-tested solids (one instanced draw).

    box_min, box_max: (n, 3) model coordinates; colours: (n, 3) uint8, by default
    :meth:`id_colours` so that an image read back names the box at each pixel.
    The occluder/occludee scene of the occlusion culling tests.
    """

    def __init__(self, ctx: moderngl.Context, box_min, box_max, colours=None):
        lo = np.asarray(box_min, dtype=np.float32).reshape(-1, 3)
        hi = np.asarray(box_max, dtype=np.float32).reshape(-1, 3)
        if lo.shape != hi.shape:
            raise ValueError(f"box_min {lo.shape} and box_max {hi.shape} differ")
        n = len(lo)
        colours = self.id_colours(n) if colours is None else np.asarray(colours, dtype=np.uint8).reshape(n, 3)
        self.ctx = ctx
        self.n = n
        self._data = np.ascontiguousarray(np.concatenate([lo, hi, colours / np.float32(255)], axis=1),
                                          dtype=np.float32)
        self._released = False
        self._program = load_program(ctx, SHADER, {"BOXES": 1})
        self._buffer = ctx.buffer(reserve=max(n, 1) * 9 * 4)
        self._vao = ctx.vertex_array(self._program, [(self._buffer, "3f 3f 3f/i", "in_min", "in_max", "in_colour")])

    @staticmethod
    def id_colours(n: int) -> np.ndarray:
        """(n, 3) uint8 colours that encode id + 1 in 24 bits (black = background)."""
        v = np.arange(1, n + 1, dtype=np.int64)
        return np.stack([v & 255, (v >> 8) & 255, (v >> 16) & 255], axis=1).astype(np.uint8)

    @staticmethod
    def decode_ids(image: np.ndarray) -> np.ndarray:
        """Box id at each pixel of an (h, w, 3) uint8 image drawn with :meth:`id_colours` → (h, w) int64, −1 = none."""
        im = np.asarray(image).astype(np.int64)
        return (im[..., 0] | (im[..., 1] << 8) | (im[..., 2] << 16)) - 1

    def draw(self, view_proj, indices=None) -> None:
        """Draw the boxes with the given indices (None: all) with ``view_proj`` (4, 4) row-major."""
        if self._released:
            raise RuntimeError("BoxRenderer used after release()")
        idx = np.arange(self.n) if indices is None else np.asarray(indices, dtype=np.int64).reshape(-1)
        if len(idx) == 0:
            return
        self._buffer.write(self._data[idx].tobytes())
        self._program["u_view_proj"].write(np.ascontiguousarray(np.asarray(view_proj, np.float32).T).tobytes())
        self._vao.render(moderngl.TRIANGLES, vertices=36, instances=len(idx))

    def draw_ranges(self, view_proj, ranges) -> None:
        """Draw the boxes in [begin, end) ranges (r, 2) — the shape of a ``draw_callback`` argument."""
        self.draw(view_proj, ranges_to_indices(ranges))

    def release(self) -> None:
        """Free the program, buffer and vertex array (idempotent)."""
        if self._released:
            return
        self._released = True
        self._vao.release()
        self._buffer.release()
        self._program.release()

    def __enter__(self) -> BoxRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()
