"""A pass drawn over the screen by a shader that makes its own vertices, sampling one texture.

:class:`ScreenPass` owns the program, a vertex array without buffers and the texture, which
:meth:`ScreenPass.texture_of_size` replaces when its size changes; the sky
(:class:`~render.sky.SkyPass`) and the heads-up display (:class:`~render.hud.HudOverlay`) are
such passes.
"""

from __future__ import annotations

import moderngl

from .program import load_program
from .resources import GpuOwner


class ScreenPass(GpuOwner):
    """The program of ``shader`` with a vertex array without buffers, and ``texture`` (None until
    :meth:`texture_of_size`); :meth:`release` frees them (idempotent)."""

    def __init__(self, ctx: moderngl.Context, shader: str):
        self.ctx = ctx
        self.texture: moderngl.Texture | None = None
        self._objects: list | None = []
        try:
            self.program = self._keep(load_program(ctx, shader))
            self.vao = self._keep(ctx.vertex_array(self.program, []))
        except BaseException:
            self.release()
            raise

    def texture_of_size(self, size: tuple[int, int], components: int, dtype: str = "f1") -> moderngl.Texture:
        """``texture``, made anew (nearest filtering) when it is not ``size`` (w, h) texels."""
        if self.texture is None or self.texture.size != size:
            if self.texture is not None:
                self.texture.release()
                self.texture = None
            self.texture = self.ctx.texture(size, components, dtype=dtype)
            self.texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return self.texture

    def release(self) -> None:
        """Free the program, vertex array and texture (idempotent)."""
        if self.released:
            return
        if self.texture is not None:
            self.texture.release()
            self.texture = None
        super().release()
