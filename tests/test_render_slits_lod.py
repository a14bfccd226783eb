"""Slits, view brackets and levels of detail: the numpy side of the GPU decode."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.decode import direction_index
from billboards.geometry import BILLBOARD, FACADE, GROUND
from render.lod import LodConfig, lod_levels, texel_pixels
from billboards.slits import (build_slits, exact_runs, exact_runs_reference, pack_columns, pack_columns_reference,
                          whole_runs)
from render.view_brackets import storage_slots, view_brackets

from .test_render_gpu import make_model


def wall_blocks(rng, columns=12, size=0.5):
    """Facade columns of random heights (some with a gap), shuffled among billboards and ground blocks."""
    centres, kind, yaw = [], [], []
    for c in range(columns):
        heights = np.arange(rng.integers(1, 9)) * size + size / 2
        if len(heights) > 4 and c % 3 == 0:
            heights = np.delete(heights, 2)  # a gap: two columns
        for z in heights:
            centres.append((c * size, 4.0, z))
            kind.append(FACADE)
            yaw.append(-np.pi / 2)
    for _ in range(30):
        centres.append((rng.uniform(0, 6), rng.uniform(-3, 3), rng.uniform(0, 4)))
        kind.append(int(rng.choice([BILLBOARD, GROUND])))
        yaw.append(0.0)
    perm = rng.permutation(len(centres))
    return (np.array(centres, np.float32)[perm], np.array(kind, np.uint8)[perm],
            np.array(yaw, np.float32)[perm])


def test_slits_stack_facade_columns_from_the_top():
    rng = np.random.default_rng(1)
    centres, kind, yaw = wall_blocks(rng)
    slits = build_slits(centres, kind, yaw, 0.5)
    assert np.array_equal(np.sort(slits.order), np.arange(len(centres)))
    assert np.array_equal(slits.order[slits.position], np.arange(len(centres)))
    for start, count in zip(slits.column_start, slits.column_count):
        members = slits.order[start:start + count]
        if count > 1:
            assert np.all(kind[members] == FACADE)
            assert np.allclose(centres[members, :2], centres[members[0], :2])
            assert np.allclose(np.diff(centres[members, 2]), -0.5)  # top down, no gap
    assert slits.num_columns < len(centres)
    # every facade block with a neighbour 0.5 m above or below shares its column
    facade = np.flatnonzero(kind == FACADE)
    for b in facade:
        above = [o for o in facade if np.allclose(centres[o], centres[b] + [0, 0, 0.5])]
        for o in above:
            assert slits.column[slits.position[o]] == slits.column[slits.position[b]]
    # no merging (pitch sampled), and a cap on the column height
    alone = build_slits(centres, kind, yaw, 0.5, merge=False)
    assert alone.num_columns == len(centres)
    capped = build_slits(centres, kind, yaw, 0.5, max_blocks=3)
    assert capped.column_count.max() <= 3 and capped.num_columns > slits.num_columns


def test_runs_match_the_reference_and_whole_columns_draw_once():
    rng = np.random.default_rng(2)
    centres, kind, yaw = wall_blocks(rng, columns=20)
    slits = build_slits(centres, kind, yaw, 0.5)
    n = len(centres)
    for trial in range(20):
        chosen = rng.choice(n, size=rng.integers(0, n + 1), replace=False)
        got = exact_runs(slits, chosen)
        want = exact_runs_reference(slits, chosen)
        assert all(np.array_equal(a, b) for a, b in zip(got, want))
        covered = np.concatenate([np.arange(s, s + c) for s, c in zip(*got)] or [np.zeros(0, int)])
        assert np.array_equal(np.sort(slits.order[covered]), np.sort(chosen))
    drawn = np.zeros(slits.num_columns, bool)
    first = whole_runs(slits, [0, 1, 2], drawn)
    again = whole_runs(slits, np.arange(n), drawn)
    cols = np.r_[slits.column[first[0]], slits.column[again[0]]]
    assert len(np.unique(cols)) == len(cols) == slits.num_columns  # each column once per frame
    assert np.array_equal(whole_runs(slits, np.arange(n), drawn)[0], [])


def test_pack_columns_never_crosses_a_band():
    rng = np.random.default_rng(3)
    counts = rng.integers(1, 9, 500)
    first = pack_columns(counts, 8)
    assert np.array_equal(first, pack_columns_reference(counts, 8))
    mostly_single = np.where(rng.random(500) < 0.8, 1, counts)  # as in a street: few slits among blocks
    assert np.array_equal(pack_columns(mostly_single, 8), pack_columns_reference(mostly_single, 8))
    assert np.all(first // 8 == (first + counts - 1) // 8)
    assert np.all(np.diff(first) >= counts[:-1])
    assert len(pack_columns(np.zeros(0, int), 8)) == 0
    with pytest.raises(ValueError):
        pack_columns([9], 8)


@pytest.mark.parametrize("pitches", [(0.0,), (0.0, 20.0, 40.0)])
@pytest.mark.parametrize("interpolate", [True, False])
def test_view_brackets_agree_with_the_reference_decode(pitches, interpolate):
    rng = np.random.default_rng(4)
    n = 400
    centres = rng.uniform(-5, 5, (n, 3))
    model = make_model(centres, d_yaw=9, pitches_deg=pitches, pitched=len(pitches) > 1, rank=1)
    eye = np.array([0.3, -12.0, 1.5])
    direction, weight = view_brackets(eye, model.centres, model.base_yaw, model.yaw_offsets, model.pitches,
                                      interpolate)
    assert direction.shape == weight.shape == (n, storage_slots(len(pitches)))
    assert np.allclose(weight.sum(1), 1.0, atol=1e-6) and np.all(weight >= 0)
    assert np.all((direction >= 0) == (weight > 0))
    yi, pi = direction_index(model, np.arange(n), eye - model.centres.astype(np.float64))
    if not interpolate:
        yi, pi = np.floor(yi + 0.5), np.floor(pi + 0.5)
    dy = len(model.yaw_offsets)
    # the blend of held directions reproduces the bilinear weights over the direction table
    for i in range(n):
        want = np.zeros(model.num_directions)
        y0 = min(int(np.floor(yi[i])), dy - 2)
        p0 = min(int(np.floor(pi[i])), max(len(pitches) - 2, 0))
        fy, fp = yi[i] - y0, pi[i] - p0
        for p, wp in ((p0, 1 - fp), (min(p0 + 1, len(pitches) - 1), fp)):
            for y, wy in ((y0, 1 - fy), (y0 + 1, fy)):
                want[p * dy + y] += wp * wy
        got = np.zeros(model.num_directions)
        for d, w in zip(direction[i], weight[i]):
            if d >= 0:
                got[d] += w
        np.testing.assert_allclose(got, want, atol=1e-6)


def test_view_brackets_reuse_the_shared_corner():
    """Crossing into the next yaw bracket keeps the shared direction in its slot."""
    yaw_offsets = np.deg2rad(np.arange(-90.0, 91.0, 6.0))
    eyes = [np.array([np.cos(a), np.sin(a), 0.0]) * 10 for a in np.deg2rad([10.0, 14.0])]
    a, _ = view_brackets(eyes[0], np.zeros((1, 3)), np.zeros(1), yaw_offsets, np.zeros(1))
    b, _ = view_brackets(eyes[1], np.zeros((1, 3)), np.zeros(1), yaw_offsets, np.zeros(1))
    assert set(a[0]) != set(b[0]) and len(set(a[0]) & set(b[0])) == 1
    shared = (set(a[0]) & set(b[0])).pop()
    assert list(a[0]).index(shared) == list(b[0]).index(shared)


def test_lod_levels_and_hysteresis():
    cfg = LodConfig(full_texel_px=0.5, mean_texel_px=0.15, hysteresis=0.25)
    px = np.array([2.0, 0.5, 0.3, 0.15, 0.1, np.inf])
    assert lod_levels(px, None, cfg).tolist() == [0, 0, 1, 1, 2, 0]
    # just past a threshold the previous level holds; well past it, it changes
    assert lod_levels(np.array([0.45, 0.3]), np.array([0, 0], np.int8), cfg).tolist() == [0, 1]
    assert lod_levels(np.array([0.55, 0.7]), np.array([1, 1], np.int8), cfg).tolist() == [1, 0]
    assert lod_levels(np.array([0.3]), np.array([-1], np.int8), cfg).tolist() == [1]
    d = texel_pixels([0.0, 0.0, 0.0], np.array([[10.0, 0, 0], [0.0, 0, 0]]), np.array([0.5, 0.5]), 8, 1000.0)
    assert d[0] == pytest.approx(1000 * 0.5 / 8 / 10) and d[1] == np.inf
    for bad in (dict(full_texel_px=0.1, mean_texel_px=0.2), dict(hysteresis=1.0), dict(reduced_rank=-1),
                dict(mean_texel_px=0.0), dict(decoded_format="f32"), dict(refresh_tiles_per_frame=-1),
                dict(refresh_tiles_per_frame=2.5), dict(refresh_tiles_per_frame=True)):
        with pytest.raises(ValueError):
            LodConfig(**bad)
