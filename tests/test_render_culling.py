"""Frustum culling over the octree, the screen-space quadtree and hardware occlusion culling.

Fast versions against slow, obvious references (per-billboard sphere tests, brute-force
corner tests in clip space, an exhaustive covering-cell search), and the occlusion culler on
a synthetic box scene on a headless context (EGL; Mesa llvmpipe without a GPU): images with
and without culling must be identical, and nothing seen in the reference image may be culled.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np
import pytest

from billboards.geometry import billboard_radius
from billboards.octree import OctreeConfig, build_octree
from render.culling import (boxes_outside, classify_boxes, frustum_cull_nodes,
                            frustum_cull_reference, frustum_planes, indices_to_ranges, merge_ranges,
                            ranges_to_indices, ranges_to_mask)
from render.quadtree import (ScreenQuadtree, cell_coords, covering_cell_reference, level_offset,
                             project_boxes)

# ----------------------------------------------------------------------------------------------
# cameras (standard GL matrices, built here so the tests do not depend on render.camera)


def perspective(fovy_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    f = 1.0 / math.tan(math.radians(fovy_deg) / 2)
    P = np.zeros((4, 4))
    P[0, 0], P[1, 1] = f / aspect, f
    P[2, 2], P[2, 3] = -(far + near) / (far - near), -2 * far * near / (far - near)
    P[3, 2] = -1
    return P


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    V = np.eye(4)
    V[0, :3], V[1, :3], V[2, :3] = s, u, -f
    V[:3, 3] = -V[:3, :3] @ eye
    return V


def view_proj(eye, target, fovy=70.0, aspect=4 / 3, near=0.1, far=500.0) -> np.ndarray:
    return perspective(fovy, aspect, near, far) @ look_at(eye, target)


def clip_of(vp: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.concatenate([points, np.ones((len(points), 1))], axis=1) @ vp.T


# ----------------------------------------------------------------------------------------------
# planes and boxes


def test_frustum_planes_of_a_known_projection():
    near, far = 0.5, 100.0
    planes = frustum_planes(perspective(90.0, 1.0, near, far))  # eye at the origin looking down −z
    h = 1 / math.sqrt(2)
    expected = np.array([[h, 0, -h, 0], [-h, 0, -h, 0], [0, h, -h, 0], [0, -h, -h, 0],
                         [0, 0, -1, -near], [0, 0, 1, far]])
    np.testing.assert_allclose(planes, expected, atol=1e-12)
    # signed distances are metres: a point 3 m in front of the near plane
    assert planes[4, :3] @ [0, 0, -3.5] + planes[4, 3] == pytest.approx(3.0)
    # inside all planes ⇔ inside GL clip space
    rng = np.random.default_rng(1)
    vp = view_proj((3, -4, 2), (10, 20, 1))
    p = rng.uniform(-60, 60, (5000, 3))
    c = clip_of(vp, p)
    inside_clip = (np.abs(c[:, :3]) <= c[:, 3:]).all(axis=1)
    d = p @ frustum_planes(vp)[:, :3].T + frustum_planes(vp)[:, 3]
    far_from_edge = np.abs(d).min(axis=1) > 1e-9
    assert inside_clip.any()
    np.testing.assert_array_equal(((d >= 0).all(axis=1))[far_from_edge], inside_clip[far_from_edge])


def test_planes_and_rects_follow_the_renderers_opencv_camera():
    """With render.camera's matrices, the planes bound the OpenCV image and rects are GL window pixels."""
    from render.camera import look_at as cv_look_at
    from render.camera import project_cv, projection_from_K, view_from_pose
    w, h = 160, 120
    K = np.array([[100.0, 0.0, 81.3], [0.0, 95.0, 57.9], [0.0, 0.0, 1.0]])
    origin = np.array([1e6, -2e6, 30.0])
    T = cv_look_at(origin + [2, -3, 1.5], origin + [10, 20, 1.0])
    near, far = 0.5, 60.0
    vp = projection_from_K(K, (w, h), near, far).astype(np.float64) @ view_from_pose(T, origin).astype(np.float64)
    rng = np.random.default_rng(9)
    p = rng.uniform([-40, -40, -20], [40, 70, 20], (20000, 3))  # model coordinates
    uv, z = project_cv(p + origin, K, T)
    inside_cv = ((uv >= -0.5) & (uv <= [w - 0.5, h - 0.5])).all(axis=1) & (z >= near) & (z <= far)
    planes = frustum_planes(vp)
    d = p @ planes[:, :3].T + planes[:, 3]
    clear = np.abs(d).min(axis=1) > 1e-3
    assert inside_cv.sum() > 100
    np.testing.assert_array_equal((d >= 0).all(axis=1)[clear], inside_cv[clear])
    # a tiny box around a point lands in the rect around (u + ½, h − v − ½)
    q = p[inside_cv][:50]
    rects, depth, crosses = project_boxes(vp, q - 1e-4, q + 1e-4, w, h, pad_px=0.0)
    quv, _ = project_cv(q + origin, K, T)
    x, y = quv[:, 0] + 0.5, h - quv[:, 1] - 0.5
    assert not crosses.any()
    assert ((rects[:, 0] <= x) & (x <= rects[:, 2]) & (rects[:, 1] <= y) & (y <= rects[:, 3])).all()
    assert (rects[:, 2] - rects[:, 0] <= 2).all() and (rects[:, 3] - rects[:, 1] <= 2).all()


def test_boxes_outside_is_conservative_against_clip_space_corners():
    rng = np.random.default_rng(2)
    vp = view_proj((0, 0, 1.5), (1, 5, 0.5), fovy=60, near=0.2, far=80)
    planes = frustum_planes(vp)
    lo = rng.uniform(-100, 100, (20000, 3))
    hi = lo + rng.exponential(4.0, (20000, 3))
    fast = boxes_outside(planes, lo, hi)
    bits = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], dtype=bool)
    corners = np.where(bits[None], hi[:, None], lo[:, None]).reshape(-1, 3)
    c = clip_of(vp, corners).reshape(-1, 8, 4)
    x, y, z, w = (c[..., i] for i in range(4))
    outside_plane = np.stack([x < -w, x > w, y < -w, y > w, z < -w, z > w], axis=-1)  # (k, 8, 6)
    brute = outside_plane.all(axis=1).any(axis=1)  # all eight corners beyond one plane
    assert not (fast & ~brute).any(), "a box meeting the frustum was called outside"
    assert 0.3 < brute.mean() < 0.999
    assert (fast == brute).mean() > 0.999
    cls = classify_boxes(planes, lo, hi)
    np.testing.assert_array_equal(cls == 0, fast)
    inside = cls == 2  # every corner inside every plane
    assert inside.any()
    assert (np.abs(c[inside][..., :3]) <= c[inside][..., 3:]).all()


def test_range_helpers_against_python():
    rng = np.random.default_rng(3)
    for _ in range(50):
        b = rng.integers(0, 60, 12)
        r = np.stack([b, b + rng.integers(0, 6, 12)], axis=1)
        covered = sorted({i for lo, hi in r.tolist() for i in range(lo, hi)})
        merged = merge_ranges(r)
        assert merged.dtype == np.int32
        assert ranges_to_indices(merged).tolist() == covered
        assert (merged[1:, 0] > merged[:-1, 1]).all()  # disjoint, not touching
        np.testing.assert_array_equal(indices_to_ranges(np.array(covered, dtype=np.int64)), merged)
        mask = ranges_to_mask(r, 70)
        assert np.flatnonzero(mask).tolist() == covered
    assert ranges_to_indices(np.zeros((0, 2), np.int32)).shape == (0,)
    assert merge_ranges(np.zeros((0, 2), np.int32)).shape == (0, 2)


# ----------------------------------------------------------------------------------------------
# hierarchical frustum culling


@pytest.fixture(scope="module")
def street_octree():
    """A random octree-like model: clustered points along a 120 m street, 0.5 m voxels."""
    rng = np.random.default_rng(4)
    blocks = rng.uniform([0, -15, 0], [120, 15, 12], (60, 3))
    pts = np.concatenate([b + rng.normal(0, [4, 2, 2], (800, 3)) for b in blocks])
    tree = build_octree(pts, OctreeConfig(voxel_size=0.5, min_points=2))
    centres = (tree.centres() - tree.origin).astype(np.float32)
    bounds = (tree.node_bounds() - tree.origin).astype(np.float32)
    return dict(centres=centres, bounds=bounds, children=tree.node_children.astype(np.int32),
                range=tree.node_range.astype(np.int32), voxel=tree.voxel_size, level=tree.node_level)


CAMERAS = [((-10, 0, 2), (50, 0, 2)), ((60, -25, 3), (60, 10, 3)), ((60, 0, 5), (61, 2, 60)),
           ((30, 3, 1.5), (90, -4, 1.0)), ((300, 0, 2), (400, 0, 2))]


@pytest.mark.parametrize("split", [None, 64])
@pytest.mark.parametrize("refine", [False, True])
@pytest.mark.parametrize("cam", CAMERAS)
def test_frustum_cull_nodes_keeps_every_visible_billboard(street_octree, cam, refine, split):
    t = street_octree
    n = len(t["centres"])
    radius = billboard_radius(t["voxel"])
    planes = frustum_planes(view_proj(*cam, far=150.0))
    ref = frustum_cull_reference(planes, t["centres"], radius)
    res = frustum_cull_nodes(planes, t["bounds"], t["children"], t["range"], pad=radius,
                             centres=t["centres"] if refine else None, radius=radius if refine else None,
                             split_inside_above=split)
    got = ranges_to_mask(res.visible_ranges, n)
    assert not (ref & ~got).any(), f"{int((ref & ~got).sum())} visible billboards culled"
    assert res.num_billboards == got.sum()
    if not ref.any():
        assert not got.any() and res.nodes_tested == 1  # the root is outside: one test
        return
    assert got.sum() < n  # tighter than everything
    extra = int((got & ~ref).sum())
    if refine:
        assert extra == 0  # partial leaves tested per billboard with the reference's sphere
    else:
        assert extra <= 0.25 * ref.sum() + 50
    # objects: disjoint, ascending, each inside its node's range, union = visible ranges
    obj = res.object_ranges.astype(np.int64)
    assert (obj[1:, 0] >= obj[:-1, 1]).all() and (obj[:, 1] > obj[:, 0]).all()
    node_r = t["range"][res.object_nodes]
    assert ((obj[:, 0] >= node_r[:, 0]) & (obj[:, 1] <= node_r[:, 1])).all()
    np.testing.assert_array_equal(merge_ranges(obj), res.visible_ranges)
    assert res.nodes_tested == res.nodes_inside + res.nodes_partial + res.nodes_outside
    assert res.nodes_tested < len(t["bounds"])  # hierarchical: far fewer tests than nodes
    if split is not None:
        sizes = obj[:, 1] - obj[:, 0]
        whole = ~np.isin(res.object_nodes, np.flatnonzero((t["children"] < 0).all(axis=1)))
        assert (sizes[whole] <= split).all()


def test_frustum_cull_nodes_empty_and_all_inside(street_octree):
    planes = frustum_planes(view_proj((0, 0, 0), (1, 0, 0)))
    z = frustum_cull_nodes(planes, np.zeros((0, 2, 3), np.float32), np.zeros((0, 8), np.int32),
                           np.zeros((0, 2), np.int32))
    assert z.visible_ranges.shape == (0, 2) and z.num_billboards == 0
    t = street_octree
    far_back = frustum_planes(view_proj((60, -400, 300), (60, 0, 0), fovy=60, far=2000))
    res = frustum_cull_nodes(far_back, t["bounds"], t["children"], t["range"], pad=billboard_radius(t["voxel"]))
    assert res.visible_ranges.tolist() == [[0, len(t["centres"])]]
    assert res.nodes_tested <= 9 and res.nodes_inside >= 1  # the root or its children are inside


# ----------------------------------------------------------------------------------------------
# quadtree


@pytest.mark.parametrize("size,max_depth", [((640, 480), 5), ((333, 101), 4), ((64, 64), 6)])
def test_quadtree_smallest_covering_cell_matches_brute_force(size, max_depth):
    w, h = size
    rng = np.random.default_rng(5)
    k = 400
    x0 = rng.uniform(-20, w + 20, k)
    y0 = rng.uniform(-20, h + 20, k)
    x1 = x0 + rng.exponential(w / 10, k)
    y1 = y0 + rng.exponential(h / 10, k)
    rects = np.stack([x0, y0, x1, y1], axis=1)
    # edges exactly on cell borders, and degenerate rects
    gx, gy = w / 2 ** max_depth, h / 2 ** max_depth
    snap = rng.random(k) < 0.3
    xs = rng.integers(0, 2 ** max_depth, snap.sum()) * gx
    ys = rng.integers(0, 2 ** max_depth, snap.sum()) * gy
    rects[snap] = np.stack([xs, ys, xs, ys], axis=1)
    rects[snap, 2] += rng.integers(0, 4, snap.sum()) * gx
    rects[snap, 3] += rng.integers(0, 4, snap.sum()) * gy
    qt = ScreenQuadtree(w, h, max_depth)
    cell, level = qt.insert(rects, rng.uniform(-1, 1, k))
    boxes = qt.cell_rects(cell)
    clipped = np.stack([np.clip(rects[:, 0], 0, w), np.clip(rects[:, 1], 0, h),
                        np.clip(rects[:, 2], 0, w), np.clip(rects[:, 3], 0, h)], axis=1)
    assert ((boxes[:, :2] <= clipped[:, :2]) & (clipped[:, 2:] <= boxes[:, 2:])).all()
    for i in range(k):
        ref_cell, ref_level = covering_cell_reference(rects[i], w, h, max_depth)
        assert level[i] == ref_level, (rects[i], level[i], ref_level)
    lv, ix, iy = cell_coords(cell)
    np.testing.assert_array_equal(lv, level)
    np.testing.assert_array_equal(cell, level_offset(level) + iy * 2 ** level + ix)
    groups = qt.cells_by_level()
    assert (np.diff(groups.level) >= 0).all() and (np.diff(groups.cell) > 0).all()
    for g in range(len(groups.cell)):
        members = groups.order[groups.start[g]:groups.start[g + 1]]
        assert (cell[members] == groups.cell[g]).all()
    assert groups.start[-1] == k
    for lvl in range(max_depth + 1):  # an ancestor's box holds the cell's box
        anc = qt.ancestors(lvl)
        ok = level >= lvl
        assert (anc[~ok] == -1).all()
        a, b = qt.cell_rects(anc[ok]), boxes[ok]
        assert ((a[:, :2] <= b[:, :2]) & (b[:, 2:] <= a[:, 2:])).all()


def test_project_boxes_bounds_the_projection():
    rng = np.random.default_rng(6)
    w, h = 160, 120
    vp = view_proj((0, 0, 1.5), (0, 10, 1.5), aspect=w / h, near=0.1)
    lo = rng.uniform([-20, 2, -5], [20, 40, 5], (300, 3))
    hi = lo + rng.uniform(0.1, 4, (300, 3))
    rects, depth, crosses = project_boxes(vp, lo, hi, w, h)
    assert not crosses.any()
    pts = lo[:, None] + rng.random((300, 50, 3)) * (hi - lo)[:, None]
    c = clip_of(vp, pts.reshape(-1, 3)).reshape(300, 50, 4)
    ndc = c[..., :3] / c[..., 3:]
    xw, yw = (ndc[..., 0] + 1) * w / 2, (ndc[..., 1] + 1) * h / 2
    on = (xw >= 0) & (xw <= w) & (yw >= 0) & (yw <= h)
    inside = (xw >= rects[:, None, 0]) & (xw <= rects[:, None, 2]) & (yw >= rects[:, None, 1]) & (yw <= rects[:, None, 3])
    assert inside[on].all()
    assert (ndc[..., 2] >= depth[:, None]).all()
    assert (rects == np.round(rects)).all()
    # the eye inside a box, a box across the camera plane, a box behind
    lo2 = np.array([[-1, -1, 0.5], [-3, -2, 0], [-1, -10, 0]])
    hi2 = np.array([[1, 1, 2.5], [3, 5, 3], [1, -5, 3]])
    rects, depth, crosses = project_boxes(vp, lo2, hi2, w, h)
    assert crosses.all()
    np.testing.assert_array_equal(rects, [[0, 0, w, h]] * 3)
    np.testing.assert_array_equal(depth, -1)


# ----------------------------------------------------------------------------------------------
# occlusion culling on a headless context

W, H = 160, 120


@pytest.fixture(scope="module")
def gl():
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as e:  # no EGL here
        pytest.skip(f"no headless OpenGL context: {e}")
    colour = ctx.renderbuffer((W, H), 4)
    depth = ctx.depth_renderbuffer((W, H))
    fbo = ctx.framebuffer(color_attachments=[colour], depth_attachment=depth)
    yield ctx, fbo
    fbo.release()
    colour.release()
    depth.release()
    ctx.release()


def street_scene(seed: int = 7):
    """A wall 10 m ahead, small boxes hidden behind it, boxes beside it, one peeking round its edge.

    Camera at the origin looking along +y, z up. Returns box_min, box_max (n, 3) and the
    index groups. The wall spans x ∈ [−6, 6], z ∈ [−4, 5] at y = 10: its shadow at depth y
    is |x| < 0.6·y.
    """
    rng = np.random.default_rng(seed)
    lo, hi = [np.array([-6.0, 10.0, -4.0])], [np.array([6.0, 10.5, 5.0])]
    hidden = rng.uniform([-1, 14, -1], [1, 40, 1], (120, 3))
    hidden[:, 0] *= 0.45 * hidden[:, 1]  # well inside the shadow
    hidden[:, 2] *= 0.3 * hidden[:, 1]
    size = rng.uniform(0.2, 1.0, (120, 3))
    lo += list(hidden - size / 2)
    hi += list(hidden + size / 2)
    beside = np.stack([rng.choice([-1, 1], 40) * rng.uniform(0.68, 0.88, 40),  # tan of the half field of view: 0.93
                       rng.uniform(15, 40, 40), rng.uniform(-0.2, 0.2, 40)], axis=1)
    beside[:, [0, 2]] *= beside[:, 1:2]
    size = rng.uniform(0.3, 1.0, (40, 3))
    lo += list(beside - size / 2)
    hi += list(beside + size / 2)
    lo.append(np.array([11.0, 19.5, -0.5]))  # the wall's edge at y = 20 is x = 12
    hi.append(np.array([13.0, 20.5, 0.5]))
    lo, hi = np.array(lo), np.array(hi)
    groups = dict(wall=np.array([0]), hidden=np.arange(1, 121), beside=np.arange(121, 161), peek=np.array([161]))
    return lo, hi, groups


def render_frame(ctx, fbo, boxes, culler, vp, lo, hi, keys=True):
    """One frame: clear, cull and draw the boxes through the callback; → (h, w, 3) uint8 image."""
    fbo.use()
    fbo.viewport = (0, 0, W, H)
    fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
    ctx.enable_only(moderngl.DEPTH_TEST)
    n = len(lo)
    ranges = np.stack([np.arange(n), np.arange(1, n + 1)], axis=1).astype(np.int32)
    drawn = []

    def draw(r):
        drawn.append(r.copy())
        boxes.draw_ranges(vp, r)

    stats = culler.cull(vp, lo, hi, ranges, draw, keys=np.arange(n) if keys else None)
    ctx.finish()
    image = np.frombuffer(fbo.read(components=3, alignment=1), np.uint8).reshape(H, W, 3)
    drawn_mask = ranges_to_mask(np.concatenate(drawn) if drawn else np.zeros((0, 2), np.int32), n)
    np.testing.assert_array_equal(drawn_mask, culler.visible)  # each visible object drawn, once
    return image, stats


def reference_image(ctx, fbo, boxes, vp):
    fbo.use()
    fbo.viewport = (0, 0, W, H)
    fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
    ctx.enable_only(moderngl.DEPTH_TEST)
    boxes.draw(vp)
    ctx.finish()
    return np.frombuffer(fbo.read(components=3, alignment=1), np.uint8).reshape(H, W, 3)


def seen_ids(image, n):
    from .boxes import BoxRenderer
    ids = BoxRenderer.decode_ids(image)
    return np.isin(np.arange(n), ids[ids >= 0])


CONFIGS = {
    "default": {},
    "no-temporal": dict(temporal=False),
    "edo": dict(object_queries=False, temporal=False),
    "shallow": dict(max_depth=2, revisit_frames=2),
}


@pytest.mark.parametrize("config", list(CONFIGS))
def test_occlusion_culling_matches_the_unculled_image(gl, config):
    from render.occlusion import OcclusionConfig, OcclusionCuller

    from .boxes import BoxRenderer
    ctx, fbo = gl
    lo, hi, g = street_scene()
    n = len(lo)
    with BoxRenderer(ctx, lo, hi) as boxes, \
            OcclusionCuller(ctx, W, H, mode="occlusion", config=OcclusionConfig(**CONFIGS[config])) as culler:
        # a camera walking sideways and turning: later frames reuse earlier visibility
        for f in range(6):
            eye = np.array([0.8 * f, 0.3 * f, 0.2 * f])
            vp = view_proj(eye, eye + [0.05 * f, 10, 0], aspect=W / H, near=0.1, far=200)
            ref = reference_image(ctx, fbo, boxes, vp)
            image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
            np.testing.assert_array_equal(image, ref)
            seen = seen_ids(ref, n)
            assert not (seen & ~culler.visible).any(), f"frame {f}: a visible box was culled"
            assert stats.objects == n and stats.objects_drawn == culler.visible.sum()
            if f == 0:
                assert seen[g["peek"]].all() and seen[g["beside"]].any()
                assert not seen[g["hidden"]].any()
                if config != "edo":  # Edo draws every object of a passing cell
                    assert not culler.visible[g["hidden"]].any(), "boxes behind the wall were drawn"
                else:
                    assert culler.visible[g["hidden"]].mean() < 0.5
                assert culler.visible[g["wall"]].all() and culler.visible[g["peek"]].all()
                assert stats.queries > 0 and stats.draw_calls >= 1
                assert stats.culled_by_query + stats.culled_by_parent + stats.objects_offscreen \
                    == stats.objects_culled
        assert stats.cull_s >= 0 and stats.billboards == n


def test_hidden_boxes_culled_without_their_own_queries(gl):
    """Cells behind the wall fail as a whole (Edo); with temporal coherence few queries remain (CHC++)."""
    from render.occlusion import OcclusionConfig, OcclusionCuller

    from .boxes import BoxRenderer
    ctx, fbo = gl
    lo, hi, g = street_scene()
    n = len(lo)
    vp = view_proj((0, 0, 0), (0, 10, 0), aspect=W / H, near=0.1, far=200)
    with BoxRenderer(ctx, lo, hi) as boxes:
        ref = reference_image(ctx, fbo, boxes, vp)
        seen = seen_ids(ref, n)
        for temporal in (False, True):
            with OcclusionCuller(ctx, W, H, mode="occlusion", config=OcclusionConfig(temporal=temporal)) as culler:
                for f in range(3):
                    image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
                    np.testing.assert_array_equal(image, ref)
                    assert not (seen & ~culler.visible).any()
                    assert not culler.visible[g["hidden"]].any() and culler.visible.sum() <= seen.sum() + 5
                    assert stats.culled_by_parent > 0 and stats.queries < n
                    if temporal and f > 0:  # last frame's visible set drawn first: the cells fail at once
                        assert stats.queries < n // 4 and stats.objects_temporal > 0
                        assert stats.culled_by_parent > n // 4


def test_camera_inside_a_box_and_empty_scene(gl):
    from render.occlusion import OcclusionCuller

    from .boxes import BoxRenderer
    ctx, fbo = gl
    lo, hi, _ = street_scene()
    lo = np.concatenate([lo, [[-0.5, -0.5, -0.5]]])  # a box around the eye: its inside hides the rest
    hi = np.concatenate([hi, [[0.5, 3.0, 0.5]]])
    n = len(lo)
    vp = view_proj((0, 0, 0), (0, 10, 0), aspect=W / H, near=0.1, far=200)
    with BoxRenderer(ctx, lo, hi) as boxes, OcclusionCuller(ctx, W, H, mode="occlusion") as culler:
        for _ in range(2):
            image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
            np.testing.assert_array_equal(image, reference_image(ctx, fbo, boxes, vp))
            assert culler.visible[n - 1] and stats.objects_near >= 1
            assert (BoxRenderer.decode_ids(image) == n - 1).all()
            assert stats.objects_drawn < n // 2  # the rest is hidden by the box around the eye
        empty = np.zeros((0, 3))
        image, stats = render_frame(ctx, fbo, boxes, culler, vp, empty, empty)
        assert (image == 0).all() and stats.objects == 0 and stats.draw_calls == 0 and stats.queries == 0


def auto_trials(ctx, fbo, make_culler, frames: int) -> tuple[list[bool], object]:
    """Frames of an auto culler (``make_culler(ctx, W, H)``) over boxes in a row across the view, where
    nothing hides anything: whether it culled in each frame (the image always the reference's)."""
    from .boxes import BoxRenderer

    x = np.linspace(-8, 8, 24)
    lo = np.stack([x - 0.3, np.full_like(x, 15.0), np.full_like(x, -0.3)], axis=1)
    hi = lo + 0.6
    vp = view_proj((0, 0, 0), (0, 10, 0), aspect=W / H, near=0.1, far=200)
    with BoxRenderer(ctx, lo, hi) as boxes, make_culler(ctx, W, H) as culler:
        ref = reference_image(ctx, fbo, boxes, vp)
        active = []
        for _ in range(frames):
            image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
            np.testing.assert_array_equal(image, ref)
            active.append(stats.active)
            assert stats.objects_drawn == len(lo)
        return active, culler


def test_auto_mode_switches_off_when_nothing_is_culled_and_retries(gl):
    from render.culler_base import auto_pays
    from render.occlusion import OcclusionConfig, OcclusionCuller

    ctx, fbo = gl
    cfg = OcclusionConfig(auto_window=3, auto_backoff=4, auto_backoff_max=8)
    active, culler = auto_trials(ctx, fbo, lambda c, w, h: OcclusionCuller(c, w, h, mode="auto", config=cfg), 16)
    # a losing trial ends after 2 frames: on 2, off 4, on 2, off 8 (backoff doubled)
    assert active == [True] * 2 + [False] * 4 + [True] * 2 + [False] * 8
    assert culler.last_decision["pays"] is False and culler.cost_per_billboard is not None
    assert not auto_pays(0, 0.0, 1.0)
    assert auto_pays(100, 1e-3, 2e-5) and not auto_pays(10, 1e-3, 2e-5)


def test_culler_checks_viewport_modes_and_release(gl):
    from render.occlusion import OcclusionCuller
    ctx, fbo = gl
    culler = OcclusionCuller(ctx, W + 1, H, mode="occlusion")
    fbo.use()
    fbo.viewport = (0, 0, W, H)
    box = np.array([[0.0, 5.0, 0.0]])
    with pytest.raises(ValueError, match="viewport"):
        culler.cull(view_proj((0, 0, 0), (0, 1, 0)), box, box + 1, np.array([[0, 1]]), lambda r: None)
    with pytest.raises(ValueError):
        culler.mode = "sometimes"
    culler.mode = "frustum"  # frustum: no viewport needed, one draw of everything
    calls = []
    stats = culler.cull(view_proj((0, 0, 0), (0, 1, 0)), box, box + 1, np.array([[0, 1]]), calls.append)
    assert len(calls) == 1 and calls[0].tolist() == [[0, 1]] and not stats.active
    culler.release()
    culler.release()
    with pytest.raises(RuntimeError):
        culler.cull(view_proj((0, 0, 0), (0, 1, 0)), box, box + 1, np.array([[0, 1]]), calls.append)


def test_cull_nodes_on_an_octree_frustum_result(gl):
    """Frustum result → occlusion culler on an octree of a dense wall with a cloud behind it."""
    from render.occlusion import OcclusionCuller

    from .boxes import BoxRenderer
    ctx, fbo = gl
    rng = np.random.default_rng(8)
    gy, gz = np.meshgrid(np.arange(-10, 10, 0.1), np.arange(0, 10, 0.1))
    wall = np.stack([rng.uniform(20, 20.4, gy.size), gy.ravel(), gz.ravel()], axis=1)
    cloud = rng.uniform([30, -5, 1], [45, 5, 9], (20000, 3))
    beside = rng.uniform([30, 12, 1], [45, 16, 9], (5000, 3))
    tree = build_octree(np.concatenate([wall, cloud, beside]), OctreeConfig(voxel_size=0.5, min_points=1))
    t = dict(bounds=(tree.node_bounds() - tree.origin).astype(np.float32), children=tree.node_children,
             range=tree.node_range.astype(np.int32))
    s = tree.voxel_size
    c = tree.centres() - tree.origin
    lo, hi = c - s / 2, c + s / 2  # each billboard as its voxel cube
    eye = np.array([-10.0, 0.0, 5.0]) - tree.origin
    vp = view_proj(eye, eye + [1, 0.1, 0], aspect=W / H, near=0.1, far=150)
    radius = billboard_radius(s)
    res = frustum_cull_nodes(frustum_planes(vp), t["bounds"], t["children"], t["range"], pad=radius,
                             split_inside_above=32)
    n = len(c)
    with BoxRenderer(ctx, lo, hi) as boxes, OcclusionCuller(ctx, W, H, mode="occlusion") as culler:
        ref = reference_image(ctx, fbo, boxes, vp)
        for _ in range(2):
            fbo.use()
            fbo.viewport = (0, 0, W, H)
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            drawn = []
            stats = culler.cull_nodes(vp, res, t["bounds"], lambda r: (drawn.append(r), boxes.draw_ranges(vp, r)),
                                      pad=radius)
            ctx.finish()
            image = np.frombuffer(fbo.read(components=3, alignment=1), np.uint8).reshape(H, W, 3)
            np.testing.assert_array_equal(image, ref)
            got = ranges_to_mask(np.concatenate(drawn), n)
            assert not (seen_ids(ref, n) & ~got).any()
            assert stats.billboards == res.num_billboards
            assert stats.billboards_drawn == got.sum() < 0.6 * res.num_billboards  # the cloud is hidden
