"""The ``street`` scene: a straight two-lane road between two rows of buildings.

The road runs along +x from 0 to ``length`` and is centred on y = 0. Buildings
stand on both sides with varied widths, heights, setbacks and gaps; arcades,
free-standing pillars and street-light poles stand in front of the facades
(the occluders that broke the billboards paper's texture sampling).

A street may open into a **square** (``square`` > 0, metres): the building of the right-hand
row (y < 0) whose frontage is centred nearest the street's middle (:func:`free_building`)
then stands alone. Every other building whose footprint comes within ``square`` of its
footprint's centre is left out, with its arcade and pillars, and so are the building's own
occluders and every pillar, beam and pole that comes that near; the ground, road and
sidewalks stay. Nothing else changes: the random sequence is walked as without a square,
so the street outside it is the plain street of the same seed, object for object.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from core.errors import InputError

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
    square: float = 0.0  # radius of an open square around one free-standing building, metres (0: none)

    def __post_init__(self):
        if not (np.isfinite(self.length) and self.length > 0):
            raise InputError(f"StreetConfig.length must be a finite number of metres > 0, got {self.length!r}")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise InputError(f"StreetConfig.seed must be an integer ≥ 0, got {self.seed!r}")
        if isinstance(self.square, bool) or not isinstance(self.square, (int, float)) \
                or not (np.isfinite(self.square) and self.square >= 0):
            raise InputError(f"StreetConfig.square must be a finite number of metres ≥ 0 (0: no square), "
                             f"got {self.square!r}")


def street_settings(cfg: StreetConfig) -> dict:
    """The JSON object of ``cfg`` that ``gt/scene.json`` and ``dataset.json`` hold: its fields,
    less ``square`` when there is none (streets keep the bytes they had before squares)."""
    data = asdict(cfg)
    if not cfg.square:
        del data["square"]
    return data


#: Seeds drawn for the ground, the road and the two sidewalks before the buildings' rows.
_SURFACE_SEEDS = (1, 1, 2)


def _seeds(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.integers(0, 2**32, size=n, dtype=np.uint64).astype(np.uint32)


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


def _footprints(cfg: StreetConfig, side: float, spans: np.ndarray, setback: np.ndarray,
                depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """xy corners lo, hi (b, 2) of one row's buildings (``side`` −1: y < 0, +1: y > 0)."""
    near = cfg.lane_width + cfg.sidewalk_width + setback  # |y| of each facade
    far = near + depth
    lo_y, hi_y = np.where(side < 0, -far, near), np.where(side < 0, -near, far)
    return np.stack([spans[:, 0], lo_y], -1), np.stack([spans[:, 1], hi_y], -1)


def free_building(cfg: StreetConfig) -> tuple[np.ndarray, np.ndarray]:
    """xy corners lo, hi (2,) float64 of the building that stands alone in the street's square
    (see the module doc; with ``square`` 0 the building it would be): of the right-hand row
    (y < 0), the one whose frontage is centred nearest x = length / 2 (the first on a tie)."""
    rng = np.random.default_rng(cfg.seed)
    for n in _SURFACE_SEEDS:  # the draws before the right-hand row's layout, as generate_street makes them
        _seeds(rng, n)
    spans, setback, _, depth = _layout_side(rng, cfg)
    lo, hi = _footprints(cfg, -1.0, spans, setback, depth)
    i = int(np.argmin(np.abs(spans.mean(axis=1) - cfg.length / 2)))
    return lo[i], hi[i]


def _clear_of(centre: np.ndarray | None, radius: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(b,) bool: the boxes (xy corners lo, hi (b, ≥2)) that stay farther than ``radius`` from
    ``centre`` (2,) (all of them without a centre)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if centre is None:
        return np.ones(len(lo), dtype=bool)
    gap = np.maximum(np.maximum(lo[:, :2] - centre, centre - hi[:, :2]), 0.0)
    return np.hypot(gap[:, 0], gap[:, 1]) > radius


def build_street(cfg: StreetConfig) -> Scene:
    """Generate the street scene for ``cfg`` (deterministic in ``cfg.seed``)."""
    return generate_street(cfg, MeshBuilder()).build("street", street_settings(cfg))


def generate_street(cfg: StreetConfig, mb: MeshBuilder) -> MeshBuilder:
    """Walk the street's random sequence, adding its objects to ``mb`` in a fixed order (any
    :class:`MeshBuilder`: one that keeps all, a section's, a digest's); returns ``mb``. Objects
    in the square (``cfg.square``) are drawn and left out, so the sequence stays the same."""
    rng = np.random.default_rng(cfg.seed)
    half_road = cfg.lane_width
    front0 = half_road + cfg.sidewalk_width  # facade line with zero setback
    x0, x1 = -cfg.margin - 40.0, cfg.length + cfg.margin + 40.0
    centre, alone = None, None  # the square's centre (2,) and its building's corners
    if cfg.square > 0:
        alone = free_building(cfg)
        centre = (alone[0] + alone[1]) / 2

    def clear(lo, hi) -> np.ndarray:
        return _clear_of(centre, cfg.square, lo, hi)

    # open ground under everything, the road, and two raised sidewalks
    ground, road, sidewalks = (_seeds(rng, n) for n in _SURFACE_SEEDS)
    g = mb.new_objects(Kind.GROUND, ground)
    mb.add_quads([[x0, -front0 - 60.0]], [[x1, front0 + 60.0]], [-0.02], g)
    r = mb.new_objects(Kind.ROAD, road)
    mb.add_quads([[x0, -half_road]], [[x1, half_road]], [0.0], r)
    s = mb.new_objects(Kind.SIDEWALK, sidewalks)
    mb.add_boxes([[x0, -front0 - cfg.max_setback, -0.02], [x0, half_road, -0.02]],
                 [[x1, -half_road, cfg.kerb_height], [x1, front0 + cfg.max_setback, cfg.kerb_height]], s)

    for side in (-1.0, 1.0):  # -1: right of the outbound drive (y < 0), +1: left
        spans, setback, height, depth = _layout_side(rng, cfg)
        b = len(spans)
        near = front0 + setback  # |y| of each facade
        lo2, hi2 = _footprints(cfg, side, spans, setback, depth)
        # in a square: the buildings clear of it stand, and its own building, without occluders
        own = np.all(lo2 == alone[0], axis=1) & np.all(hi2 == alone[1], axis=1) if alone is not None \
            else np.zeros(b, dtype=bool)
        stands = clear(lo2, hi2) | own
        ids = mb.new_objects(Kind.BUILDING, _seeds(rng, b)[stands])
        if stands.any():
            mb.add_boxes(np.concatenate([lo2, np.zeros((b, 1))], -1)[stands],
                         np.concatenate([hi2, height[:, None]], -1)[stands], ids)
        fronted = stands & ~own  # buildings whose occluders may stand

        # arcades: a row of square pillars carrying a beam, 1.8 m in front of the facade
        arcade = rng.random(b) < cfg.arcade_probability
        for i in np.flatnonzero(arcade):
            xa, xb = spans[i]
            n = max(int((xb - xa - 1.0) // 3.0), 1)
            px = np.linspace(xa + 0.5, xb - 0.5, n + 1)
            py = side * (near[i] - 1.8)
            beam_top = min(4.2, height[i] - 0.5)
            pillar_seeds, beam_seed = _seeds(rng, len(px)), _seeds(rng, 1)
            lo = np.stack([px - 0.2, np.full_like(px, py - 0.2), np.full_like(px, cfg.kerb_height)], -1)
            hi = np.stack([px + 0.2, np.full_like(px, py + 0.2), np.full_like(px, beam_top - 0.4)], -1)
            yb0, yb1 = sorted((py - side * 0.25, side * near[i]))
            beam_lo, beam_hi = [[xa + 0.3, yb0, beam_top - 0.4]], [[xb - 0.3, yb1, beam_top]]
            if not (fronted[i] and clear(lo, hi).all() and clear(beam_lo, beam_hi).all()):
                continue  # an arcade stands whole or not at all
            mb.add_boxes(lo, hi, mb.new_objects(Kind.PILLAR, pillar_seeds))
            mb.add_boxes(beam_lo, beam_hi, mb.new_objects(Kind.BEAM, beam_seed))

        # free-standing pillars (columns, monuments) in front of non-arcaded facades
        single = (~arcade) & (rng.random(b) < cfg.pillar_probability)
        n_single = int(single.sum())
        if n_single:
            cx = rng.uniform(spans[single, 0] + 1.0, np.maximum(spans[single, 1] - 1.0, spans[single, 0] + 1.01))
            cy = side * (near[single] - rng.uniform(0.8, 1.6, n_single))
            hgt = rng.uniform(2.5, 5.0, n_single)
            lo = np.stack([cx - 0.25, cy - 0.25, np.full(n_single, cfg.kerb_height)], -1)
            hi = np.stack([cx + 0.25, cy + 0.25, cfg.kerb_height + hgt], -1)
            keep = fronted[single] & clear(lo, hi)
            pid = mb.new_objects(Kind.PILLAR, _seeds(rng, n_single)[keep])
            if keep.any():
                mb.add_boxes(lo[keep], hi[keep], pid)

        # street-light poles along the kerb
        px = np.arange(-cfg.margin + rng.uniform(0, cfg.pole_spacing), cfg.length + cfg.margin, cfg.pole_spacing)
        py = np.full_like(px, side * (half_road + 0.45))
        keep = clear(np.stack([px - 0.09, py - 0.09], -1), np.stack([px + 0.09, py + 0.09], -1))
        pid = mb.new_objects(Kind.POLE, _seeds(rng, len(px))[keep])
        if keep.any():
            mb.add_prisms(np.stack([px, py], -1)[keep], 0.09, cfg.kerb_height, 6.0, pid)

    return mb
