"""Far octree nodes drawn as impostors: one quad with the node rendered into a texture.

Level of detail for geometry. Far from the eye a 4 m octree node holds tens of quads that
cover a few dozen pixels, and on a CPU rasterizer every quad costs vertex and triangle
setup on one thread. Such a node is drawn instead as one quad textured with an image of
its quads (a dynamic impostor, Schaufler 1995):

- **Which nodes.** The octree nodes whose edge is closest to ``ImpostorConfig.node_edge``
  whose box (tight around its quads) spans at most ``texels`` pixels on screen either way
  and lies wholly in front of the eye (with ``hysteresis`` on that size, so a node does
  not switch back and forth).
- **The image.** The node's quads drawn by the decoder with the eye's own perspective
  cropped to the box's screen rectangle, twice as fine as the node is on screen, into a
  studio (:class:`ImpostorStudio`: colour and depth, cleared transparent, shared by the tiles
  of a set), then copied into a part of the node's ``texels``² tile of an RGBA8 atlas: an
  atlas holds no depth, half the bytes it would (the depth an image is drawn with is not
  needed once it is made), so a GPU budget holds more tiles.
  The impostor quad lies on the plane through the box's centre facing the eye, cut to
  that rectangle; its fragments look the image up through the camera it was made with
  (projective texturing), so at that moment it shows what the quads would show.
- **Reuse.** The image is kept while the eye's motion moves it less than ``max_error_px`` on
  screen (the parallax of the node's depth), the direction from the node to the eye stays
  within ``max_angle_deg`` of the one it was made from (view-dependent texture) and the
  distance within 25 %: a far node's image lasts many frames of a drive, a near one's few.
  Images are made at the start of a frame (leaving the frame's framebuffer would make
  llvmpipe finish it), for nodes drawn far the frame before, all in one draw
  (:meth:`~render.gpu_decode.GpuDecoder.draw_views`). A far node whose image is missing or
  twice past those bounds is drawn in full, so quality never waits on the budget and no frame
  pays for every node at once; such a node costs about as much every frame as making its image
  once, so these get the larger budget, ``in_full_updates_per_frame`` (nearest first), and
  images still usable are remade within ``updates_per_frame`` (the stalest first). At the end
  of a street, turning round brings hundreds of far nodes into view whose images were made from
  the other side.

The split happens per selection of billboards (:meth:`Impostors.split`), so it works under
every culling mode: blocks of impostor nodes are replaced by their node's quad.
"""

from __future__ import annotations

import moderngl
import numpy as np

from billboards.model import BillboardModel
from billboards.model_set import model_quad_radius

from core.errors import InputError

from .camera import GLCamera, gl_bytes
from .context import max_texture_size
from .culling import ranges_to_indices
from .lod import ImpostorConfig
from .program import ProgramCache
from .resources import GpuOwner, set_uniform

#: Per-impostor record of the draw (impostor.glsl): the quad's corners (model coordinates; bottom
#: left, bottom right, top left, top right), rows 0, 1 and 3 of the matrix from model coordinates to
#: the image's clip space when it was made (projective texturing), and the image's texel origin and
#: extent in its tile (the node's size on screen then, so a thin node costs few texels).
IMPOSTOR_DTYPE = np.dtype([("corners", "<f4", (4, 3)), ("image_from_model", "<f4", (3, 4)), ("origin", "<f4", 2),
                           ("extent", "<f4", 2)])
IMPOSTOR_FORMAT = "3f 3f 3f 3f 4f 4f 4f 2f 2f/i"
IMPOSTOR_ATTRIBUTES = ("in_corner0", "in_corner1", "in_corner2", "in_corner3", "in_image_x", "in_image_y",
                       "in_image_w", "in_origin", "in_extent")

ATLAS_WIDTH = 4096  # texels per row of the impostor atlas (at most)
STUDIO_ROWS = 1  # rows of tiles of an ImpostorStudio: the images one pass makes (32 of 128² texels)

#: Per-image record of the copy from the studio into an atlas (impostor_copy.glsl).
COPY_DTYPE = np.dtype([("source", "<f4", 2), ("target", "<f4", 2), ("extent", "<f4", 2)])
COPY_FORMAT = "2f 2f 2f/i"
COPY_ATTRIBUTES = ("in_source", "in_target", "in_extent")

#: Change of distance an image survives: made twice as fine as the node is on screen, a texel
#: stays under 0.7 pixels 25 % nearer (and under-sampling 25 % farther is what the quads do).
MAX_SCALE_CHANGE = 0.25
#: An image is remade once its age (:meth:`Impostors._age`) passes 1 and drawn until it passes this.
USABLE_AGE = 2.0


def tile_origins(count: int, texels: int) -> np.ndarray:
    """(count, 2) int32 texel origins of ``count`` tiles of ``texels``² in rows of ATLAS_WIDTH."""
    per_row = max(ATLAS_WIDTH // texels, 1)
    tiles = np.arange(count)
    return np.stack([(tiles % per_row) * texels, (tiles // per_row) * texels], 1).astype(np.int32)


def atlas_size(count: int, texels: int) -> tuple[int, int]:
    """(width, height) texels of an atlas of ``count`` tiles of ``texels``² (at least one)."""
    per_row = max(ATLAS_WIDTH // texels, 1)
    return min(max(count, 1), per_row) * texels, max(-(-count // per_row), 1) * texels


def impostor_nodes(model: BillboardModel, node_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """The octree level whose edge is closest to ``node_edge``: its nodes (k,) int64 and, per billboard,
    the index into them of the node holding it ((n,) int64). Every billboard lies in one node of
    each level (the octree's ranges nest), so the map is total."""
    n = model.num_billboards
    if len(model.node_level) == 0 or n == 0:
        return np.zeros(0, np.int64), np.zeros(n, np.int64)
    edges = (model.node_bounds[:, 1, 0] - model.node_bounds[:, 0, 0]).astype(np.float64)
    levels = np.unique(model.node_level)
    level_edge = np.array([np.median(edges[model.node_level == lv]) for lv in levels])
    level = levels[np.argmin(np.abs(np.log(level_edge / node_edge)))]
    nodes = np.flatnonzero((model.node_level == level) & (model.node_range[:, 1] > model.node_range[:, 0]))
    nodes = nodes[np.argsort(model.node_range[nodes, 0], kind="stable")]
    starts = model.node_range[nodes, 0].astype(np.int64)
    owner = np.searchsorted(starts, np.arange(n), side="right") - 1
    inside = (owner >= 0) & (np.arange(n) < model.node_range[nodes[np.maximum(owner, 0)], 1])
    if not inside.all():
        raise InputError("octree node ranges do not cover every billboard at one level")
    return nodes.astype(np.int64), owner.astype(np.int64)


class Impostors(GpuOwner):
    """Impostors of a model's far nodes; :meth:`release` is idempotent.

    Per frame: :meth:`begin_frame`, then :meth:`split` on each selection of billboards
    (returns the ones to draw in full), then :meth:`draw`, which makes the images due
    (through ``draw_quads(camera, billboards)``, drawing into the bound framebuffer) and
    draws the impostors.
    """

    def __init__(self, ctx: moderngl.Context, model: BillboardModel, config: ImpostorConfig = ImpostorConfig(),
                 programs: ProgramCache | None = None, studio: ImpostorStudio | None = None):
        self.ctx = ctx
        self.model = model
        self.config = config
        self.nodes, self.node_of = impostor_nodes(model, config.node_edge)
        k = len(self.nodes)
        self._range = model.node_range[self.nodes].astype(np.int64)  # (k, 2) billboards of each node
        # tight boxes around each node's quads (a facade's node is a slab, seen edge-on from the street)
        pad = model_quad_radius(model)
        centres = model.centres.astype(np.float64)
        starts = self._range[:, 0]
        self.box = np.stack([np.minimum.reduceat(centres, starts, axis=0) - pad,
                             np.maximum.reduceat(centres, starts, axis=0) + pad], 1) if k else np.zeros((0, 2, 3))
        self.centre = self.box.mean(axis=1)  # (k, 3)
        corner_index = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
        corners = np.where(corner_index[None, :, :] == 0, self.box[:, None, 0], self.box[:, None, 1])  # (k, 8, 3)
        self._corners8 = np.concatenate([corners, np.ones((k, 8, 1))], axis=2).astype(np.float32)  # homogeneous
        self._far = np.zeros(k, bool)
        self._made_dir = np.zeros((k, 3))  # unit direction node → eye the image was made from
        self._made_dist = np.zeros(k)  # 0: no image
        self._corners = np.zeros((k, 4, 3), np.float32)
        self._image_from_model = np.zeros((k, 3, 4), np.float32)
        self._extent = np.ones((k, 2), np.float32)
        self._wanted = np.zeros(k, bool)  # nodes selected this frame
        self._objects = []
        t = config.texels
        size = atlas_size(k, t)
        limit = max_texture_size(ctx)
        if size[1] > limit:
            raise InputError(f"{k} impostor tiles of {t}² texels need an atlas {size[1]} texels tall; "
                             f"GL_MAX_TEXTURE_SIZE is {limit} (fewer texels or a larger node_edge)")
        if studio is not None and studio.texels != t:
            raise InputError(f"an impostor studio of {studio.texels}² tiles cannot make images of {t}² texels")
        self._origin = tile_origins(k, t)
        self.atlas_size = size
        # the atlas is allocated with the first image: a tile uploaded while paging does not pay
        # for it in the frame that uploads the rest (llvmpipe fills new textures, ~15 ms)
        self.atlas = self.fbo = None
        try:
            if programs is None:
                programs = self._keep(ProgramCache(ctx))
            self.own_studio = studio is None
            self.studio = self._keep(ImpostorStudio(ctx, t, programs)) if studio is None else studio
            self.program = programs.get("impostor.glsl")
            self.stream, self.vao = self._keep_instanced(self.program, IMPOSTOR_DTYPE.itemsize, IMPOSTOR_FORMAT,
                                                         IMPOSTOR_ATTRIBUTES)
        except BaseException:
            self.release()
            raise
        self.nbytes = size[0] * size[1] * 4

    def begin_frame(self, camera: GLCamera, draw_views) -> dict:
        """Choose the far nodes for this view — those whose box spans at most ``texels`` pixels
        either way on screen (with hysteresis), wholly in front of the eye — and make images for
        far nodes that were drawn last frame (``draw_views``: :meth:`GpuDecoder.draw_views`):
        those drawn in full for want of a usable image, nearest first, within
        ``in_full_updates_per_frame``, and the stalest usable ones within ``updates_per_frame``.
        Images are made before the frame's own drawing because on llvmpipe leaving the frame's
        framebuffer makes it finish everything drawn so far.
        Returns stats {impostor_updates}."""
        if len(self.nodes) == 0:
            return {"impostor_updates": 0}
        t, h = self.config.texels, self.config.hysteresis
        side = self._screen_sides(camera, t * (1 - h))
        self._far = np.where(self._far, side < t * (1 + h), side < t * (1 - h))
        candidates = np.flatnonzero(self._far & self._wanted)
        self._wanted[:] = False
        age = self._age(camera, candidates)
        in_full = candidates[age > USABLE_AGE]
        in_full = in_full[np.argsort(np.linalg.norm(self.centre[in_full] - camera.eye, axis=1),
                                     kind="stable")[:self.config.in_full_updates_per_frame]]  # nearest first
        stale = (age > 1) & (age <= USABLE_AGE)
        remade = candidates[stale][np.argsort(-age[stale], kind="stable")[:self.config.updates_per_frame]]
        update = np.concatenate([in_full, remade])
        if len(update):
            self._make(camera, update, draw_views)
        return {"impostor_updates": len(update)}

    def _age(self, camera: GLCamera, nodes: np.ndarray) -> np.ndarray:
        """(N,) float64 how far each node's image is from ``camera``'s view, in units of what an
        image may drift before it is remade (≤ 1: fresh; inf: no image): the largest of its
        parallax error on screen over ``max_error_px``, the turn of the direction to the eye over
        ``max_angle_deg`` and the change of distance over MAX_SCALE_CHANGE. The parallax of a point ``δ``
        off the image's plane when the direction turns by θ is ``δ·sin θ`` (at most half the
        box's extent along the view), ``f/d`` pixels a metre at distance d: the same turn is
        far more visible on a near node than on a far one."""
        cfg = self.config
        to_eye = np.asarray(camera.eye, np.float64) - self.centre[nodes]
        dist = np.linalg.norm(to_eye, axis=1)
        unit = to_eye / np.maximum(dist, 1e-9)[:, None]
        cosine = np.clip(np.einsum("ij,ij->i", unit, self._made_dir[nodes]), -1.0, 1.0)
        sine = np.sqrt(1.0 - cosine * cosine)
        depth = 0.5 * np.einsum("ij,ij->i", self.box[nodes, 1] - self.box[nodes, 0], np.abs(unit))
        focal_px = 0.5 * float(camera.projection[0, 0]) * camera.size[0]
        parallax_px = depth * sine * focal_px / np.maximum(dist, 1e-9)
        made = self._made_dist[nodes] > 0
        ratio = dist / np.where(made, self._made_dist[nodes], 1.0)
        age = np.maximum.reduce([parallax_px / cfg.max_error_px,
                                 np.degrees(np.arccos(cosine)) / cfg.max_angle_deg, np.abs(ratio - 1) / MAX_SCALE_CHANGE])
        return np.where(made, age, np.inf)

    def _screen_sides(self, camera: GLCamera, small: float) -> np.ndarray:
        """(k,) the larger side in pixels of each node's box on screen (inf reaching behind the near
        plane); only bounded by ``small`` where a bound on the box's sphere shows it is below: the
        exact rectangle (eight projected corners) is computed for the other nodes only."""
        view = camera.view.astype(np.float64)
        depth = -(self.centre @ view[2, :3] + view[2, 3])  # along the view direction
        radius = 0.5 * np.linalg.norm(self.box[:, 1] - self.box[:, 0], axis=1)
        scale = 0.5 * max(camera.size) * float(max(camera.projection[0, 0], camera.projection[1, 1]))
        # a sphere off the axis projects larger than on it: twice the on-axis bound covers any
        # field of view below 120°
        gap = depth - radius
        bound = np.where(gap > 0, 4 * radius * scale / np.where(gap > 0, gap, 1.0), np.inf)
        side = np.where(bound < small, bound, np.inf)
        # a box wholly behind the eye has no rectangle (inf, as _screen_rects would give it)
        exact = np.flatnonzero(~(bound < small) & (depth + radius > 0))
        if len(exact):
            rect = self._screen_rects(camera, exact)
            side[exact] = np.maximum(rect[:, 1, 0] - rect[:, 0, 0], rect[:, 1, 1] - rect[:, 0, 1]) \
                * 0.5 * max(camera.size)  # NDC → pixels (the larger image side: conservative)
        return side

    def _screen_rects(self, camera: GLCamera, nodes=None) -> np.ndarray:
        """(k, 2, 2) NDC (min, max) of the nodes' boxes; boxes reaching behind the eye's near plane
        get an infinite rectangle."""
        corners = self._corners8 if nodes is None else self._corners8[nodes]
        m = (camera.projection.astype(np.float64) @ camera.view.astype(np.float64)).astype(np.float32)
        clip = corners @ m.T  # (k, 8, 4)
        w = clip[..., 3]
        in_front = np.all(w > 1e-6, axis=1)
        ndc = clip[..., :2] / np.where(w > 1e-6, w, 1.0)[..., None]
        rect = np.stack([ndc.min(axis=1), ndc.max(axis=1)], 1)
        rect[~in_front] = [[-np.inf, -np.inf], [np.inf, np.inf]]
        return rect

    def forget(self) -> None:
        """Drop every image (the decode's settings changed): far nodes are drawn in full until remade."""
        self._made_dist[:] = 0.0

    def split(self, billboards: np.ndarray) -> np.ndarray:
        """Of ``billboards`` (B,) int, those to draw in full; the nodes of the rest are kept for :meth:`draw`."""
        b = np.asarray(billboards, np.int64)
        if len(self.nodes) == 0 or len(b) == 0:
            return b
        node = self.node_of[b]
        far = self._far[node]
        self._wanted[node[far]] = True
        return b[~far]

    def draw(self, camera: GLCamera, draw_quads) -> dict:
        """Draw the far nodes selected this frame into the bound framebuffer: as impostors where the
        image is usable (:meth:`_usable`), else in full (``draw_quads(camera, billboards)``).
        Returns stats {impostors, nodes_in_full}."""
        wanted, usable = self._usable(camera)
        stats = {"impostors": 0, "nodes_in_full": 0}
        if len(wanted) == 0:
            return stats
        if not usable.all():
            draw_quads(camera, self._billboards(wanted[~usable]))
        shown = wanted[usable]

        if len(shown):
            records = np.empty(len(shown), IMPOSTOR_DTYPE)
            records["corners"] = self._corners[shown]
            records["image_from_model"] = self._image_from_model[shown]
            records["origin"] = self._origin[shown]
            records["extent"] = self._extent[shown]
            self.stream.write(records)
            prog = self.program
            self.atlas.use(0)
            set_uniform(prog, "u_atlas", 0)
            set_uniform(prog, "u_atlas_texel", tuple(1.0 / float(v) for v in self.atlas.size))
            self.ctx.enable(moderngl.DEPTH_TEST)
            prog["u_projection"].write(gl_bytes(camera.projection))
            prog["u_view"].write(gl_bytes(camera.view))
            self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=len(shown))
        stats.update(impostors=len(shown), nodes_in_full=int(np.count_nonzero(~usable)))
        return stats

    def _usable(self, camera: GLCamera) -> tuple[np.ndarray, np.ndarray]:
        """The far nodes selected this frame (N,) int64 and whether each has a usable image (N,)
        bool (:meth:`_age` at most 2: an image is remade at the start of a frame once its age
        passes 1, but only so many per frame)."""
        wanted = np.flatnonzero(self._wanted)
        return wanted, self._age(camera, wanted) <= USABLE_AGE

    def in_full(self, camera: GLCamera) -> np.ndarray:
        """(B,) int64 billboards of the far nodes selected this frame that :meth:`draw` would draw
        in full (no usable image)."""
        wanted, usable = self._usable(camera)
        return self._billboards(wanted[~usable])

    def _make(self, camera: GLCamera, nodes: np.ndarray, draw_views) -> None:
        """Render the images of ``nodes`` (U,) from ``camera`` into their tiles, through the
        studio (:meth:`ImpostorStudio.make`: as many images a pass as it has tiles) with the
        views ``draw_views(camera, projections, rects, selections)`` (the decoder's)."""
        view = camera.view.astype(np.float64)
        proj = camera.projection.astype(np.float64)
        eye = np.asarray(camera.eye, np.float64)
        inverse = np.linalg.inv(proj @ view)
        rects = self._screen_rects(camera, nodes)
        t = self.config.texels
        if self.atlas is None:
            self.atlas = self._keep(self.ctx.texture(self.atlas_size, 4))
            self.atlas.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.fbo = self._keep(self.ctx.framebuffer(color_attachments=[self.atlas]))
        # each image twice as fine as the node is on screen now (resampling a 1:1 image blurs it),
        # at least 2 texels and at most the tile
        extent = np.clip(np.ceil((rects[:, 1] - rects[:, 0]) * np.asarray(camera.size)), 2, t)
        self._extent[nodes] = extent
        # the plane through each box's centre facing the eye, cut to the box's screen rectangle
        centre = self.centre[nodes]
        to_eye = eye - centre
        distance = np.linalg.norm(to_eye, axis=1)
        normal = to_eye / distance[:, None]
        lo, hi = rects[:, 0], rects[:, 1]
        ndc = np.stack([lo, np.stack([hi[:, 0], lo[:, 1]], 1), np.stack([lo[:, 0], hi[:, 1]], 1), hi], 1)  # (U, 4, 2)
        far = np.concatenate([ndc, np.ones(ndc.shape)], axis=2) @ inverse.T  # (U, 4, 4): on the far plane
        ray = far[..., :3] / far[..., 3:] - eye
        along = np.einsum("uj,uj->u", -to_eye, normal)[:, None] / np.einsum("ukj,uj->uk", ray, normal)
        self._corners[nodes] = (eye + ray * along[..., None]).astype(np.float32)
        size = np.maximum(hi - lo, 1e-9)
        crop = np.tile(np.eye(4), (len(nodes), 1, 1))  # each rectangle → the whole of NDC
        crop[:, 0, 0], crop[:, 1, 1] = 2 / size[:, 0], 2 / size[:, 1]
        crop[:, 0, 3], crop[:, 1, 3] = -(hi[:, 0] + lo[:, 0]) / size[:, 0], -(hi[:, 1] + lo[:, 1]) / size[:, 1]
        self._image_from_model[nodes] = (crop @ proj @ view)[:, [0, 1, 3]].astype(np.float32)
        self._made_dir[nodes] = normal
        self._made_dist[nodes] = distance
        selections = [np.arange(*self._range[node]) for node in nodes.tolist()]
        self.studio.make(camera, crop @ proj, extent, self._origin[nodes], selections, self.fbo, draw_views)

    def _billboards(self, nodes) -> np.ndarray:
        """(B,) int64 billboards of ``nodes`` (a node's billboards are one range of the octree order)."""
        return ranges_to_indices(self._range[np.asarray(nodes, np.int64)])

    def release(self) -> None:
        """Free the atlas, its framebuffer, the stream and an own studio (idempotent)."""
        super().release()


class ImpostorStudio(GpuOwner):
    """Where impostor images are drawn: a colour and depth target of ``slots`` tiles of
    ``texels``² (default STUDIO_ROWS rows; allocated on first use), then copied into their
    atlases' tiles, ``slots`` images a pass. Shared
    by the impostors of every tile a :class:`~render.tiled_renderer.TiledRenderer` draws (an
    :class:`Impostors` without one makes its own), so an atlas holds colour only."""

    def __init__(self, ctx: moderngl.Context, texels: int, programs: ProgramCache | None = None,
                 slots: int | None = None):
        self.ctx = ctx
        self.texels = int(texels)
        self.slots = max(ATLAS_WIDTH // self.texels, 1) * STUDIO_ROWS if slots is None else int(slots)
        if self.slots < 1:
            raise InputError(f"an impostor studio needs at least one tile, got {slots}")
        self.size = atlas_size(self.slots, self.texels)
        self._origin = tile_origins(self.slots, self.texels)
        self.colour = self.depth = self.fbo = None
        self._objects = []
        try:
            if programs is None:
                programs = self._keep(ProgramCache(ctx))
            self.clear_program = programs.get("impostor_clear.glsl")
            self.copy_program = programs.get("impostor_copy.glsl")
            self.clear_stream, self.clear_vao = self._keep_instanced(self.clear_program, 16, "4f/i", ("in_rect",))
            self.copy_stream, self.copy_vao = self._keep_instanced(self.copy_program, COPY_DTYPE.itemsize,
                                                                   COPY_FORMAT, COPY_ATTRIBUTES)
        except BaseException:
            self.release()
            raise
        self.nbytes = self.size[0] * self.size[1] * 8

    def make(self, camera: GLCamera, image_projections: np.ndarray, extent: np.ndarray, targets: np.ndarray,
             selections: list, atlas_fbo: moderngl.Framebuffer, draw_views) -> None:
        """Draw U images and copy each into ``atlas_fbo``: image i shows ``selections[i]``
        through ``image_projections[i]`` (4, 4) (GL eye → the whole of NDC), ``extent[i]`` (2,)
        texels from ``targets[i]`` (2,) of the atlas; ``draw_views``: the decoder's
        :meth:`~render.gpu_decode.GpuDecoder.draw_views`. ``slots`` images a pass, each pass
        one visit of the studio and one of the atlas; rebinds the caller's framebuffer."""
        if self.fbo is None:
            self.colour = self._keep(self.ctx.texture(self.size, 4))
            self.depth = self._keep(self.ctx.depth_renderbuffer(self.size))
            self.fbo = self._keep(self.ctx.framebuffer(color_attachments=[self.colour], depth_attachment=self.depth))
        width, height = self.size
        target = self.ctx.fbo
        for first in range(0, len(selections), self.slots):
            last = min(first + self.slots, len(selections))
            origin = self._origin[:last - first].astype(np.float64)
            rects = np.concatenate([origin, origin + extent[first:last]], axis=1)  # (u, 4) pixels
            x0, y0, x1, y1 = rects.T
            place = np.tile(np.eye(4), (last - first, 1, 1))  # the whole of NDC → each image's studio tile
            place[:, 0, 0], place[:, 1, 1] = (x1 - x0) / width, (y1 - y0) / height
            place[:, 0, 3], place[:, 1, 3] = (x0 + x1) / width - 1, (y0 + y1) / height - 1
            self.fbo.use()
            self.fbo.viewport = (0, 0, width, height)
            self.clear_stream.write(rects.astype(np.float32))
            set_uniform(self.clear_program, "u_target_size", (float(width), float(height)))
            self.ctx.depth_func = "1"  # always: the far plane overwrites the old depth
            self.clear_vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=last - first)
            self.ctx.depth_func = "<"
            draw_views(camera, place @ image_projections[first:last], rects, selections[first:last])
            records = np.empty(last - first, COPY_DTYPE)
            records["source"] = origin
            records["target"] = targets[first:last]
            records["extent"] = extent[first:last]
            self.copy_stream.write(records)
            set_uniform(self.copy_program, "u_target_size", tuple(float(v) for v in atlas_fbo.size))
            set_uniform(self.copy_program, "u_studio", 0)
            self.colour.use(0)
            atlas_fbo.use()
            atlas_fbo.viewport = (0, 0, *atlas_fbo.size)
            self.ctx.disable(moderngl.DEPTH_TEST)  # the atlas has no depth; every texel of an image is written
            self.copy_vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=last - first)
            self.ctx.enable(moderngl.DEPTH_TEST)
        target.use()
