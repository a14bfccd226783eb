"""The sky pass: a model's :class:`billboards.sky.Sky` drawn behind its billboards.

:class:`SkyPass` uploads the sky's bins once (an RGBA32F texture of ``bins`` × 1 texels)
and draws one full-screen triangle (``sky.glsl``) with the depth test off, so it writes
no depth and the billboards drawn after it (and the occlusion culler's depth) see a
cleared depth buffer. Each pixel takes the colour of its view ray's world elevation,
linear between bin centres (:meth:`Sky.colour <billboards.sky.Sky.colour>` is the
numpy reference). :func:`render_over_sky` renders one image with a
:class:`~render.renderer.BillboardRenderer` over the sky.
"""

from __future__ import annotations

import moderngl
import numpy as np

from billboards.sky import Sky

from .camera import check_intrinsics, check_pose
from .screen_pass import ScreenPass


class SkyPass(ScreenPass):
    """Draws ``sky`` into the bound framebuffer; :meth:`release` is idempotent."""

    def __init__(self, ctx: moderngl.Context, sky: Sky):
        self.sky: Sky | None = None
        super().__init__(ctx, "sky.glsl")
        try:
            self.set_sky(sky)
        except BaseException:
            self.release()
            raise

    def set_sky(self, sky: Sky) -> None:
        """Use ``sky`` from the next :meth:`draw` on (uploads its bins when it is another sky)."""
        if self.released:
            raise RuntimeError("SkyPass used after release()")
        if sky is self.sky:
            return
        rgba = np.ones((sky.bins, 4), np.float32)
        rgba[:, :3] = sky.colours
        self.texture_of_size((sky.bins, 1), 4, dtype="f4").write(rgba.tobytes())
        self.sky = sky

    def draw(self, K, world_from_cam, size) -> None:
        """Fill the bound framebuffer's viewport of ``size`` = (w, h) with the sky seen by the
        OpenCV camera K (3, 3), world_from_cam (4, 4) float64. Leaves depth test, blending
        and face culling off (the billboard renderer enables what it needs)."""
        if self.released:
            raise RuntimeError("SkyPass used after release()")
        K = check_intrinsics(K)
        R = check_pose(world_from_cam)[:3, :3]
        world_from_pixel = (R @ np.linalg.inv(K)).astype(np.float32)
        p = self.program
        p["u_world_from_pixel"].write(world_from_pixel.T.tobytes())  # GLSL matrices are column-major
        p["u_height"].value = float(size[1])
        p["u_elevation"].value = tuple(float(v) for v in np.deg2rad(self.sky.elevation_deg))
        p["u_bins"].value = int(self.sky.bins)
        p["u_sky"].value = 0
        self.texture.use(0)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
        self.vao.render(moderngl.TRIANGLES, vertices=3)


def render_over_sky(renderer, sky_pass: SkyPass | None, K, world_from_cam, size, visible=None) -> np.ndarray:
    """(h, w, 3) uint8: ``renderer`` (a :class:`~render.renderer.BillboardRenderer`) drawing its
    model from the OpenCV camera over the sky of ``sky_pass`` (None: its plain background,
    exactly ``renderer.render``). ``visible`` as for ``renderer.render``."""
    if sky_pass is None:
        return renderer.render(K, world_from_cam, size, visible)
    camera = renderer.camera(K, world_from_cam, size)
    renderer.targets.begin(camera.size, renderer.background)
    sky_pass.draw(K, world_from_cam, camera.size)
    renderer.draw(camera, visible)
    return renderer.targets.read(camera.size)
