"""Which sampled directions a view blends, per quad, and where their decoded tiles live (numpy).

The GPU decode keeps, per billboard, its texture decoded at up to four sampled
directions — the corners of the yaw × pitch bracket around the eye — and blends them
per fragment. A direction with yaw index y and pitch index p is kept in storage slot
``(p mod 2)·2 + (y mod 2)`` (``y mod 2`` when the model samples one pitch): the
bracket's corners always fall into different slots, and when the eye crosses into the
next bracket the corner it shares with the last one is still in its slot, so only the
new side is decoded. This is the decode reuse of the renderer: a tile is decoded again
only when the direction its slot must hold changes.

:func:`view_brackets` uses the CPU decode's direction indices and bracketing
(:mod:`billboards.decode`), so both decodes blend the same directions.
"""

from __future__ import annotations

import numpy as np

from billboards.decode import bracket, view_direction_index


def storage_slots(num_pitches: int) -> int:
    """Decoded tiles kept per billboard: 2 with one sampled pitch, else 4."""
    return 2 if num_pitches <= 1 else 4


def view_brackets(eye, centres: np.ndarray, base_yaw: np.ndarray, yaw_offsets: np.ndarray, pitches: np.ndarray,
                  interpolate: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Directions and weights per storage slot for quads at ``centres`` seen from ``eye``.

    eye (3,), centres (R, 3) model coordinates; base_yaw (R,) radians; yaw_offsets (d_yaw,),
    pitches (d_pitch,) radians, increasing. Without ``interpolate`` the nearest sampled
    direction alone (ties go to the larger index). Returns (direction (R, S) int32: the
    direction index p·d_yaw + y each storage slot must hold, −1 where its weight is 0;
    weight (R, S) float32, summing to 1 per quad), S = :func:`storage_slots`.
    """
    # The view vector as the CPU decode forms it (float32 eye minus float32 centre): straight above
    # or below a quad its yaw is atan2 of rounding noise, and both decodes must see the same noise.
    c = np.asarray(centres, np.float32).reshape(-1, 3)
    v = (np.asarray(eye, np.float64).reshape(1, 3).astype(np.float32) - c).astype(np.float64)
    dy, dp = len(yaw_offsets), len(pitches)
    yi, pi = view_direction_index(v, base_yaw, yaw_offsets, pitches)
    y0, y1, fy = bracket(yi, dy)
    p0, p1, fp = bracket(pi, dp)
    if not interpolate:
        fy = (fy >= 0.5).astype(np.float32)
        fp = (fp >= 0.5).astype(np.float32)
    slots = storage_slots(dp)
    direction = np.full((len(c), slots), -1, np.int32)
    weight = np.zeros((len(c), slots), np.float64)
    rows = np.arange(len(c))
    for p, wp in ((p0, 1 - fp), (p1, fp)):
        for y, wy in ((y0, 1 - fy), (y1, fy)):
            w = wp * wy
            slot = (y & 1) if slots == 2 else (p & 1) * 2 + (y & 1)
            weight[rows, slot] += w  # a clamped bracket (y0 == y1) puts both corners in one slot
            direction[rows, slot] = np.where(w > 0, p * dy + y, direction[rows, slot])
    direction[weight <= 0] = -1
    return direction, weight.astype(np.float32)
