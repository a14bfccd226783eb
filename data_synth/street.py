"""The ``street`` scene: a straight two-lane road between two rows of buildings.

The road runs along +x from 0 to ``length`` and is centred on y = 0. Buildings
stand on both sides with varied widths, heights, setbacks and gaps; arcades,
free-standing pillars and street-light poles stand in front of the facades
(the occluders that broke the billboards paper's texture sampling).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .scene import Kind, MeshBuilder, Scene


@dataclass(frozen=True)
class StreetConfig:
    length: float = 300.0  # street length along x, metres
    seed: int = 0  # same seed → same scene, byte for byte
    lane_width: float = 3.5  # width of each of the two lanes, metres
    sidewalk_width: float = 3.0  # sidewalk on each side, metres
    kerb_height: float = 0.12  # sidewalk height above the road, metres
    margin: float = 25.0  # buildings and road continue this far past both ends
    building_width: tuple[float, float] = (6.0, 20.0)  # min/max frontage, metres
    building_height: tuple[float, float] = (6.0, 24.0)  # min/max height, metres
    building_depth: tuple[float, float] = (8.0, 15.0)  # min/max depth, metres
    max_setback: float = 3.0  # facades stand 0..max_setback behind the sidewalk
    gap_probability: float = 0.2  # chance of an alley after each building
    gap_width: tuple[float, float] = (1.5, 5.0)  # alley width, metres
    arcade_probability: float = 0.25  # chance that a building has an arcade of pillars
    pole_spacing: float = 12.0  # street-light poles along each kerb, metres apart
    pillar_probability: float = 0.15  # chance of a free-standing pillar in front of a building

    def __post_init__(self):
        if not (np.isfinite(self.length) and self.length > 0):
            raise ValueError(f"StreetConfig.length must be a finite number of metres > 0, got {self.length!r}")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"StreetConfig.seed must be an integer ≥ 0, got {self.seed!r}")


def _layout_side(rng: np.random.Generator, cfg: StreetConfig):
    """Building frontages along one side: (b, 2) x-extents, (b,) setbacks, heights, depths."""
    x = -cfg.margin
    spans, setbacks, heights, depths = [], [], [], []
    end = cfg.length + cfg.margin
    while x < end - cfg.building_width[0]:
        w = min(rng.uniform(*cfg.building_width), end - x)
        spans.append((x, x + w))
        setbacks.append(rng.uniform(0.0, cfg.max_setback) if rng.random() < 0.6 else 0.0)
        heights.append(rng.uniform(*cfg.building_height))
        depths.append(rng.uniform(*cfg.building_depth))
        x += w
        if rng.random() < cfg.gap_probability:
            x += rng.uniform(*cfg.gap_width)
    return np.array(spans), np.array(setbacks), np.array(heights), np.array(depths)


def build_street(cfg: StreetConfig) -> Scene:
    """Generate the street scene for ``cfg`` (deterministic in ``cfg.seed``)."""
    return generate_street(cfg, MeshBuilder()).build("street", asdict(cfg))


def generate_street(cfg: StreetConfig, mb: MeshBuilder) -> MeshBuilder:
    """Walk the street's random sequence, adding its objects to ``mb`` in a fixed order (any
    :class:`MeshBuilder`: one that keeps all, a section's, a digest's); returns ``mb``."""
    rng = np.random.default_rng(cfg.seed)
    half_road = cfg.lane_width
    front0 = half_road + cfg.sidewalk_width  # facade line with zero setback
    x0, x1 = -cfg.margin - 40.0, cfg.length + cfg.margin + 40.0

    def seeds(n: int) -> np.ndarray:
        return rng.integers(0, 2**32, size=n, dtype=np.uint64).astype(np.uint32)

    # open ground under everything, the road, and two raised sidewalks
    g = mb.new_objects(Kind.GROUND, seeds(1))
    mb.add_quads([[x0, -front0 - 60.0]], [[x1, front0 + 60.0]], [-0.02], g)
    r = mb.new_objects(Kind.ROAD, seeds(1))
    mb.add_quads([[x0, -half_road]], [[x1, half_road]], [0.0], r)
    s = mb.new_objects(Kind.SIDEWALK, seeds(2))
    mb.add_boxes([[x0, -front0 - cfg.max_setback, -0.02], [x0, half_road, -0.02]],
                 [[x1, -half_road, cfg.kerb_height], [x1, front0 + cfg.max_setback, cfg.kerb_height]], s)

    for side in (-1.0, 1.0):  # -1: right of the outbound drive (y < 0), +1: left
        spans, setback, height, depth = _layout_side(rng, cfg)
        b = len(spans)
        near = front0 + setback  # |y| of each facade
        far = near + depth
        lo_y = np.where(side < 0, -far, near)
        hi_y = np.where(side < 0, -near, far)
        ids = mb.new_objects(Kind.BUILDING, seeds(b))
        mb.add_boxes(np.stack([spans[:, 0], lo_y, np.zeros(b)], -1),
                     np.stack([spans[:, 1], hi_y, height], -1), ids)

        # arcades: a row of square pillars carrying a beam, 1.8 m in front of the facade
        arcade = rng.random(b) < cfg.arcade_probability
        for i in np.flatnonzero(arcade):
            xa, xb = spans[i]
            n = max(int((xb - xa - 1.0) // 3.0), 1)
            px = np.linspace(xa + 0.5, xb - 0.5, n + 1)
            py = side * (near[i] - 1.8)
            beam_top = min(4.2, height[i] - 0.5)
            pid = mb.new_objects(Kind.PILLAR, seeds(len(px)))
            lo = np.stack([px - 0.2, np.full_like(px, py - 0.2), np.full_like(px, cfg.kerb_height)], -1)
            hi = np.stack([px + 0.2, np.full_like(px, py + 0.2), np.full_like(px, beam_top - 0.4)], -1)
            mb.add_boxes(lo, hi, pid)
            bid = mb.new_objects(Kind.BEAM, seeds(1))
            yb0, yb1 = sorted((py - side * 0.25, side * near[i]))
            mb.add_boxes([[xa + 0.3, yb0, beam_top - 0.4]], [[xb - 0.3, yb1, beam_top]], bid)

        # free-standing pillars (columns, monuments) in front of non-arcaded facades
        single = (~arcade) & (rng.random(b) < cfg.pillar_probability)
        n_single = int(single.sum())
        if n_single:
            cx = rng.uniform(spans[single, 0] + 1.0, np.maximum(spans[single, 1] - 1.0, spans[single, 0] + 1.01))
            cy = side * (near[single] - rng.uniform(0.8, 1.6, n_single))
            hgt = rng.uniform(2.5, 5.0, n_single)
            pid = mb.new_objects(Kind.PILLAR, seeds(n_single))
            mb.add_boxes(np.stack([cx - 0.25, cy - 0.25, np.full(n_single, cfg.kerb_height)], -1),
                         np.stack([cx + 0.25, cy + 0.25, cfg.kerb_height + hgt], -1), pid)

        # street-light poles along the kerb
        px = np.arange(-cfg.margin + rng.uniform(0, cfg.pole_spacing), cfg.length + cfg.margin, cfg.pole_spacing)
        pid = mb.new_objects(Kind.POLE, seeds(len(px)))
        py = np.full_like(px, side * (half_road + 0.45))
        mb.add_prisms(np.stack([px, py], -1), 0.09, cfg.kerb_height, 6.0, pid)

    return mb
