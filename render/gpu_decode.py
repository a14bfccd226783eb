"""GPU decode path: every billboard's eigen-texture decoded on the GPU.

Per view, a weights pass (``billboard_weights.glsl``: a full-screen triangle over two
RGBA32F textures laid out like the slot table) folds the view-dependent eigen weights
into the dequantisation constants of every slot (T_k = w_k·scale_k, and
C = Σ_k w_k·offset_k at each billboard's first slot). Each batch is then one
instanced draw (``billboard.glsl``) of triangle strips, 4 vertices and one instance
per billboard, whose fragments need two texel fetches per tile. Weighing per fragment
instead (coefficients, slot table and direction bracketing for every fragment) made
frames about 2× slower on llvmpipe. The weights are recomputed only when the eye (or
the interpolation setting) changes, and only in the rows of the weight textures that hold
the slots being drawn, so a culled frame computes little and its batches share it.

With ``visible=None`` the static instance buffer of
:class:`~render.resources.ModelResources` is drawn as is; a subset is gathered into
a per-frame instance buffer (24 bytes per billboard).
"""

from __future__ import annotations

import moderngl
import numpy as np

from .camera import GLCamera, gl_bytes
from .program import load_program
from .resources import (INSTANCE_ATTRIBUTES, INSTANCE_DTYPE, INSTANCE_FORMAT, GpuOwner, InstanceStream, ModelResources,
                        check_billboards, set_uniform, vertex_binding)


class GpuDecoder(GpuOwner):
    """Draws a model's billboards with the decode in the shader; :meth:`release` is idempotent.

    ``resources`` is borrowed (not released here). ``spherical``: quads pitch toward
    the eye too (else they turn about the vertical axis only). ``interpolate``: blend
    the sampled directions around the view (else the nearest one only); may be changed
    between draws. ``linear``: texels bilinear within each tile (else the nearest texel);
    may be changed between draws.
    """

    TERMS_UNIT, CONSTS_UNIT = 6, 7  # texture units of the weight textures (ModelResources uses 0…4)

    def __init__(self, ctx: moderngl.Context, resources: ModelResources, spherical: bool = False,
                 interpolate: bool = True, linear: bool = True):
        self.ctx = ctx
        self.linear = bool(linear)
        self.resources = resources
        self.spherical = bool(spherical)
        self.interpolate = bool(interpolate)
        self._objects = []
        self._weights_key = None  # (eye, interpolate) the weight textures were computed for ...
        try:
            self.program = self._keep(load_program(ctx, "billboard.glsl"))
            self.weights_program = self._keep(load_program(ctx, "billboard_weights.glsl"))
            self.stream = self._keep(InstanceStream(ctx, INSTANCE_DTYPE.itemsize))
            self.vao_subset = self._instanced_vao(self.stream.buffer)
            self.vao_all = None if resources.instances is None else self._instanced_vao(resources.instances)
            self.weights_vao = self._keep(ctx.vertex_array(self.weights_program, []))
            spr = resources.slots_per_row
            self.weights_size = (spr, max(-(-resources.model.num_slots // spr), 1))
            self.terms = self._keep(ctx.texture(self.weights_size, 4, dtype="f4"))
            self.consts = self._keep(ctx.texture(self.weights_size, 4, dtype="f4"))
            for tex in (self.terms, self.consts):
                tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self.weights_fbo = self._keep(ctx.framebuffer(color_attachments=[self.terms, self.consts]))
            self._rows_current = np.zeros(self.weights_size[1], bool)  # ... in these rows
        except BaseException:
            self.release()
            raise

    def _instanced_vao(self, buffer: moderngl.Buffer) -> moderngl.VertexArray:
        return self._keep(self.ctx.vertex_array(
            self.program, [vertex_binding(self.program, buffer, INSTANCE_FORMAT, INSTANCE_ATTRIBUTES)]))

    def update_weights(self, eye, billboards=None) -> int:
        """Make the view-dependent constants of the slots of ``billboards`` ((B,) int; None:
        all) current for ``eye`` (model coordinates): the weights pass runs over the rows of
        the weight textures that hold them and are not yet current. Returns the rows computed;
        restores the bound framebuffer."""
        eye = tuple(np.asarray(eye, np.float32).tolist())
        key = (eye, self.interpolate)
        if key != self._weights_key:
            self._weights_key = key
            self._rows_current[:] = False
        spr, rows = self.weights_size
        need = np.ones(rows, bool)
        if billboards is not None:
            model = self.resources.model
            first = model.first_slot[billboards].astype(np.int64)
            last = first + model.rank[billboards]
            need[:] = False
            need[first // spr] = True  # a billboard's slots may run past a row's end
            need[last // spr] = True
        todo = need & ~self._rows_current
        if not todo.any():
            return 0
        target = self.ctx.fbo
        prog = self.weights_program
        self.resources.bind(prog)
        set_uniform(prog, "u_eye", eye)
        set_uniform(prog, "u_interpolate", self.interpolate)
        self.weights_fbo.use()  # no depth attachment: the depth test passes
        edges = np.flatnonzero(np.diff(np.r_[0, todo.astype(np.int8), 0]))
        for r0, r1 in edges.reshape(-1, 2):  # runs of rows: one full-width band each
            self.ctx.viewport = (0, int(r0), spr, int(r1 - r0))
            self.weights_vao.render(moderngl.TRIANGLES, vertices=3)
        target.use()
        self._rows_current |= todo
        return int(todo.sum())

    def draw(self, camera: GLCamera, visible=None) -> dict:
        """Draw into the bound framebuffer; returns stats {draw_calls, instances, upload_bytes,
        weights_rows} (draw_calls: instanced billboard draws; weights_rows: rows of the weight
        textures the weights pass computed for this draw).

        visible: None (all billboards), (B,) int indices or an (n,) bool mask.
        """
        if self.released:
            raise RuntimeError("GpuDecoder used after release()")
        n = self.resources.model.num_billboards
        visible = check_billboards(visible, n)
        count = n if visible is None else len(visible)
        stats = {"draw_calls": 0, "instances": count, "upload_bytes": 0, "weights_rows": 0}
        if count == 0:
            return stats
        if visible is None:
            vao = self.vao_all
        else:
            stats["upload_bytes"] = self.stream.write(self.resources.instance_data(visible))
            vao = self.vao_subset
        stats["weights_rows"] = self.update_weights(camera.eye, visible)
        prog = self.program
        self.resources.bind(prog)
        self.terms.use(self.TERMS_UNIT)
        self.consts.use(self.CONSTS_UNIT)
        set_uniform(prog, "u_slot_terms", self.TERMS_UNIT)
        set_uniform(prog, "u_slot_const", self.CONSTS_UNIT)
        prog["u_projection"].write(gl_bytes(camera.projection))
        prog["u_view"].write(gl_bytes(camera.view))
        set_uniform(prog, "u_eye", tuple(np.asarray(camera.eye, np.float32).tolist()))
        set_uniform(prog, "u_spherical", self.spherical)
        set_uniform(prog, "u_linear", self.linear)
        vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=count)
        stats["draw_calls"] = 1
        return stats

    def release(self) -> None:
        """Free the programs, vertex arrays, instance stream and weight textures (idempotent)."""
        super().release()
