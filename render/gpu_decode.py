"""GPU decode path: every billboard's eigen-texture decoded in the fragment shader.

One instanced draw call per batch (``billboard.glsl``): triangle strips of 4
vertices, one instance per billboard. With ``visible=None`` the static instance
buffer of :class:`~render.resources.ModelResources` is drawn as is; a subset is
gathered into a per-frame instance buffer (24 bytes per billboard).
"""

from __future__ import annotations

import moderngl
import numpy as np

from .camera import GLCamera, gl_bytes
from .program import load_program
from .resources import (INSTANCE_ATTRIBUTES, INSTANCE_DTYPE, INSTANCE_FORMAT, InstanceStream, ModelResources,
                        check_billboards, release_all, set_uniform, vertex_binding)


class GpuDecoder:
    """Draws a model's billboards with the decode in the shader; :meth:`release` is idempotent.

    ``resources`` is borrowed (not released here). ``spherical``: quads pitch toward
    the eye too (else they turn about the vertical axis only).
    """

    def __init__(self, ctx: moderngl.Context, resources: ModelResources, spherical: bool = False):
        self.ctx = ctx
        self.resources = resources
        self.spherical = bool(spherical)
        self.program = load_program(ctx, "billboard.glsl")
        self._objects = [self.program]
        try:
            self.stream = InstanceStream(ctx, INSTANCE_DTYPE.itemsize)
            self._objects.append(self.stream)
            self.vao_subset = ctx.vertex_array(
                self.program, [vertex_binding(self.program, self.stream.buffer, INSTANCE_FORMAT, INSTANCE_ATTRIBUTES)])
            self._objects.append(self.vao_subset)
            self.vao_all = None
            if resources.instances is not None:
                self.vao_all = ctx.vertex_array(
                    self.program, [vertex_binding(self.program, resources.instances, INSTANCE_FORMAT,
                                                  INSTANCE_ATTRIBUTES)])
                self._objects.append(self.vao_all)
        except BaseException:
            self.release()
            raise

    def draw(self, camera: GLCamera, visible=None) -> dict:
        """Draw into the bound framebuffer; returns stats {draw_calls, instances, upload_bytes}.

        visible: None (all billboards), (B,) int indices or an (n,) bool mask.
        """
        if self._objects is None:
            raise RuntimeError("GpuDecoder used after release()")
        n = self.resources.model.num_billboards
        visible = check_billboards(visible, n)
        count = n if visible is None else len(visible)
        stats = {"draw_calls": 0, "instances": count, "upload_bytes": 0}
        if count == 0:
            return stats
        if visible is None:
            vao = self.vao_all
        else:
            stats["upload_bytes"] = self.stream.write(self.resources.instance_data(visible))
            vao = self.vao_subset
        prog = self.program
        self.resources.bind(prog)
        prog["u_projection"].write(gl_bytes(camera.projection))
        prog["u_view"].write(gl_bytes(camera.view))
        set_uniform(prog, "u_eye", tuple(np.asarray(camera.eye, np.float32).tolist()))
        set_uniform(prog, "u_spherical", self.spherical)
        vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=count)
        stats["draw_calls"] = 1
        return stats

    def release(self) -> None:
        """Free the program, vertex arrays and instance stream (idempotent)."""
        release_all(self._objects)
        self._objects = None
