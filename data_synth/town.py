"""The ``town`` scene: a dense grid of narrow streets and small houses.

This is the occlusion-culling case of the Edo townscape paper: tens of
thousands of separate objects (each house with its gable roof is one object
with its own bounding box), almost all of them hidden behind the first row of
houses from any street-level viewpoint. Generation is fully vectorised.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from core.errors import InputError

from .scene import Kind, MeshBuilder, Scene


@dataclass(frozen=True)
class TownConfig:
    size: float = 2000.0  # side of the square town, metres
    seed: int = 0  # same seed → same scene, byte for byte
    street_width: float = 5.0  # narrow streets between blocks, metres
    block_size: float = 36.0  # square block side, metres
    lot_width: float = 6.0  # house lots along a block edge, metres
    house_depth: tuple[float, float] = (6.0, 9.0)  # min/max house depth, metres
    house_height: tuple[float, float] = (3.0, 7.0)  # min/max wall height, metres
    roof_height: tuple[float, float] = (1.2, 2.8)  # min/max ridge height above the walls, metres
    path_street: int = -1  # index of the street the capture path follows (-1: the middle one)

    def __post_init__(self):
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise InputError(f"TownConfig.seed must be an integer ≥ 0, got {self.seed!r}")


def street_centres(cfg: TownConfig) -> np.ndarray:
    """Centre lines of the streets running along x (their y coordinates), (s,) float64."""
    pitch = cfg.block_size + cfg.street_width
    n_blocks = int(cfg.size // pitch)
    return -cfg.size / 2 + pitch * np.arange(n_blocks + 1) + cfg.street_width / 2


def build_town(cfg: TownConfig) -> Scene:
    """Generate the town for ``cfg``: ground, then four rows of houses per block."""
    return generate_town(cfg, MeshBuilder()).build("town", asdict(cfg))


def generate_town(cfg: TownConfig, mb: MeshBuilder) -> MeshBuilder:
    """Walk the town's random sequence into ``mb`` (any :class:`MeshBuilder`); returns ``mb``."""
    rng = np.random.default_rng(cfg.seed)
    pitch = cfg.block_size + cfg.street_width
    n_blocks = int(cfg.size // pitch)
    half = cfg.size / 2
    g = mb.new_objects(Kind.GROUND, rng.integers(0, 2**32, 1, dtype=np.uint64).astype(np.uint32))
    mb.add_quads([[-half - 50, -half - 50]], [[half + 50, half + 50]], [0.0], g)

    # Houses along the two x-running edges of each block (facing the x streets)
    # and along the two y-running edges between them, all axis-aligned.
    starts = -half + cfg.street_width + pitch * np.arange(n_blocks)  # block minimum corner
    n_lots = int(cfg.block_size // cfg.lot_width)
    lot = cfg.block_size / n_lots
    bx, by = np.meshgrid(starts, starts, indexing="ij")
    bx, by = bx.ravel(), by.ravel()
    los, his = [], []
    k = np.arange(n_lots)
    for edge in range(4):
        n = len(bx) * n_lots
        depth = rng.uniform(*cfg.house_depth, n)
        width = lot - rng.uniform(0.3, 1.2, n)
        along = (np.repeat(bx if edge < 2 else by, n_lots) + np.tile(k * lot, len(bx))
                 + rng.uniform(0.0, lot - width))
        if edge < 2:  # rows along x, on the block's south (edge 0) / north (edge 1) side
            y_lo = np.repeat(by, n_lots) if edge == 0 else np.repeat(by, n_lots) + cfg.block_size - depth
            lo = np.stack([along, y_lo], -1)
            hi = np.stack([along + width, y_lo + depth], -1)
        else:  # rows along y on the west/east sides, inset to clear the x rows
            inset = cfg.house_depth[1] + 0.5
            keep = (along > np.repeat(by, n_lots) + inset) & (along + width < np.repeat(by, n_lots) + cfg.block_size - inset)
            x_lo = np.repeat(bx, n_lots) if edge == 2 else np.repeat(bx, n_lots) + cfg.block_size - depth
            lo = np.stack([x_lo, along], -1)[keep]
            hi = np.stack([x_lo + depth, along + width], -1)[keep]
        los.append(lo)
        his.append(hi)
    lo2, hi2 = np.concatenate(los), np.concatenate(his)
    n = len(lo2)
    wall = rng.uniform(*cfg.house_height, n)
    ridge = rng.uniform(*cfg.roof_height, n)
    lo3 = np.concatenate([lo2, np.zeros((n, 1))], axis=1)
    hi3 = np.concatenate([hi2, wall[:, None]], axis=1)
    ids = mb.new_objects(Kind.HOUSE, rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32))
    mb.add_boxes(lo3, hi3, ids)
    # Roofs share the house's object id: one object per house, as the culling paper counts them.
    mb.add_gable_roofs(lo3, hi3, ridge, ids)
    return mb
