"""View-frustum culling over the billboard model's octree (pure numpy, no GPU).

Conventions. ``view_proj`` is a row-major (4, 4) matrix mapping *model*
coordinates (world − model.origin, the coordinates of ``node_bounds`` and
``centres``) to OpenGL clip space, ``clip = view_proj @ [x, y, z, 1]``; a point is
inside the view volume when −w ≤ x, y, z ≤ w (standard GL clip space, as built by
:func:`render.camera.projection_from_K`: pass ``projection @ view``). Planes are
(a, b, c, d) rows with the inside where a·x + b·y + c·z + d ≥ 0, normalised so
that (a, b, c) has unit length and a·x + b·y + c·z + d is a distance in metres.

Conservative throughout. A box or sphere is called outside only when it lies
beyond one plane by more than a small tolerance (:data:`PLANE_REL_EPS` of the
magnitudes involved, so that float32 rounding on the GPU cannot make a culled
billboard light a pixel). Boxes at a frustum corner may be kept although they
miss the frustum (the usual plane-by-plane test): that costs a few extra
billboards, never a missing one.

Billboard bounds. A billboard quad turned toward the viewer stays inside the
sphere of radius ``voxel_size·√3/2`` around its centre
(:func:`billboards.geometry.billboard_radius`).
Node bounds are the octree cells, whose billboard centres lie at least half a
voxel inside; a billboard quad can still reach out of its cell (pitched quads,
by up to (√2 − 1)/2 of a voxel), so node boxes are grown by ``pad`` before they
are tested. Passing ``pad = billboard_radius(voxel_size)`` is always safe, also
for bounds that are tight around the centres.

:func:`frustum_cull_nodes` is the fast hierarchical version (vectorised level by
level, no Python loop per node or billboard); :func:`frustum_cull_reference` is
the slow, obvious per-billboard version the tests compare with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

#: Relative tolerance of plane tests: a point is outside only if its signed distance is
#: below −PLANE_REL_EPS·(|n|·|x| + |d| + extent). float32 clip coordinates on the GPU are
#: good to ~1e-7 of the same magnitudes; 1e-5 leaves a wide margin (1 mm at 100 m).
PLANE_REL_EPS = 1e-5

PLANE_NAMES = ("left", "right", "bottom", "top", "near", "far")


#: How a renderer culls: none (draws everything), frustum (the view frustum), occlusion (the
#: frustum, then hardware occlusion queries), hzb (the frustum, then a hierarchical depth buffer
#: read back once per frame, :mod:`render.hzb_culler`), auto (the HZB while it pays for itself,
#: else frustum).
CULL_MODES = ("none", "frustum", "occlusion", "hzb", "auto")


def check_cull(cull: str) -> str:
    """``cull`` if it is one of :data:`CULL_MODES`; else :class:`~core.errors.InputError`."""
    if cull not in CULL_MODES:
        raise InputError(f"cull must be one of {CULL_MODES}, got {cull!r}")
    return cull


# ---------------------------------------------------------------------------------------------
# Planes and boxes


def frustum_planes(view_proj: np.ndarray) -> np.ndarray:
    """The six clip planes of a GL view-projection matrix (Gribb–Hartmann).

    view_proj: (4, 4) row-major, clip = view_proj @ [x, y, z, 1], GL clip space
    −w ≤ x, y, z ≤ w. Returns (6, 4) float64 planes (a, b, c, d) in the order of
    :data:`PLANE_NAMES` (left, right, bottom, top, near, far), each normalised so
    that (a, b, c) is a unit inward normal and a·x + b·y + c·z + d the signed
    distance (m) of a model-space point, ≥ 0 inside.
    """
    m = np.asarray(view_proj, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"view_proj must be a finite (4, 4) matrix, got shape {m.shape}"
                         + ("" if m.shape != (4, 4) else " with non-finite entries"))
    planes = np.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
    norm = np.linalg.norm(planes[:, :3], axis=1)
    if np.any(norm == 0):
        raise InputError("view_proj has a degenerate clip plane (zero normal)")
    return planes / norm[:, None]


def _check_planes(planes) -> np.ndarray:
    p = np.asarray(planes, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 4 or len(p) == 0:
        raise InputError(f"planes must be a (p, 4) array, got shape {p.shape}")
    return p


def _check_boxes(box_min, box_max) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(box_min, dtype=np.float64)
    hi = np.asarray(box_max, dtype=np.float64)
    if lo.ndim != 2 or lo.shape[1] != 3 or lo.shape != hi.shape:
        raise InputError(f"box_min and box_max must be two (k, 3) arrays, got {lo.shape} and {hi.shape}")
    return lo, hi


def _box_plane_distances(planes: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Centre distances (k, p), half-extent projections (k, p) and tolerances (k, p) of boxes to planes.

    The p-vertex (the corner farthest along a plane's normal) lies at distance
    centre + extent; the n-vertex at centre − extent.
    """
    n, d = planes[:, :3], planes[:, 3]
    c = (lo + hi) * 0.5
    e = (hi - lo) * 0.5
    an = np.abs(n).T
    dist = c @ n.T + d
    ext = e @ an
    tol = PLANE_REL_EPS * (np.abs(c) @ an + np.abs(d) + ext)
    return dist, ext, tol


def classify_boxes(planes, box_min, box_max) -> np.ndarray:
    """Each box against the frustum → (k,) int8: 0 outside, 1 partial (or unsure), 2 inside.

    planes (p, 4) as from :func:`frustum_planes`; box_min, box_max (k, 3). Outside
    (0) is conservative as in :func:`boxes_outside`; inside (2) means every corner
    is inside every plane by more than the tolerance.
    """
    planes = _check_planes(planes)
    lo, hi = _check_boxes(box_min, box_max)
    out = np.ones(len(lo), dtype=np.int8)
    if len(lo) == 0:
        return out
    dist, ext, tol = _box_plane_distances(planes, lo, hi)
    out[(dist - ext > tol).all(axis=1)] = 2
    out[(dist + ext < -tol).any(axis=1)] = 0
    return out


def boxes_outside(planes, box_min, box_max) -> np.ndarray:
    """Axis-aligned boxes that lie entirely outside one frustum plane → (k,) bool.

    planes: (p, 4) float64 from :func:`frustum_planes`; box_min, box_max: (k, 3)
    in the planes' coordinates. p-vertex test: a box is outside when its corner
    farthest along some plane's normal is still behind that plane (by more than
    the tolerance). Conservative: never True for a box that meets the frustum.
    """
    planes = _check_planes(planes)
    lo, hi = _check_boxes(box_min, box_max)
    if len(lo) == 0:
        return np.zeros(0, dtype=bool)
    dist, ext, tol = _box_plane_distances(planes, lo, hi)
    return (dist + ext < -tol).any(axis=1)


def spheres_outside(planes, centres, radius) -> np.ndarray:
    """Spheres entirely behind one frustum plane → (n,) bool (vectorised, conservative).

    planes (p, 4); centres (n, 3); radius: scalar or (n,).
    """
    planes = _check_planes(planes)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(c),))
    if len(c) == 0:
        return np.zeros(0, dtype=bool)
    n, d = planes[:, :3], planes[:, 3]
    dist = c @ n.T + d
    tol = PLANE_REL_EPS * (np.abs(c) @ np.abs(n).T + np.abs(d) + r[:, None])
    return (dist + r[:, None] < -tol).any(axis=1)


# ---------------------------------------------------------------------------------------------
# Ranges


def _check_ranges(ranges) -> np.ndarray:
    r = np.asarray(ranges)
    if r.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if r.ndim != 2 or r.shape[1] != 2 or not np.issubdtype(r.dtype, np.integer):
        raise InputError(f"ranges must be an (r, 2) integer array of [begin, end), got {r.dtype} {r.shape}")
    return r.astype(np.int64, copy=False)


def merge_ranges(ranges) -> np.ndarray:
    """Sort and merge [begin, end) ranges that overlap or touch → (r', 2) int32, ascending, disjoint.

    ranges: (r, 2) integers; empty ranges (end ≤ begin) are dropped.
    """
    r = _check_ranges(ranges)
    r = r[r[:, 1] > r[:, 0]]
    if len(r) == 0:
        return np.zeros((0, 2), dtype=np.int32)
    r = r[np.argsort(r[:, 0], kind="stable")]
    reach = np.maximum.accumulate(r[:, 1])
    new = np.empty(len(r), dtype=bool)
    new[0] = True
    new[1:] = r[1:, 0] > reach[:-1]  # a gap after everything so far starts a new run
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], len(r)) - 1
    return np.stack([r[starts, 0], reach[ends]], axis=1).astype(np.int32)


def ranges_to_indices(ranges) -> np.ndarray:
    """Every index in the [begin, end) ranges, in the ranges' order → (n,) int64 (vectorised)."""
    r = _check_ranges(ranges)
    r = r[r[:, 1] > r[:, 0]]
    if len(r) == 0:
        return np.zeros(0, dtype=np.int64)
    lengths = r[:, 1] - r[:, 0]
    firsts = np.cumsum(lengths) - lengths  # position of each range's first index in the output
    return np.arange(int(lengths.sum()), dtype=np.int64) + np.repeat(r[:, 0] - firsts, lengths)


def ranges_to_mask(ranges, n: int) -> np.ndarray:
    """(n,) bool mask of the indices covered by the [begin, end) ranges (each within [0, n])."""
    mask = np.zeros(int(n), dtype=bool)
    r = merge_ranges(ranges)
    if len(r) and (r[0, 0] < 0 or r[-1, 1] > n):
        raise InputError(f"ranges reach outside [0, {n}]")
    delta = np.zeros(int(n) + 1, dtype=np.int64)
    np.add.at(delta, r[:, 0], 1)
    np.add.at(delta, r[:, 1], -1)
    mask[:] = np.cumsum(delta[:-1]) > 0
    return mask


def indices_to_ranges(indices) -> np.ndarray:
    """Ascending unique indices (n,) → (r, 2) int32 ranges of consecutive runs."""
    i = np.asarray(indices, dtype=np.int64).reshape(-1)
    if len(i) == 0:
        return np.zeros((0, 2), dtype=np.int32)
    brk = np.flatnonzero(np.diff(i) != 1)
    starts = np.concatenate([[0], brk + 1])
    ends = np.concatenate([brk, [len(i) - 1]])
    return np.stack([i[starts], i[ends] + 1], axis=1).astype(np.int32)


# ---------------------------------------------------------------------------------------------
# Hierarchical frustum culling


@dataclass(frozen=True)
class FrustumResult:
    """What survives frustum culling.

    The *objects* are the units handed to occlusion culling: each is one accepted
    node (inside the frustum, or a partial leaf) with its billboard range; a
    partial leaf tested per billboard may give several objects with the same
    node. Object ranges are disjoint and ascending; ``visible_ranges`` is their
    merged union (what to draw without occlusion culling).
    """

    visible_ranges: np.ndarray  # (r, 2) int32 merged [begin, end) billboard ranges to draw
    object_nodes: np.ndarray  # (m,) int32 node of each object
    object_ranges: np.ndarray  # (m, 2) int32 [begin, end) billboards of each object, ascending
    nodes_tested: int  # nodes whose box was tested against the planes
    nodes_inside: int  # tested nodes entirely inside (their subtree taken without tests)
    nodes_partial: int  # tested nodes that straddle a plane (descended, or kept / refined if leaves)
    nodes_outside: int  # tested nodes entirely outside (subtree dropped)
    billboards_tested: int  # billboards sphere-tested in partial leaves

    @property
    def num_billboards(self) -> int:
        """Billboards in the visible ranges."""
        r = self.visible_ranges
        return int((r[:, 1].astype(np.int64) - r[:, 0]).sum()) if len(r) else 0


def _children_of(node_children: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    c = node_children[nodes].reshape(-1)
    return c[c >= 0].astype(np.int64)


def frustum_cull_nodes(planes, node_bounds, node_children, node_range, *, pad: float = 0.0,
                       centres=None, radius: float | None = None,
                       split_inside_above: int | None = None) -> FrustumResult:
    """Hierarchical frustum culling of the octree node table.

    planes: (p, 4) from :func:`frustum_planes`. node_bounds: (k, 2, 3) min/max
    (model coordinates, float32 or float64); node_children: (k, 8) int, −1 = none;
    node_range: (k, 2) int [begin, end) billboards; node 0 is the root.
    pad: metres added on every side of every node box (see the module notes;
    :func:`billboards.geometry.billboard_radius` of the voxel size is always safe).

    Level by level, the whole frontier at once: a node entirely inside adds its
    range without testing its children; one entirely outside drops its subtree;
    a partial node descends. A partial *leaf* (no children) is kept whole, or,
    when ``centres`` (n, 3) and ``radius`` are given, each of its billboards is
    tested as a sphere (vectorised) and the survivors kept as runs.
    split_inside_above: when set, an inside node with more billboards than this
    and with children is split into its children (without plane tests) so that
    occlusion culling gets objects of a useful size; None keeps inside nodes whole.
    """
    planes = _check_planes(planes)
    bounds = np.asarray(node_bounds)
    children = np.asarray(node_children)
    rng = np.asarray(node_range)
    k = len(bounds)
    if bounds.shape != (k, 2, 3) or children.shape != (k, 8) or rng.shape != (k, 2):
        raise InputError(f"node table shapes disagree: bounds {bounds.shape}, children {children.shape}, "
                         f"range {rng.shape} (want (k, 2, 3), (k, 8), (k, 2))")
    refine = centres is not None
    if refine:
        if radius is None:
            raise InputError("frustum_cull_nodes: give radius with centres")
        centres = np.asarray(centres)
    counts = dict(tested=0, inside=0, partial=0, outside=0, bb=0)
    empty = np.zeros(0, dtype=np.int64)
    if k == 0:
        return FrustumResult(np.zeros((0, 2), np.int32), np.zeros(0, np.int32), np.zeros((0, 2), np.int32),
                             0, 0, 0, 0, 0)
    # Everything per node is gathered for the frontier only: a frame touches a few thousand
    # nodes of a table that may hold millions.
    accepted = []  # node ids taken whole
    partial_leaves = []
    frontier = np.zeros(1, dtype=np.int64)  # nodes to test
    known_inside = empty  # children of split inside nodes: inside without a test
    while len(frontier) or len(known_inside):
        box = bounds[frontier].astype(np.float64)
        cls = classify_boxes(planes, box[:, 0] - pad, box[:, 1] + pad)
        counts["tested"] += len(frontier)
        counts["inside"] += int((cls == 2).sum())
        counts["partial"] += int((cls == 1).sum())
        counts["outside"] += int((cls == 0).sum())
        inside = np.concatenate([frontier[cls == 2], known_inside])
        partial = frontier[cls == 1]
        if split_inside_above is not None and len(inside):
            size = rng[inside, 1].astype(np.int64) - rng[inside, 0]
            split = (size > split_inside_above) & (children[inside] >= 0).any(axis=1)
            accepted.append(inside[~split])
            known_inside = _children_of(children, inside[split])
        else:
            accepted.append(inside)
            known_inside = empty
        descend = (children[partial] >= 0).any(axis=1)
        partial_leaves.append(partial[~descend])
        frontier = _children_of(children, partial[descend])

    acc = np.concatenate(accepted)
    leaves = np.concatenate(partial_leaves)
    obj_nodes = [acc]
    obj_ranges = [rng[acc].astype(np.int64)]
    if refine and len(leaves):
        leaf_r = rng[leaves].astype(np.int64)
        idx = ranges_to_indices(leaf_r)
        owner = np.repeat(leaves, leaf_r[:, 1] - leaf_r[:, 0])
        counts["bb"] = len(idx)
        keep = ~spheres_outside(planes, centres[idx], radius)
        idx, owner = idx[keep], owner[keep]
        if len(idx):
            order = np.argsort(idx, kind="stable")
            idx, owner = idx[order], owner[order]
            brk = np.flatnonzero((np.diff(idx) != 1) | (np.diff(owner) != 0))
            starts = np.concatenate([[0], brk + 1])
            ends = np.concatenate([brk, [len(idx) - 1]])
            obj_nodes.append(owner[starts])
            obj_ranges.append(np.stack([idx[starts], idx[ends] + 1], axis=1))
    else:
        obj_nodes.append(leaves)
        obj_ranges.append(rng[leaves].astype(np.int64))
    nodes = np.concatenate(obj_nodes)
    ranges = np.concatenate(obj_ranges).reshape(-1, 2)
    order = np.argsort(ranges[:, 0], kind="stable")
    nodes, ranges = nodes[order], ranges[order]
    return FrustumResult(visible_ranges=merge_ranges(ranges), object_nodes=nodes.astype(np.int32),
                         object_ranges=ranges.astype(np.int32), nodes_tested=counts["tested"],
                         nodes_inside=counts["inside"], nodes_partial=counts["partial"],
                         nodes_outside=counts["outside"], billboards_tested=counts["bb"])


def frustum_cull_reference(planes, centres, radius) -> np.ndarray:
    """Slow, obvious per-billboard culling, for tests → (n,) bool, True = possibly visible.

    planes (p, 4); centres (n, 3); radius scalar. A billboard is culled when its
    bounding sphere lies entirely behind one plane (Python loop per billboard and
    plane; no tolerance).
    """
    planes = np.asarray(planes, dtype=np.float64).tolist()
    r = float(radius)
    visible = []
    for x, y, z in np.asarray(centres, dtype=np.float64).reshape(-1, 3).tolist():
        visible.append(all(a * x + b * y + c * z + d >= -r for a, b, c, d in planes))
    return np.array(visible, dtype=bool)
