"""Procedural materials, evaluated at ray hits.

Every function maps hit points to colours with detail down to about a
centimetre (bricks, mortar, window frames, sign lettering, asphalt grain), so
that stereo has something to match at street distances. Colours are floats in
[0, 1], display-referred. All randomness comes from object seeds through
:mod:`data_synth.noise`, so the same scene renders the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from core.arrays import mix_rows, put_rows, row_norms, select_rows

from .noise import fbm, rand01, value_noise
from .scene import Kind, Scene

#: Direction towards the sun (world, unit) and the share of ambient light.
SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
AMBIENT = 0.55


@dataclass(frozen=True)
class Hits:
    """Ray hits on objects of one kind.

    p: (n, 3) float64 points; normal: (n, 3) float64 unit normals;
    obj: (n,) int object ids; scene: the scene (object tables);
    view: (n, 3) float64 unit directions from the eye to each hit, or None
    (seen head-on, along −normal: the colour a view-independent caller gets).
    """

    p: np.ndarray
    normal: np.ndarray
    obj: np.ndarray
    scene: Scene
    view: np.ndarray | None = None

    def view_dirs(self) -> np.ndarray:
        """(n, 3) float64 unit eye → hit directions (−normal where no view was given)."""
        return -self.normal if self.view is None else self.view

    @cached_property
    def lo(self) -> np.ndarray:
        """(n, 3) float64 minimum of each hit's object box."""
        return np.take(self.scene.object_bounds[:, 0], self.obj, axis=0)

    @cached_property
    def hi(self) -> np.ndarray:
        """(n, 3) float64 maximum of each hit's object box."""
        return np.take(self.scene.object_bounds[:, 1], self.obj, axis=0)

    @cached_property
    def seed(self) -> np.ndarray:
        """(n,) int64 texture seed of each hit's object."""
        return self.scene.object_seed[self.obj].astype(np.int64)

    def param(self, key: int, lo: float, hi: float) -> np.ndarray:
        """Per-object parameter in [lo, hi), hashed once per object → (n,)."""
        return (lo + (hi - lo) * rand01(self.scene.object_seed, key))[self.obj]

    def palette(self, key: int, colours: np.ndarray) -> np.ndarray:
        """One of ``colours`` (p, 3) per object → (n, 3)."""
        idx = (rand01(self.scene.object_seed, key) * len(colours)).astype(np.int64)
        return np.take(colours[idx], self.obj, axis=0)

    def subset(self, mask: np.ndarray) -> "Hits":
        return Hits(select_rows(self.p, mask), select_rows(self.normal, mask), self.obj[mask], self.scene,
                    None if self.view is None else select_rows(self.view, mask))


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Colour a (n, 3) where t (n,) bool is False, b where True."""
    return mix_rows(a, b, t)


def _where(mask: np.ndarray, colour: np.ndarray, fn, *args) -> None:
    """colour[mask] = fn(*(arg[mask] for arg in args)): evaluate costly detail only where it shows."""
    if mask.any():
        put_rows(colour, np.flatnonzero(mask), fn(*(select_rows(a, mask) if isinstance(a, np.ndarray) and a.ndim
                                                    and len(a) == len(mask) else a for a in args)))


_PLASTER = np.array([[0.86, 0.80, 0.70], [0.78, 0.74, 0.68], [0.90, 0.86, 0.78], [0.72, 0.62, 0.52],
                     [0.80, 0.70, 0.58], [0.66, 0.70, 0.72], [0.88, 0.78, 0.62]])
_BRICK = np.array([[0.62, 0.30, 0.22], [0.55, 0.35, 0.28], [0.70, 0.45, 0.32], [0.48, 0.26, 0.20]])
_SIGN = np.array([[0.75, 0.12, 0.10], [0.10, 0.30, 0.65], [0.12, 0.50, 0.22], [0.85, 0.65, 0.10],
                  [0.20, 0.20, 0.22]])


def facade_uv(p: np.ndarray, normal: np.ndarray, lo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wall coordinates of hits on vertical faces.

    p: (n, 3) float64 hits; normal: (n, 3); lo: (n, 3) object box minimum.
    Returns u (n,) along the wall and v (n,) height above the object's base, metres.
    """
    along_x = np.abs(normal[:, 1]) >= np.abs(normal[:, 0])
    u = np.where(along_x, p[:, 0] - lo[:, 0], p[:, 1] - lo[:, 1])
    v = p[:, 2] - lo[:, 2]
    return u, v


def _bricks(u, v, seed, base):
    """Running-bond brick wall with mortar and per-brick tone."""
    row = np.floor(v / 0.075)
    shift = 0.5 * (row.astype(np.int64) & 1)
    x = u / 0.25 + shift
    col = np.floor(x)
    mortar = ((v / 0.075 - row) < 0.14) | ((x - col) < 0.045)
    tone = 0.78 + 0.4 * rand01(seed, col, row)
    grain = 0.9 + 0.2 * value_noise(u, v, 0.012, seed + 11)
    brick = base * (tone * grain)[:, None]
    return _mix(brick, 0.72 * grain[:, None] * np.ones(3), mortar)


def _plaster(u, v, seed, base):
    """Rendered wall: fine grain plus blotches."""
    n = 0.82 + 0.18 * fbm(u, v, 0.35, seed, octaves=2) + 0.12 * (value_noise(u, v, 0.01, seed + 3) - 0.5)
    return base * n[:, None]


def _sign_letters(u, fy, seed, top, colour):
    """Shop sign board with a 5x7 dot matrix of pseudo letters (sharp, high-frequency)."""
    x = u / 0.32
    cx = np.floor(x)
    dots_x = np.floor((x - cx) * 6.0)  # 5 dot columns + 1 spacing column
    dots_y = np.floor(np.clip((top - fy) / 0.42, 0, 0.999) * 9.0) - 1  # 7 dot rows with margins
    lit = (rand01(seed, cx, dots_x, dots_y) < 0.5) & (dots_x < 5) & (dots_y >= 0) & (dots_y < 7)
    lit &= rand01(seed, cx, 99) < 0.85  # spaces between words
    return _mix(colour, np.full_like(colour, 0.95), lit)


#: Glass: reflectance at normal incidence (Schlick's F0), per building in this range
#: (single panes about 0.04; double glazing and coatings reflect more).
GLASS_F0 = (0.06, 0.15)


def fresnel_schlick(cos_theta: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """Schlick's reflectance F0 + (1 − F0)(1 − cos θ)⁵. cos_theta, f0: (n,) → (n,) in [F0, 1]."""
    c = np.clip(cos_theta, 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def _glass(u, v, fy, seed, sill_y, win_h, lit_room, normal, view, f0):
    """Window panes: the room behind (dark, some lit) plus the sky mirrored in the pane.

    The view ray (n, 3) unit is mirrored about the pane's normal (n, 3) and looks up
    :func:`sky`; Schlick's Fresnel weight (F0 per building, more at grazing angles)
    mixes it with the interior. The result is radiance (not lit again by the sun)
    and depends on the direction the pane is seen from: stereo finds no stable
    texture on it, as on real glass.
    """
    t = np.clip((fy - sill_y) / win_h, 0.0, 1.0)
    dim = 0.8 + 0.4 * value_noise(u, v, 0.3, seed + 5) - 0.15 * t  # curtains, furniture, ceiling shadow
    interior = np.array([0.07, 0.075, 0.085]) * dim[:, None]
    interior = np.where(lit_room[:, None], np.array([0.55, 0.45, 0.28]) * dim[:, None], interior)
    cos_theta = -np.einsum("ij,ij->i", view, normal)
    mirrored = view + 2.0 * cos_theta[:, None] * normal
    weight = fresnel_schlick(np.abs(cos_theta), f0)[:, None]
    return (1.0 - weight) * interior + weight * sky(mirrored)


_FRAMES = np.array([[0.95, 0.95, 0.93], [0.25, 0.22, 0.20], [0.45, 0.30, 0.18]])
_DOORS = np.array([[0.40, 0.24, 0.12], [0.18, 0.22, 0.30], [0.30, 0.10, 0.08]])


def facade(h: Hits, house: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Building walls: bricks or plaster, windows with frames, mullions and sills,
    a door, shop windows and a lettered sign on the ground floor; flat roofs on top.
    Returns colour (n, 3) float64 and radiance (n,) bool: True where the colour is
    already the light leaving the surface (glass), not an albedo to light."""
    p, normal, seed = h.p, h.normal, h.seed
    lo, hi = h.lo, h.hi
    u, v = facade_uv(p, normal, lo)
    width = np.where(np.abs(normal[:, 1]) >= np.abs(normal[:, 0]), hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1])
    colour = np.empty((len(p), 3))
    brick = h.param(1, 0, 1) < (0.2 if house else 0.45)
    _where(brick, colour, _bricks, u, v, seed, h.palette(2, _BRICK))
    _where(~brick, colour, _plaster, u, v, seed, h.palette(3, _PLASTER))

    floor_h = h.param(4, 2.8, 3.1) if house else h.param(4, 3.0, 3.6)
    pitch = h.param(5, 2.2, 3.4)
    win_w = np.minimum(h.param(6, 0.9, 1.4), pitch - 0.6)
    win_h = h.param(7, 1.2, 1.7)
    frame_col = h.palette(8, _FRAMES)
    storey = np.floor(v / floor_h)
    fy = v - storey * floor_h
    n_cols = np.maximum(np.floor((width - 0.8) / pitch), 1.0)
    cu = (u - 0.5 * (width - n_cols * pitch)) / pitch
    col = np.floor(cu)
    fx = (cu - col - 0.5) * pitch  # metres from the window axis
    in_cols = (col >= 0) & (col < n_cols)

    cornice = np.flatnonzero((fy < 0.12) & (storey >= 1))
    put_rows(colour, cornice, np.take(colour, cornice, axis=0) * 0.7 + 0.1)

    upper = (storey >= 1) & in_cols & (v < hi[:, 2] - 0.6)
    sill_y, border = 0.9, 0.07
    win = upper & (np.abs(fx) < win_w / 2) & (fy > sill_y) & (fy < sill_y + win_h)
    inner = win & (np.abs(fx) < win_w / 2 - border) & (fy > sill_y + border) & (fy < sill_y + win_h - border)
    mullion = inner & ((np.abs(fx) < 0.03) | (np.abs(fy - sill_y - 0.62 * win_h) < 0.03))
    colour = _mix(colour, frame_col, win & ~inner)
    pane = inner & ~mullion
    lit_room = rand01(seed, col, storey, 3) < 0.15
    view, f0 = h.view_dirs(), h.param(14, *GLASS_F0)
    _where(pane, colour, _glass, u, v, fy, seed, sill_y, win_h, lit_room, normal, view, f0)
    radiance = pane.copy()
    colour = _mix(colour, frame_col, mullion)
    sill = upper & (np.abs(fx) < win_w / 2 + 0.08) & (fy > sill_y - 0.08) & (fy <= sill_y)
    put_rows(colour, np.flatnonzero(sill), 0.85)

    ground = (storey == 0) & in_cols
    door = ground & (col == np.floor(h.param(9, 0, 1) * n_cols)) & (np.abs(fx) < 0.55) & (fy < 2.2)
    panel = door & ((np.abs(np.abs(fx) - 0.25) < 0.025) | (np.abs(fy - 1.1) < 0.025) | (np.abs(fx) < 0.02))
    door_rgb = h.palette(10, _DOORS)
    _where(door, colour, lambda x, y, s, c: c * (0.85 + 0.3 * value_noise(x * 5, y, 0.05, s))[:, None],
           u, v, seed + 8, door_rgb)
    colour = _mix(colour, door_rgb * 0.6, panel)
    if not house:
        shop = ground & ~door & (np.abs(fx) < pitch / 2 - 0.3) & (fy > 0.5) & (fy < 2.3)
        shop_inner = shop & (np.abs(fx) < pitch / 2 - 0.38) & (fy > 0.58) & (fy < 2.22)
        colour = _mix(colour, frame_col * 0.8, shop & ~shop_inner)
        _where(shop_inner, colour, _glass, u, v, fy, seed, 0.58, 1.64, lit_room, normal, view, f0)
        radiance |= shop_inner
        sign_top = floor_h - 0.12
        sign = ((h.param(11, 0, 1) < 0.7) & (storey == 0) & (fy > sign_top - 0.55) & (fy < sign_top)
                & (u > 0.3) & (u < width - 0.3))
        _where(sign, colour, _sign_letters, u, fy, seed, sign_top, h.palette(12, _SIGN))

    up = normal[:, 2] > 0.5
    _where(up, colour, lambda x, y, s: np.array([0.32, 0.31, 0.30]) * (0.8 + 0.4 * value_noise(x, y, 0.03, s))[:, None],
           p[:, 0], p[:, 1], seed + 21)
    return colour, radiance & ~up


_PILLARS = np.array([[0.78, 0.76, 0.72], [0.55, 0.53, 0.50], [0.70, 0.20, 0.15], [0.25, 0.35, 0.30]])
_POLES = np.array([[0.20, 0.32, 0.24], [0.25, 0.25, 0.28], [0.55, 0.55, 0.58]])
_ROOFS = np.array([[0.55, 0.22, 0.15], [0.30, 0.30, 0.33], [0.45, 0.30, 0.22]])


def pillar(h: Hits) -> np.ndarray:
    """Concrete or painted pillars and beams: joints every half metre, bands, fine grain."""
    u, v = facade_uv(h.p, h.normal, h.lo)
    flat = np.abs(h.normal[:, 2]) > 0.5  # tops and undersides (of beams): texture over x and y
    u = np.where(flat, h.p[:, 0] - h.lo[:, 0], u)
    v = np.where(flat, h.p[:, 1] - h.lo[:, 1], v)
    seed = h.seed
    grain = 0.85 + 0.25 * value_noise(u, v, 0.015, seed) + 0.1 * (value_noise(u, v, 0.2, seed + 1) - 0.5)
    colour = h.palette(1, _PILLARS) * grain[:, None]
    joint = np.abs(v / 0.5 - np.round(v / 0.5)) * 0.5 < 0.012
    band = (v % 1.7) < 0.18
    colour = _mix(colour, colour * 0.55, joint)
    return _mix(colour, np.clip(colour * 1.3 + 0.1, 0, 1), band)


def pole(h: Hits) -> np.ndarray:
    """Painted metal poles with light bands and flecks."""
    lo, hi = h.lo, h.hi
    v = h.p[:, 2] - lo[:, 2]
    angle = np.arctan2(h.p[:, 1] - 0.5 * (lo[:, 1] + hi[:, 1]), h.p[:, 0] - 0.5 * (lo[:, 0] + hi[:, 0]))
    fleck = 0.85 + 0.3 * value_noise(angle * 0.1, v, 0.01, h.seed)
    colour = h.palette(1, _POLES) * fleck[:, None]
    band = ((v > 2.4) & (v < 2.7)) | ((v % 0.9) < 0.05)
    return _mix(colour, np.full_like(colour, 0.9), band)


def road(h: Hits) -> np.ndarray:
    """Asphalt with grain and lane markings (centre dashes, edge lines) along x."""
    x, y, seed = h.p[:, 0], h.p[:, 1], h.seed
    grain = 0.75 + 0.35 * value_noise(x, y, 0.012, seed) + 0.25 * (fbm(x, y, 0.6, seed + 1, 2) - 0.5)
    colour = np.array([0.30, 0.30, 0.31]) * grain[:, None]
    yc = 0.5 * (h.lo[:, 1] + h.hi[:, 1])
    half = 0.5 * (h.hi[:, 1] - h.lo[:, 1])
    centre = (np.abs(y - yc) < 0.07) & ((x % 6.0) < 3.0)
    edge = np.abs(np.abs(y - yc) - (half - 0.25)) < 0.07
    return _mix(colour, np.array([0.92, 0.92, 0.88]) * (0.8 + 0.2 * grain[:, None]), centre | edge)


def sidewalk(h: Hits) -> np.ndarray:
    """Paving slabs with grout lines and per-slab tone; plain kerb faces."""
    x, y, seed = h.p[:, 0], h.p[:, 1], h.seed
    size = 0.4
    ix, iy = np.floor(x / size), np.floor(y / size)
    grout = ((x / size - ix) < 0.03) | ((y / size - iy) < 0.03)
    tone = 0.8 + 0.3 * rand01(seed, ix, iy)
    grain = 0.9 + 0.2 * value_noise(x, y, 0.01, seed + 1)
    colour = np.array([0.66, 0.64, 0.60]) * (tone * grain)[:, None]
    colour = _mix(colour, np.full_like(colour, 0.35), grout)
    kerb = np.array([0.6, 0.6, 0.6]) * grain[:, None]
    return np.where((h.normal[:, 2] > 0.5)[:, None], colour, kerb)


def ground(h: Hits) -> np.ndarray:
    """Open ground: grass and earth patches, both grainy."""
    x, y, seed = h.p[:, 0], h.p[:, 1], h.seed
    patches = value_noise(x, y, 3.0, seed)
    grain = 0.8 + 0.4 * value_noise(x, y, 0.015, seed + 1)
    grass = np.array([0.35, 0.45, 0.22]) * grain[:, None]
    earth = np.array([0.48, 0.40, 0.30]) * grain[:, None]
    t = np.clip((patches - 0.4) * 4, 0, 1)[:, None]
    return grass * (1 - t) + earth * t


def roof(h: Hits) -> np.ndarray:
    """Tiled pitched roofs: rows of tiles down the slope."""
    x, z = h.p[:, 0], h.p[:, 2]
    row = np.floor(z / 0.12)
    tile = np.floor(x / 0.2 + 0.5 * (row.astype(np.int64) & 1))
    tone = 0.8 + 0.35 * rand01(h.seed, tile, row)
    colour = h.palette(13, _ROOFS) * tone[:, None]
    return _mix(colour, colour * 0.5, (z / 0.12 - row) < 0.15)


def house(h: Hits) -> tuple[np.ndarray, np.ndarray]:
    """Small town houses: plain facades below, tiled gable roofs (sloped faces) above.
    Returns colour (n, 3) and radiance (n,) bool, as :func:`facade`."""
    colour, radiance = facade(h, house=True)
    sloped = (h.normal[:, 2] > 0.2) & (h.normal[:, 2] < 0.99)
    if sloped.any():
        put_rows(colour, np.flatnonzero(sloped), roof(h.subset(sloped)))
    return colour, radiance & ~sloped


_MATERIALS = {
    Kind.GROUND: ground,
    Kind.ROAD: road,
    Kind.SIDEWALK: sidewalk,
    Kind.BUILDING: facade,
    Kind.PILLAR: pillar,
    Kind.POLE: pole,
    Kind.BEAM: pillar,
    Kind.HOUSE: house,
}


def shade(scene: Scene, p: np.ndarray, normal: np.ndarray, obj: np.ndarray,
          view: np.ndarray | None = None) -> np.ndarray:
    """Colour of hits: material albedo times simple sun + ambient light; glass
    reflects the sky as seen from ``view``.

    p: (n, 3) float64 hit points; normal: (n, 3) float32 unit normals;
    obj: (n,) int object ids (all valid); view: (n, 3) directions from the eye
    to each hit (any length), or None for a head-on view of every hit.
    A material returns an albedo (n, 3), or (colour (n, 3), radiance (n,) bool)
    where some colours are already radiance and are not lit again.
    Returns (n, 3) float64 in [0, 1].
    """
    # the hits grouped by kind (one gather each, then contiguous slices): every hit's colour is
    # computed from its own values alone, so the order it is computed in changes no byte
    order = kind_order(scene, obj)
    shaded = np.empty((len(p), 3))
    shaded[order] = shade_grouped(scene, p[order], normal[order], obj[order], None if view is None else view[order])
    return shaded


def kind_order(scene: Scene, obj: np.ndarray) -> np.ndarray:
    """(n,) int64: the order that groups hits on objects ``obj`` (n,) by their kind (stable)."""
    return np.argsort(scene.object_kind[obj], kind="stable")


def shade_grouped(scene: Scene, p: np.ndarray, normal: np.ndarray, obj: np.ndarray,
                  view: np.ndarray | None = None) -> np.ndarray:
    """:func:`shade` of hits already grouped by their objects' kind (:func:`kind_order`), in
    their order: a caller that gathers its hits anyway gathers them once."""
    n = len(p)
    if n == 0:
        return np.zeros((0, 3))
    kinds = scene.object_kind[obj]
    normal = normal.astype(np.float64)
    if view is not None:
        view = np.asarray(view, dtype=np.float64)
        view = view / row_norms(view)[:, None]
    colour = np.empty((n, 3))
    radiance = np.zeros(n, dtype=bool)
    ends = np.append(np.flatnonzero(kinds[1:] != kinds[:-1]) + 1, n)
    start = 0
    for end in ends:
        group = slice(start, end)
        out = _MATERIALS[Kind(int(kinds[start]))](
            Hits(p[group], normal[group], obj[group], scene, None if view is None else view[group]))
        if isinstance(out, tuple):
            colour[group], radiance[group] = out
        else:
            colour[group] = out
        start = end
    light = AMBIENT + (1.0 - AMBIENT) * np.clip(normal @ SUN, 0.0, 1.0)
    light[radiance] = 1.0
    return np.clip(colour * light[:, None], 0.0, 1.0)


def sky(directions: np.ndarray) -> np.ndarray:
    """Smooth, textureless sky. directions: (n, 3) world ray directions → (n, 3) colour."""
    d = directions / row_norms(directions)[:, None]
    t = np.clip(d[:, 2], 0.0, 1.0)[:, None]
    horizon = np.array([0.80, 0.86, 0.92])
    zenith = np.array([0.42, 0.58, 0.84])
    return horizon * (1 - t) + zenith * t
