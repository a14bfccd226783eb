"""The settings of the billboard stage, :class:`BuildConfig`, and their JSON form."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

import numpy as np

from core.errors import InputError
from recon.epi import EpiConfig

from .fit import FitConfig
from .geometry import DirectionConfig
from .layer import LayerConfig
from .octree import OctreeConfig
from .pca import PcaConfig
from .photometry import PhotometryConfig
from .planes import PlaneConfig
from .sampling import SamplingConfig

#: Where textures come from: the captured images, or the cloud's own points.
SOURCES = ("images", "points")


@dataclass(frozen=True)
class BuildConfig:
    """The settings of the billboard stage (:func:`billboards.build.main`)."""

    octree: OctreeConfig = field(default_factory=OctreeConfig)        # voxel size, min points
    sampling: SamplingConfig = field(default_factory=SamplingConfig)  # directions, texels, occlusion test
    pca: PcaConfig = field(default_factory=PcaConfig)                 # rank rule
    source: str = "images"       # "images" (project the captured images) or "points" (splat the cloud)
    tile_mode: str = "u8"        # eigen/mean tiles: "u8" (per-tile scale/offset) or "f16"
    coef_mode: str = "f16"       # coefficients: "f32", "f16" or "u8"
    page_size: int = 8192        # atlas page edge (texels); the renderer passes GL_MAX_TEXTURE_SIZE
    chunk: int = 128             # billboards sampled and compressed together (bounds memory)
    task_chunks: int = 8         # chunks per worker task (neighbouring billboards share cached images)
    error_stride: int = 4        # decode PSNR is measured on every n-th billboard (1: all)
    holdout: int = 0             # leave every n-th frame's images out of the sampling (for novel-view tests; 0: none)
    layer: LayerConfig | None = field(default_factory=LayerConfig)  # the facade layer (None: billboards only)
    planes: PlaneConfig | None = None  # planar leaves as quads in their plane (None: every leaf a billboard;
                                       # off by default: measured no better, docs/surfaces/README.md)
    photometry: PhotometryConfig | None = field(default_factory=PhotometryConfig)  # per-image gains divided out
                                                                                  # before sampling (None: off)
    fit: FitConfig | None = field(default_factory=FitConfig)  # textures fitted to the training images through
                                                             # the rendering (billboards.fit; None: as sampled)
    fit_views_per_task: int = 12      # training views ray cast per worker task of the fit
    tile_metres: float | None = None  # build a model set of square tiles this wide (m, whole voxels; None: one model)
    tile_margin: float = 8.0          # a tile's context: its neighbours' points this near (m; layer, occlusion)
    sample_points: int = 2_000_000    # a tiled build estimates gains and sky from at most this many cloud points

    def __post_init__(self):
        if self.source not in SOURCES:
            raise InputError(f"source must be one of {SOURCES}, got {self.source!r}")
        if self.holdout < 0 or self.holdout == 1:
            raise InputError("holdout must be 0 (none) or ≥ 2 (every n-th frame left out)")
        if self.chunk < 1 or self.task_chunks < 1 or self.error_stride < 1:
            raise InputError("chunk, task_chunks and error_stride must be ≥ 1")
        if self.tile_metres is not None and not (np.isfinite(self.tile_metres) and self.tile_metres > 0):
            raise InputError(f"tile_metres must be a finite number > 0 or None, got {self.tile_metres!r}")
        if not (np.isfinite(self.tile_margin) and self.tile_margin >= 0) or self.sample_points < 1:
            raise InputError("tile_margin must be finite and ≥ 0, sample_points ≥ 1")
        if self.fit_views_per_task < 1:
            raise InputError("fit_views_per_task must be ≥ 1")


def config_to_json(conf: BuildConfig) -> dict:
    """``conf`` as plain JSON values (tuples become lists): the build report's "config", the
    worker state's settings and what names a tiled build's work directory."""
    return json.loads(json.dumps(asdict(conf)))


def config_from_json(data: dict) -> BuildConfig:
    """The :class:`BuildConfig` that :func:`config_to_json` wrote as ``data``."""
    s = data["sampling"]
    sampling = SamplingConfig(**{**s, "directions": DirectionConfig(**{**s["directions"],
                                                                        "pitches_deg": tuple(s["directions"]["pitches_deg"])})})
    layer = data.get("layer")
    if layer is not None:
        layer = LayerConfig(**{**layer, "epi": EpiConfig(**layer["epi"])})
    photometry = data.get("photometry")
    if photometry is not None:
        photometry = PhotometryConfig(**photometry)
    fit = data.get("fit")
    if fit is not None:
        fit = FitConfig(**fit)
    planes = data.get("planes")
    if planes is not None:
        planes = PlaneConfig(**planes)
    return BuildConfig(**{**data, "octree": OctreeConfig(**data["octree"]), "sampling": sampling,
                          "pca": PcaConfig(**data["pca"]), "layer": layer, "photometry": photometry, "fit": fit,
                          "planes": planes})
