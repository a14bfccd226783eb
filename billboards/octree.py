"""A vectorised octree over a point cloud: voxel leaves and the node table.

Points are binned into cubic cells of the leaf level with a single streaming
pass (integer cell → linear key), the occupied cells are counted with
``np.bincount`` when the occupied bounding box is small enough and with a sort
otherwise, and only the unique occupied cells are Morton-encoded
(:mod:`billboards.morton`) and sorted. Cells holding at least ``min_points``
points become voxels (billboards), in ascending Morton order. The internal
nodes follow from the sorted leaf codes level by level (``code >> 3``), so
there is no per-point and no per-node Python loop.

The node table (bounds, children, contiguous range of billboards under each
node) is kept because the renderer culls by it: a node's billboards are
``leaf_codes[begin:end]``, contiguous because Morton order is depth-first.

:func:`build_octree_reference` is the slow, obvious dict version that the tests
compare with; :func:`open3d_octree` is the baseline for the benchmark.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from core.errors import InputError

from .morton import MORTON_BITS, morton_axes, morton_decode, morton_encode

logger = logging.getLogger(__name__)

#: Deepest leaf level: 3×21 bits fit a uint64 Morton code (2**21 cells per axis).
MAX_DEPTH = MORTON_BITS

_CHUNK = 1 << 14  # points per streaming chunk (a 384 kB float64 buffer stays in L2)
_TILE = 1 << 10  # points per row when a chunk is viewed as (rows, 3·_TILE): long inner loops
_DENSE_MAX_CELLS = 1 << 24  # count cells with bincount up to this many (and ≤ 2 per point), else sort
_EXACT_FLOAT = float(1 << 53)  # linear keys below this are exact in float64
_DEPTH_PAD = 1e-9  # depth-given root edge = max extent·(1 + this), so the max point lies inside


MAX_MIN_POINTS = 1_000_000  # points a voxel may be asked to need (more: no leaf of any size holds them)


@dataclass(frozen=True)
class OctreeConfig:
    voxel_size: float | None = 0.5  # leaf edge in metres; None → derived from depth
    depth: int | None = None  # levels below the root, used when voxel_size is None (voxel = root edge / 2**depth)
    min_points: int = 10  # a leaf becomes a voxel only with at least this many points

    def __post_init__(self):
        if (self.voxel_size is None) == (self.depth is None):
            raise InputError("OctreeConfig: give exactly one of voxel_size and depth "
                             f"(got voxel_size={self.voxel_size!r}, depth={self.depth!r}); "
                             "set voxel_size=None to build to a depth")
        if self.voxel_size is not None:
            v = float(self.voxel_size)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"OctreeConfig: voxel_size must be a finite number > 0, got {self.voxel_size!r}")
        if self.depth is not None:
            if isinstance(self.depth, bool) or int(self.depth) != self.depth or not 0 <= self.depth <= MAX_DEPTH:
                raise InputError(f"OctreeConfig: depth must be an integer in [0, {MAX_DEPTH}] "
                                 f"(2**{MAX_DEPTH} cells per axis fit a uint64 Morton code), got {self.depth!r}")
        if int(self.min_points) != self.min_points or not 1 <= self.min_points <= MAX_MIN_POINTS:
            raise InputError(f"OctreeConfig: min_points must be an integer in [1, {MAX_MIN_POINTS}], "
                             f"got {self.min_points!r}")


@dataclass(frozen=True, eq=False)
class Octree:
    """Voxel leaves in Morton order and the node table over them.

    Nodes are in breadth-first order: every level-l node before any level-(l+1)
    node, each level sorted by code. Only nodes with at least one voxel below
    them exist; the nodes at level ``depth`` are the voxels themselves, in order.
    """

    origin: np.ndarray  # (3,) float64 world min corner of the root cube
    voxel_size: float  # leaf edge (m); the root cube's edge is voxel_size·2**depth
    depth: int  # leaf level (root = level 0)
    leaf_codes: np.ndarray  # (n,) uint64 Morton codes of the voxel leaves, strictly ascending = billboard order
    leaf_counts: np.ndarray  # (n,) int64 points in each voxel
    node_level: np.ndarray  # (k,) uint8 level of each node, root = 0
    node_code: np.ndarray  # (k,) uint64 Morton code of the node at its level
    node_children: np.ndarray  # (k, 8) int32 child node per octant (the code's 3 low bits), -1 = none
    node_range: np.ndarray  # (k, 2) int64 [begin, end) of the voxel leaves (billboards) under the node

    @property
    def num_voxels(self) -> int:
        return len(self.leaf_codes)

    @property
    def num_nodes(self) -> int:
        return len(self.node_code)

    def leaf_index(self) -> np.ndarray:
        """Grid indices of the voxels → (n, 3) int64, each in [0, 2**depth)."""
        return morton_decode(self.leaf_codes)

    def centres(self) -> np.ndarray:
        """World centres of the voxels → (n, 3) float64."""
        return self.origin + (self.leaf_index() + 0.5) * self.voxel_size

    def node_bounds(self) -> np.ndarray:
        """World bounds of the nodes → (k, 2, 3) float64: [:, 0] min corner, [:, 1] max corner."""
        size = self.voxel_size * np.ldexp(1.0, self.depth - self.node_level.astype(np.int64))
        lo = self.origin + morton_decode(self.node_code) * size[:, None]
        return np.stack([lo, lo + size[:, None]], axis=1)

    def leaves_of_points(self, points: np.ndarray) -> np.ndarray:
        """The voxel holding each point.

        points: (N, 3) float64 world. Returns (N,) int64 index into the leaves,
        -1 for points outside the root cube (its closed bounds), in a cell below
        ``min_points``, or not finite. Cells are computed exactly as in
        :func:`build_octree`, so every point of the built cloud in a voxel maps to it.
        """
        p = _as_points(points)
        out = np.full(len(p), -1, dtype=np.int64)
        if len(p) == 0 or self.num_voxels == 0:
            return out
        top = float(1 << self.depth)
        for s in range(0, len(p), 1 << 16):
            q = (p[s:s + (1 << 16)] - self.origin) / self.voxel_size
            inside = ((q >= 0) & (q <= top)).all(axis=1)
            cells = np.minimum(np.floor(q[inside]), top - 1).astype(np.int64)
            codes = morton_encode(cells)
            j = np.searchsorted(self.leaf_codes, codes)
            j[j == self.num_voxels] = 0
            hit = self.leaf_codes[j] == codes
            out[s + np.flatnonzero(inside)[hit]] = j[hit]
        return out


# ---------------------------------------------------------------------------------------------
# Root cube


def _as_points(points: np.ndarray) -> np.ndarray:
    """Validate an (N, 3) real array → C-contiguous float64 (a copy only when needed)."""
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {p.shape}")
    if not (np.issubdtype(p.dtype, np.floating) or np.issubdtype(p.dtype, np.integer)):
        raise InputError(f"points must be a real float array, got dtype {p.dtype}")
    return np.ascontiguousarray(p, dtype=np.float64)


def _min_max(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis min and max of (N, 3) float64, N > 0 → two (3,) float64; NaN propagates.

    Reducing a C-contiguous (N, 3) array over axis 0 runs an inner loop of
    length 3; viewing it as (N/_TILE, 3·_TILE) rows makes the loop long (≈5× faster).
    """
    m = len(p) - len(p) % _TILE
    parts_lo, parts_hi = [], []
    if m:
        rows = p[:m].reshape(-1, 3 * _TILE)
        parts_lo.append(rows.min(axis=0).reshape(_TILE, 3).min(axis=0))
        parts_hi.append(rows.max(axis=0).reshape(_TILE, 3).max(axis=0))
    if m < len(p):
        parts_lo.append(p[m:].min(axis=0))
        parts_hi.append(p[m:].max(axis=0))
    return np.min(parts_lo, axis=0), np.max(parts_hi, axis=0)


def _depth_for(extent: float, voxel: float) -> int:
    """Smallest d ≥ 0 with voxel·2**d > extent; ValueError past MAX_DEPTH."""
    d = 0
    while d <= MAX_DEPTH and not voxel * float(1 << d) > extent:
        d += 1
    if d > MAX_DEPTH:
        ratio = extent / voxel
        need = f"depth {math.floor(math.log2(ratio)) + 1}" if math.isfinite(ratio) else "an unbounded depth"
        raise InputError(f"an extent of {extent:.6g} m at {voxel:.6g} m voxels needs {need} > {MAX_DEPTH} "
                         f"(at most 2**{MAX_DEPTH} cells per axis); use a coarser voxel_size or split the cloud")
    return d


def _root_cube(lo: np.ndarray, hi: np.ndarray, config: OctreeConfig) -> tuple[np.ndarray, float, int]:
    """Root cube of a cloud with per-axis bounds lo, hi (3,) → origin (3,) float64, voxel size, depth."""
    extent = float(np.max(hi - lo))
    if config.voxel_size is not None:
        voxel = float(config.voxel_size)
        return lo.astype(np.float64), voxel, _depth_for(extent, voxel)
    depth = int(config.depth)
    edge = extent * (1.0 + _DEPTH_PAD) if extent > 0 else 1.0
    return lo.astype(np.float64), edge / float(1 << depth), depth


# ---------------------------------------------------------------------------------------------
# Fast build


def _linear_keys(p: np.ndarray, origin: np.ndarray, voxel: float, dims: np.ndarray, clamp: bool) -> np.ndarray:
    """Linear cell keys of points: (N, 3) float64 → (N,) int64 = (i·ny + j)·nz + k.

    Cells are floor((p − origin) / voxel), clamped to dims − 1 when ``clamp``.
    Streams the cloud in chunks through an L2-sized buffer; the key is built in
    float64 (exact, the caller checks dims.prod() < 2**53).
    """
    n = len(p)
    keys = np.empty(n, dtype=np.int64)
    buf = np.empty((_CHUNK, 3))
    kbuf = np.empty(_CHUNK)
    origin_t = np.tile(origin, _TILE)
    top = (dims - 1).astype(np.float64)
    top_t = np.tile(top, _TILE)
    s_yz, s_z = float(dims[1] * dims[2]), float(dims[2])
    for s in range(0, n, _CHUNK):
        c = min(_CHUNK, n - s)
        b = buf[:c]
        m = c - c % _TILE  # whole rows of _TILE points: long inner loops; the rest broadcast per point
        for src, dst, o, t in ((p[s:s + m].reshape(-1, 3 * _TILE), b[:m].reshape(-1, 3 * _TILE), origin_t, top_t),
                               (p[s + m:s + c], b[m:], origin, top)):
            if len(dst):
                np.subtract(src, o, out=dst)
                np.divide(dst, voxel, out=dst)
                np.floor(dst, out=dst)
                if clamp:
                    np.minimum(dst, t, out=dst)
        k = kbuf[:c]
        np.multiply(b[:, 0], s_yz, out=k)
        k += b[:, 2]
        np.multiply(b[:, 1], s_z, out=b[:, 0])  # column 0 is free now
        k += b[:, 0]
        keys[s:s + c] = k
    return keys


def _linear_keys_int(p: np.ndarray, origin: np.ndarray, voxel: float, dims: np.ndarray) -> np.ndarray:
    """As :func:`_linear_keys` in int64 arithmetic, for grids with dims.prod() ≥ 2**53 (always clamps)."""
    n = len(p)
    keys = np.empty(n, dtype=np.int64)
    for s in range(0, n, _CHUNK):
        q = (p[s:s + _CHUNK] - origin) / voxel
        cells = np.minimum(q.astype(np.int64), dims - 1)
        keys[s:s + _CHUNK] = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    return keys


def _count_cells(keys: np.ndarray, num_cells: int, dense: bool) -> tuple[np.ndarray, np.ndarray]:
    """Occupied cells of linear keys (N,) int64 → ascending unique keys (m,) int64, counts (m,) int64."""
    if dense:
        counts = np.bincount(keys, minlength=num_cells)
        occupied = np.flatnonzero(counts)
        return occupied.astype(np.int64), counts[occupied].astype(np.int64)
    keys = np.sort(keys)
    start = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
    counts = np.diff(np.append(start, len(keys)))
    return keys[start], counts.astype(np.int64)


def _node_table(leaf_codes: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Node table from ascending leaf codes (n,) uint64, n > 0, at level ``depth``.

    Returns node_level (k,) uint8, node_code (k,) uint64, node_children (k, 8)
    int32, node_range (k, 2) int64, breadth-first.
    """
    n = len(leaf_codes)
    codes = [leaf_codes]  # per level, deepest first
    begin = [np.arange(n, dtype=np.int64)]
    end = [np.arange(1, n + 1, dtype=np.int64)]
    parent_of = []  # per level (deepest first): index of each node's parent within the level above
    for _ in range(depth):
        up = codes[-1] >> np.uint64(3)
        first = np.empty(len(up), dtype=bool)
        first[0] = True
        np.not_equal(up[1:], up[:-1], out=first[1:])
        starts = np.flatnonzero(first)
        parent_of.append(np.cumsum(first) - 1)
        codes.append(up[starts])
        begin.append(begin[-1][starts])
        end.append(end[-1][np.append(starts[1:], len(up)) - 1])
    codes.reverse(), begin.reverse(), end.reverse(), parent_of.reverse()  # now level 0 first
    sizes = [len(c) for c in codes]
    offset = np.concatenate([[0], np.cumsum(sizes)])
    k = int(offset[-1])
    if k >= 1 << 31:
        raise InputError(f"octree has {k} nodes; int32 child indices hold at most 2**31 − 1")
    children = np.full((k, 8), -1, dtype=np.int32)
    flat = children.reshape(-1)
    for level in range(depth):  # children of level `level` live at level + 1
        slot = (codes[level + 1] & np.uint64(7)).astype(np.int64)  # octant
        slot += (offset[level] + parent_of[level]) * 8  # flat index of (parent row, octant)
        flat[slot] = np.arange(offset[level + 1], offset[level + 2], dtype=np.int32)
    node_level = np.repeat(np.arange(depth + 1, dtype=np.uint8), sizes)
    node_range = np.empty((k, 2), dtype=np.int64)
    np.concatenate(begin, out=node_range[:, 0])
    np.concatenate(end, out=node_range[:, 1])
    return node_level, np.concatenate(codes), children, node_range


def _empty_octree(origin: np.ndarray, voxel: float, depth: int) -> Octree:
    return Octree(origin=origin, voxel_size=voxel, depth=depth,
                  leaf_codes=np.zeros(0, np.uint64), leaf_counts=np.zeros(0, np.int64),
                  node_level=np.zeros(0, np.uint8), node_code=np.zeros(0, np.uint64),
                  node_children=np.zeros((0, 8), np.int32), node_range=np.zeros((0, 2), np.int64))


def build_octree(points: np.ndarray, config: OctreeConfig = OctreeConfig(),
                 grid_origin: np.ndarray | None = None) -> Octree:
    """Octree of a point cloud; cells with at least ``config.min_points`` points become voxels.

    points: (N, 3) float64 world (float32 and integers are converted). The root
    cube's min corner is the cloud's per-axis minimum, or with ``grid_origin`` (3,) float64
    (``config.voxel_size`` only) the corner of the voxel grid from there that holds it, so
    that octrees of neighbouring parts of a cloud share one grid. With ``config.voxel_size``
    the depth is the smallest d with voxel_size·2**d > the largest extent; with
    ``config.depth`` the voxel is the largest extent·(1 + 1e-9) / 2**depth (1 m
    / 2**depth for a single point). Non-finite points, or a depth past
    :data:`MAX_DEPTH`, raise ValueError. An empty cloud, or one where no cell
    reaches ``min_points``, gives an octree with no voxels and no nodes.
    """
    p = _as_points(points)
    if len(p) == 0:
        voxel = float(config.voxel_size) if config.voxel_size is not None else 1.0 / float(1 << config.depth)
        return _empty_octree(np.zeros(3), voxel, 0 if config.depth is None else int(config.depth))
    lo, hi = _min_max(p)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
        raise InputError(f"points contain NaN or infinite coordinates ({len(bad)} rows, the first is row {bad[0]})")
    if grid_origin is not None:
        if config.voxel_size is None:
            raise InputError("build_octree: a grid origin needs OctreeConfig.voxel_size")
        g = np.asarray(grid_origin, dtype=np.float64).reshape(3)
        lo = g + np.floor((lo - g) / float(config.voxel_size)) * float(config.voxel_size)
    origin, voxel, depth = _root_cube(lo, hi, config)

    # Occupied bounding box of cells. floor((p − origin) / voxel) is monotonic in p, so the max
    # point's cell bounds every cell; it reaches 2**depth only by rounding, and then we clamp.
    top = 1 << depth
    cell_max = np.floor((hi - origin) / voxel)
    clamp = bool((cell_max >= top).any())
    dims = np.minimum(cell_max.astype(np.int64) + 1, top)
    num_cells = int(dims[0]) * int(dims[1]) * int(dims[2])
    if num_cells < _EXACT_FLOAT:
        keys = _linear_keys(p, origin, voxel, dims, clamp)
    else:
        keys = _linear_keys_int(p, origin, voxel, dims)
    # bincount is O(N + cells) but scatters into the count array: with spatially random keys it
    # beats a sort only while that array stays small (measured crossover ≈ 2**24 cells at 15 M points).
    dense = num_cells <= min(2 * len(p), _DENSE_MAX_CELLS)
    cells, counts = _count_cells(keys, num_cells, dense)
    del keys

    keep = counts >= config.min_points
    cells, counts = cells[keep], counts[keep]
    if len(cells) == 0:
        return _empty_octree(origin, voxel, depth)
    i, rest = np.divmod(cells, dims[1] * dims[2])
    j, k = np.divmod(rest, dims[2])
    codes = morton_axes(i, j, k)
    order = np.argsort(codes)  # codes are unique: no need for a stable sort
    leaf_codes, leaf_counts = codes[order], counts[order]
    node_level, node_code, node_children, node_range = _node_table(leaf_codes, depth)
    logger.debug("octree: %d points → %d voxels, %d nodes, depth %d, voxel %.4g m (%s count)",
                 len(p), len(leaf_codes), len(node_code), depth, voxel, "dense" if dense else "sorted")
    return Octree(origin=origin, voxel_size=voxel, depth=depth, leaf_codes=leaf_codes, leaf_counts=leaf_counts,
                  node_level=node_level, node_code=node_code, node_children=node_children, node_range=node_range)


# ---------------------------------------------------------------------------------------------
# Reference and baseline


def _morton_reference(i: int, j: int, k: int) -> int:
    code = 0
    for b in range(MAX_DEPTH):
        code |= ((i >> b) & 1) << (3 * b) | ((j >> b) & 1) << (3 * b + 1) | ((k >> b) & 1) << (3 * b + 2)
    return code


def build_octree_reference(points: np.ndarray, config: OctreeConfig = OctreeConfig()) -> Octree:
    """Slow, obvious version of :func:`build_octree` (a Python loop per point) for tests."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        voxel = float(config.voxel_size) if config.voxel_size is not None else 1.0 / 2 ** config.depth
        return _empty_octree(np.zeros(3), voxel, 0 if config.depth is None else config.depth)
    if not np.isfinite(p).all():
        raise InputError("points contain NaN or infinite coordinates")
    origin = p.min(axis=0)
    extent = max(float(h - o) for h, o in zip(p.max(axis=0), origin))
    if config.voxel_size is not None:
        voxel, depth = float(config.voxel_size), 0
        while not voxel * 2 ** depth > extent:
            depth += 1
        if depth > MAX_DEPTH:
            raise InputError(f"needs depth {depth} > {MAX_DEPTH}")
    else:
        depth = config.depth
        voxel = (extent * (1.0 + _DEPTH_PAD) if extent > 0 else 1.0) / 2 ** depth
    counts: dict[tuple[int, int, int], int] = {}
    for point in p.tolist():
        cell = tuple(min(math.floor((c - o) / voxel), 2 ** depth - 1) for c, o in zip(point, origin.tolist()))
        counts[cell] = counts.get(cell, 0) + 1
    leaves = {_morton_reference(*cell): n for cell, n in counts.items() if n >= config.min_points}
    if not leaves:
        return _empty_octree(origin, voxel, depth)
    leaf_codes = sorted(leaves)
    levels = {depth: leaf_codes}
    for level in range(depth - 1, -1, -1):
        levels[level] = sorted({c >> 3 for c in levels[level + 1]})
    index: dict[tuple[int, int], int] = {}
    for level in range(depth + 1):
        for c in levels[level]:
            index[(level, c)] = len(index)
    children = [[-1] * 8 for _ in index]
    ranges = [[len(leaf_codes), 0] for _ in index]
    for (level, c), i in index.items():
        if level > 0:
            children[index[(level - 1, c >> 3)]][c & 7] = i
    for pos, c in enumerate(leaf_codes):
        for level in range(depth + 1):
            r = ranges[index[(level, c >> (3 * (depth - level)))]]
            r[0], r[1] = min(r[0], pos), max(r[1], pos + 1)
    keys = list(index)
    return Octree(origin=origin, voxel_size=voxel, depth=depth,
                  leaf_codes=np.array(leaf_codes, dtype=np.uint64),
                  leaf_counts=np.array([leaves[c] for c in leaf_codes], dtype=np.int64),
                  node_level=np.array([lv for lv, _ in keys], dtype=np.uint8),
                  node_code=np.array([c for _, c in keys], dtype=np.uint64),
                  node_children=np.array(children, dtype=np.int32).reshape(-1, 8),
                  node_range=np.array(ranges, dtype=np.int64).reshape(-1, 2))


def open3d_octree(points: np.ndarray, depth: int) -> int:
    """Open3D's octree of the cloud at ``depth`` → its number of leaf nodes (the baseline).

    points: (N, 3) float64. Open3D's root cube has the cloud's largest extent
    as its edge, but it is centred on the bounding box along the shorter axes
    (ours starts at the per-axis minimum), and it is half-open: with
    ``size_expand=0`` it drops points on its max faces (ours keeps them in the
    last cell). Leaf counts agree when the bounding box is a cube and the last
    cell holds another point.
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_as_points(points)))
    tree = o3d.geometry.Octree(max_depth=int(depth))
    tree.convert_from_point_cloud(pcd, size_expand=0.0)
    leaves = 0

    def visit(node, info) -> bool:
        nonlocal leaves
        if isinstance(node, o3d.geometry.OctreeLeafNode):
            leaves += 1
        return False

    tree.traverse(visit)
    return leaves
