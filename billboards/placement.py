"""The quads of a cloud placed for sampling: :class:`Billboards`, from the voxel leaves of an
octree alone (:func:`place_billboards`) or with the blocks of a facade layer
(:func:`place_hybrid`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .geometry import BILLBOARD, base_yaw_toward, default_quad_arrays
from .layer import Layer
from .octree import Octree, OctreeConfig, build_octree
from .planes import PlaneConfig, with_planes
from .sampling import ImageSampler, SamplingConfig
from .splat import PointSampler
from .views import Views
from .voxels import VoxelPoints, quad_centres, voxel_points


@dataclass(frozen=True, eq=False)
class Billboards:
    """The voxels of a cloud, ready for sampling.

    octree: the voxel leaves; leaf (N,) int64 billboard of each point (−1: none);
    voxels: the points grouped by billboard (cube centres, for z-buffers and slabs);
    base_yaw (n,) float64 world yaw toward the capture path; quads (n, 3) float64
    quad centres on the surface (:func:`~billboards.voxels.quad_centres`); kind (n,) uint8 quad
    kinds; node_range (k, 2) int64 [begin, end) billboards under each octree node; unseen (n,)
    bool the continued ground blocks no camera sees (their textures are synthesised,
    :mod:`billboards.synthesis`); split (n,) uint8 a quad's edge is its kind's halved this many
    times (:mod:`billboards.resolution`); cell (n, 3) float64 the centre of the unsplit block a
    ground block was split from (None: the quads); corner_dz (n, 4) float64 the heights of a ground
    block's corners above its centre (the ground's height field; None: all flat).
    Without a facade layer there is one billboard per voxel leaf, in leaf order; with one,
    a leaf holds its billboard (if its own points make one) and the layer blocks whose
    centres lie in it, so that culling by the octree covers both.
    """

    octree: Octree
    leaf: np.ndarray
    voxels: VoxelPoints
    base_yaw: np.ndarray
    quads: np.ndarray
    kind: np.ndarray
    node_range: np.ndarray
    block_size: float | None = None
    unseen: np.ndarray | None = None
    split: np.ndarray | None = None
    cell: np.ndarray | None = None
    corner_dz: np.ndarray | None = None

    def __post_init__(self):
        default_quad_arrays(self, self.quads, unseen=False)

    @property
    def num_billboards(self) -> int:
        return len(self.kind)

    def image_sampler(self, views: Views, config: SamplingConfig) -> ImageSampler:
        return ImageSampler(views, self.quads, self.octree.voxel_size, self.base_yaw, self.voxels, config,
                            box_centres=self.voxels.centres, kind=self.kind, block_size=self.block_size,
                            split=self.split, corner_dz=self.corner_dz)

    def voxel_colours(self, colours: np.ndarray) -> np.ndarray:
        """(N', 3) uint8 colours of the points in voxels, in the order of ``voxels.points``."""
        keep = self.leaf >= 0
        return colours[keep][np.argsort(self.leaf[keep], kind="stable")]

    def point_sampler(self, colours: np.ndarray, config: SamplingConfig) -> PointSampler:
        return PointSampler(self.voxels, self.voxel_colours(colours), self.base_yaw, config, centres=self.quads)


def place_billboards(points: np.ndarray, octree: Octree, viewpoints: np.ndarray | None,
                     planes: PlaneConfig | None = None) -> Billboards:
    """Group ``points`` (N, 3) float64 by the voxels of ``octree`` and place their quads,
    facing ``viewpoints`` (v, 3) float64 camera centres (None: base yaw 0); planar leaves
    become quads in their plane by ``planes`` (None: none, :func:`~billboards.planes.with_planes`)."""
    centres = octree.centres()
    leaf = octree.leaves_of_points(points)
    voxels = voxel_points(points, leaf, centres, octree.origin, octree.voxel_size)
    base_yaw = base_yaw_toward(centres, np.zeros((0, 3)) if viewpoints is None else viewpoints)
    return with_planes(Billboards(octree, leaf, voxels, base_yaw, quad_centres(voxels, base_yaw),
                                  np.full(len(centres), BILLBOARD, np.uint8), octree.node_range.astype(np.int64)),
                       planes)


def place_hybrid(points: np.ndarray, config: OctreeConfig, viewpoints: np.ndarray, layer: Layer,
                 block_size: float | None = None, grid_origin: np.ndarray | None = None,
                 planes: PlaneConfig | None = None) -> Billboards:
    """Billboards where the cloud departs from the facade ``layer``, and the layer's blocks.

    points (N, 3) float64 world; viewpoints (v, 3) float64 camera centres; block_size: edge of
    the layer's blocks (m; None: the voxel size). The octree is
    built over the points the layer does not explain plus each block's centre (counted
    ``min_points`` times, so every block's cell is a leaf; on the voxel grid from ``grid_origin``
    when given, see :func:`~billboards.octree.build_octree`); a leaf gets a billboard when
    at least ``min_points`` unexplained points fall in it. Billboards are ordered by leaf
    (Morton order), a leaf's billboard before its blocks; planar leaves become quads in their
    plane by ``planes`` (None: none, :func:`~billboards.planes.with_planes`).
    """
    points = np.asarray(points, np.float64)
    free = np.flatnonzero(~layer.explained)
    anchors = np.concatenate([points[free], np.repeat(layer.centres, config.min_points, axis=0)])
    octree = build_octree(anchors, config, grid_origin)
    n_leaves = octree.num_voxels
    free_leaf = octree.leaves_of_points(points[free])
    counts = np.bincount(free_leaf[free_leaf >= 0], minlength=n_leaves)
    board_leaves = np.flatnonzero(counts >= config.min_points)
    block_leaves = octree.leaves_of_points(layer.centres) if len(layer.centres) else np.zeros(0, np.int64)
    if np.any(block_leaves < 0):
        raise AssertionError("a layer block fell outside the octree built around it")
    item_leaf = np.concatenate([board_leaves, block_leaves])
    item_kind = np.concatenate([np.full(len(board_leaves), BILLBOARD, np.uint8), layer.kind])
    source = np.concatenate([board_leaves, np.arange(len(block_leaves))])  # leaf (billboard) or block index
    order = np.lexsort((np.arange(len(item_leaf)), item_kind, item_leaf))
    item_leaf, item_kind, source = item_leaf[order], item_kind[order], source[order]
    is_board = item_kind == BILLBOARD
    # Each point's billboard: unexplained points of a billboard leaf, and points on a block.
    item_of_board_leaf = np.full(max(n_leaves, 1), -1, np.int64)  # (a tile's part may have no leaf)
    item_of_board_leaf[source[is_board]] = np.flatnonzero(is_board)
    item_of_block = np.full(len(layer.centres), -1, np.int64)
    item_of_block[source[~is_board]] = np.flatnonzero(~is_board)
    owner = np.full(len(points), -1, np.int64)
    owner[free] = np.where(free_leaf >= 0, item_of_board_leaf[np.maximum(free_leaf, 0)], -1)
    on_block = np.flatnonzero(layer.explained)
    owner[on_block] = item_of_block[layer.point_block[on_block]]
    leaf_centres = octree.centres()
    box_centres = np.where(is_board[:, None], leaf_centres[item_leaf],
                           layer.centres[np.where(is_board, 0, source)] if len(layer.centres) else 0.0)
    voxels = voxel_points(points, owner, box_centres, octree.origin, octree.voxel_size)
    if block_size is not None:  # a block's points reach up to a block and a half from its centre
        voxels = replace(voxels, reach=1.5 * float(block_size))
    base_yaw = base_yaw_toward(box_centres, viewpoints)
    blocks = ~is_board
    base_yaw[blocks] = layer.base_yaw[source[blocks]]
    quads = quad_centres(voxels, base_yaw)
    quads[blocks] = box_centres[blocks]
    item_begin = np.searchsorted(item_leaf, np.arange(n_leaves + 1))
    node_range = item_begin[octree.node_range]
    unseen = np.zeros(len(item_kind), bool)
    unseen[blocks] = layer.synthesised[source[blocks]]
    split = np.zeros(len(item_kind), np.uint8)
    split[blocks] = layer.split[source[blocks]]
    cell = quads.copy()
    cell[blocks] = layer.cell[source[blocks]]
    corner_dz = np.zeros((len(item_kind), 4))
    corner_dz[blocks] = layer.corner_dz[source[blocks]]
    return with_planes(Billboards(octree, owner, voxels, base_yaw, quads, item_kind, node_range, block_size, unseen,
                                  split, cell, corner_dz), planes)
