"""Level of detail of the GPU decode: fewer eigen images where a texel covers less than a pixel.

An eigen image adds view-dependent detail at the scale of a texel. Once a quad's texel is
a fraction of a pixel wide on screen, that detail averages out within the pixel, so far
quads are decoded with fewer eigen images — the decode pass's cost is proportional to
the eigen images decoded. Levels (per quad, from the width of one texel in pixels):

- 0: every eigen image (texel ≥ ``full_texel_px``),
- 1: at most ``reduced_rank`` eigen images,
- 2: the mean only (texel < ``mean_texel_px``).

A quad changes level only when its texel width is ``hysteresis`` beyond a threshold, so
an eye moving back and forth across one does not switch detail every frame (no popping);
the tile is decoded again when its level changes. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

LEVEL_NAMES = ("full", "reduced", "mean")


@dataclass(frozen=True)
class ImpostorConfig:
    """Far nodes as impostors (:mod:`render.impostors`). node_edge (m): the octree level used;
    texels: tile side; max_error_px: parallax (pixels) an image survives; max_angle_deg: turn of
    the direction to the eye an image survives (view-dependent texture); updates_per_frame:
    images remade per frame at most for nodes whose image is stale but still usable;
    in_full_updates_per_frame: images made per frame at most for far nodes drawn in full (no
    image, or one twice past the bounds), which cost about as much every frame as making the
    image once; hysteresis: fraction of the switching distance within which
    a node keeps its state."""

    node_edge: float = 4.0
    texels: int = 128
    max_error_px: float = 1.0
    max_angle_deg: float = 4.0
    updates_per_frame: int = 24
    in_full_updates_per_frame: int = 64
    hysteresis: float = 0.1

    def __post_init__(self):
        if not (np.isfinite(self.node_edge) and self.node_edge > 0):
            raise InputError(f"node_edge must be a positive length, got {self.node_edge}")
        if not 8 <= self.texels <= 1024:
            raise InputError(f"texels must lie in [8, 1024], got {self.texels}")
        if not (np.isfinite(self.max_error_px) and self.max_error_px > 0):
            raise InputError(f"max_error_px must be a positive number of pixels, got {self.max_error_px}")
        if not 0 < self.max_angle_deg <= 30:
            raise InputError(f"max_angle_deg must lie in (0, 30], got {self.max_angle_deg}")
        if self.updates_per_frame < 0:
            raise InputError(f"updates_per_frame must be ≥ 0, got {self.updates_per_frame}")
        if self.in_full_updates_per_frame < 0:
            raise InputError(f"in_full_updates_per_frame must be ≥ 0, got {self.in_full_updates_per_frame}")
        if not 0 <= self.hysteresis < 1:
            raise InputError(f"hysteresis must lie in [0, 1), got {self.hysteresis}")


#: Formats of the GPU decode's decoded atlas: "f16" (RGBA16F, the reference decode's
#: clip(Σ w·D) over the blended directions) or "u8" (RGBA8: each sampled direction's tile
#: clipped to [0, 1] and rounded to 8 bits, then blended).
DECODED_FORMATS = ("f16", "u8")


@dataclass(frozen=True)
class LodConfig:
    """Thresholds (texel width in pixels), the hysteresis band (a fraction of them), the
    impostors of far nodes (None: every quad drawn), the decoded atlas's format
    (:data:`DECODED_FORMATS`; "u8" halves its memory, and llvmpipe filters 8-bit texels in
    integer arithmetic: the draw from it takes about a quarter less time than from half
    floats; without level of detail the decode is exact, "f16") and the refreshes a frame decodes at most
    (``refresh_tiles_per_frame``: tiles decoded again because the eye moved into another
    direction bracket or level, largest on screen first; the rest are drawn from the
    direction their slots hold until a later frame refreshes them, so a sudden turn of the
    eye does not decode the whole view in one frame; None: no limit)."""

    full_texel_px: float = 0.5
    mean_texel_px: float = 0.15
    reduced_rank: int = 2
    hysteresis: float = 0.25
    impostors: ImpostorConfig | None = ImpostorConfig()
    decoded_format: str = "u8"
    refresh_tiles_per_frame: int | None = 4096

    def __post_init__(self):
        if not (0 < self.mean_texel_px <= self.full_texel_px and np.isfinite(self.full_texel_px)):
            raise InputError(f"need 0 < mean_texel_px ≤ full_texel_px, got {self.mean_texel_px}, "
                             f"{self.full_texel_px}")
        if not 0 <= self.reduced_rank <= 255:
            raise InputError(f"reduced_rank must be 0…255, got {self.reduced_rank}")
        if not 0 <= self.hysteresis < 1:
            raise InputError(f"hysteresis must lie in [0, 1), got {self.hysteresis}")
        refresh = self.refresh_tiles_per_frame
        if refresh is not None and (isinstance(refresh, bool) or not isinstance(refresh, (int, np.integer))
                                    or refresh < 0):
            raise InputError(f"refresh_tiles_per_frame must be None or an integer ≥ 0, got {refresh!r}")
        if self.decoded_format not in DECODED_FORMATS:
            raise InputError(f"decoded_format must be one of {DECODED_FORMATS}, got {self.decoded_format!r}")

    @property
    def rank_caps(self) -> np.ndarray:
        """(3,) int64 most eigen images per level."""
        return np.array([255, self.reduced_rank, 0], np.int64)


def texel_pixels(eye, centres: np.ndarray, edge: np.ndarray, tile: int, focal_px: float) -> np.ndarray:
    """(R,) float64 width in pixels of one texel of quads of ``edge`` (R,) metres at ``centres`` (R, 3)
    seen from ``eye`` (3,) with a focal length of ``focal_px`` pixels (at the image centre; an upper
    bound off-axis). A quad around the eye is infinitely large."""
    dist = np.linalg.norm(np.asarray(centres, np.float64) - np.asarray(eye, np.float64).reshape(1, 3), axis=1)
    with np.errstate(divide="ignore"):
        return np.where(dist > 0, focal_px * np.asarray(edge, np.float64) / (tile * dist), np.inf)


def _plain_level(texel_px: np.ndarray, config: LodConfig, scale: float) -> np.ndarray:
    return ((texel_px < config.full_texel_px * scale).astype(np.int8)
            + (texel_px < config.mean_texel_px * scale).astype(np.int8))


def lod_levels(texel_px: np.ndarray, previous: np.ndarray | None, config: LodConfig) -> np.ndarray:
    """(R,) int8 level per quad from its texel width (R,) px; ``previous`` (R,) int8 (−1: none)
    is kept while the width stays within the hysteresis band of its thresholds."""
    level = _plain_level(texel_px, config, 1.0)
    if previous is None or config.hysteresis == 0:
        return level
    finest = _plain_level(texel_px, config, 1.0 - config.hysteresis)
    coarsest = _plain_level(texel_px, config, 1.0 + config.hysteresis)
    keep = (previous >= finest) & (previous <= coarsest)
    return np.where(keep, previous, level).astype(np.int8)
