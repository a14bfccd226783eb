"""The fit (billboards.fit): the solve against its dense reference, ill-conditioned and
degenerate problems, the renderer's filtering, the CPU ray cast against the GL renderer,
and a known texture recovered through the renderer from a blurred, offset start."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.atlas import pack_rows, pack_tiles
from billboards.fit import (FitConfig, Quads, blended, column_taps, problem, quads_of, record_dtype, solve,
                            solve_reference)
from billboards.fit_cast import cast_view, view_records
from billboards.fit_subspace import FLOOR, expansion, expansion_reference, slots, subspace, with_slots
from billboards.geometry import BILLBOARD, FACADE, GROUND
from billboards.model import BillboardModel
from billboards.pca import EigenTextures, PcaConfig
from core.metrics import psnr


def lone_quads(n: int, dp: int, dy: int, tile: int, kind=BILLBOARD, centres=None) -> Quads:
    """Quads of one kind with a d_pitch × d_yaw table (by default billboards in a row, each alone)."""
    centres = np.stack([np.arange(n) * 3.0, np.zeros(n), np.zeros(n)], axis=1) if centres is None else centres
    return quads_of(np.zeros(3), np.asarray(centres, np.float32), np.zeros(n, np.float32), np.full(n, kind, np.uint8),
                    0.5, 0.5, tile, np.linspace(-0.5, 0.5, dy), np.linspace(-0.3, 0.3, dp) if dp > 1 else np.zeros(1))


def random_records(rng, quads: int, d: int, tile: int, rows: int, corners: int = 2) -> np.ndarray:
    rec = np.zeros(rows, record_dtype(corners))
    rec["quad"] = rng.integers(0, quads, rows)
    first = rng.integers(0, d - 1, rows)
    rec["corner"] = np.stack([first + k for k in range(corners)], axis=1) % d
    w = rng.uniform(0, 1, (rows, corners))
    rec["weight"] = w / w.sum(axis=1, keepdims=True)
    rec["texel"] = rng.uniform(-0.5, tile + 0.5, (rows, 2))
    rec["colour"] = rng.integers(0, 256, (rows, 3))
    return rec


@pytest.mark.parametrize("seed, quads, dp, dy, tile, rows",
                         [(0, 1, 1, 2, 2, 5), (1, 2, 1, 3, 2, 40), (2, 3, 1, 4, 3, 200), (3, 2, 2, 3, 2, 60)])
@pytest.mark.parametrize("prior", [1e-3, 0.1, 10.0])
def test_solve_matches_dense_reference(seed, quads, dp, dy, tile, rows, prior):
    rng = np.random.default_rng(seed)
    corners = 2 if dp == 1 else 4
    q = lone_quads(quads, dp, dy, tile)
    prob = problem(q, random_records(rng, quads, dp * dy, tile, rows, corners), 0, quads, None)
    x0 = rng.uniform(0, 1, (prob.size, 3))
    fast, history, _ = solve(prob, x0, prior, iterations=4 * prob.size, clip=False)
    ref = solve_reference(prob, x0, prior)
    np.testing.assert_allclose(fast, ref, rtol=1e-6, atol=1e-6)
    assert history[-1] <= history[0] + 1e-9


def test_solve_is_regular_where_the_images_say_little():
    """A texel seen by one pixel with a tiny weight, a quad seen edge-on (zero weight), and
    texels nothing measures: finite, pulled toward the sampled colour, never NaN."""
    rec = np.zeros(3, record_dtype(2))
    rec["quad"] = [0, 0, 1]
    rec["corner"] = [[0, 1], [0, 1], [0, 1]]
    rec["weight"] = [[1.0, 0.0], [1e-6, 1 - 1e-6], [0.0, 0.0]]   # the last: no weight at all
    rec["texel"] = [[0.5, 0.5], [1.5, 1.5], [1.0, 1.0]]
    rec["colour"] = [[255, 255, 255], [0, 0, 0], [0, 0, 0]]
    prob = problem(lone_quads(2, 1, 2, 2), rec, 0, 2, None)
    x0 = np.full((prob.size, 3), 0.5)
    x, history, _ = solve(prob, x0, prior=1.0, iterations=50)
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(history))
    # texel (0, 0) of quad 0, direction 0: one full pixel of white against a prior of one pixel
    np.testing.assert_allclose(x[0], 0.75, atol=1e-9)
    untouched = np.ones(prob.size, bool)
    untouched[np.unique(prob.idx[np.abs(prob.a) > 0])] = False
    assert untouched.sum() > 0
    np.testing.assert_array_equal(x[untouched], x0[untouched])
    # nothing measured at all: x0 back, unchanged
    empty = problem(lone_quads(2, 1, 2, 2), rec[:0], 0, 2, None)
    x, history, _ = solve(empty, x0, prior=0.1, iterations=5)
    np.testing.assert_array_equal(x, x0)
    assert history == [0.0]
    with pytest.raises(ValueError):
        solve(prob, x0, prior=0.0, iterations=1)


def test_solve_stops_at_its_deadline_and_clips():
    rng = np.random.default_rng(3)
    prob = problem(lone_quads(2, 1, 3, 2), random_records(rng, 2, 3, 2, 60), 0, 2, None)
    x0 = rng.uniform(0, 1, (prob.size, 3))
    x, history, _ = solve(prob, x0, 0.01, iterations=20, deadline=0.0)   # long past
    assert len(history) == 1
    np.testing.assert_array_equal(x, x0)
    x, *_ = solve(prob, x0 * 4 - 2, 0.01, iterations=20)
    assert x.min() >= 0 and x.max() <= 1


def test_a_passing_car_is_left_out_of_the_fit():
    """Grey texels measured grey by many pixels and red by a few (a car in one frame): the red
    ones are transients, left out; the fit stays grey. Counted in, they tint it."""
    from billboards.fit_tasks import fit_range

    q = lone_quads(1, 1, 2, 2)
    rgba = np.full((1, 2, 2, 2, 4), 120, np.uint8)
    rgba[..., 3] = 255
    rng = np.random.default_rng(5)
    rec = random_records(rng, 1, 2, 2, 80)
    rec["colour"] = rng.integers(110, 131, (80, 3))
    rec["colour"][:12] = (230, 20, 20)
    rec = rec[np.argsort(rec["quad"], kind="stable")]
    kept, stats = fit_range(q, rgba, 0, 1, rec, FitConfig(), None, PcaConfig())
    kept = kept.reconstruct().reshape(1, 2, 4, 4) * 255
    assert stats["transients"] == 12 and stats["measurements"] == 68
    assert np.abs(kept[..., :3] - 120).max() <= 10
    tinted, stats = fit_range(q, rgba, 0, 1, rec, FitConfig(transients=None), None, PcaConfig())
    tinted = tinted.reconstruct().reshape(1, 2, 4, 4) * 255
    assert stats["transients"] == 0 and (tinted[..., 0] - tinted[..., 1]).max() > 20


def random_eigen_textures(rng, count: int, d: int, texels: int, R: int) -> EigenTextures:
    rank = rng.integers(0, R + 1, count).astype(np.int32)
    rank[0] = 0
    basis = rng.normal(0, 0.3, (count, R, texels * 4)).astype(np.float32)
    coefficients = rng.normal(0, 1, (count, d, R)).astype(np.float32)
    used = np.arange(R)[None, :] < rank[:, None]
    basis[~used] = 0.0
    coefficients[~np.broadcast_to(used[:, None, :], coefficients.shape)] = 0.0
    return EigenTextures(rng.uniform(0, 1, (count, texels * 4)).astype(np.float32), basis, coefficients, rank)


@pytest.mark.parametrize("seed, quads, dy, tile, R", [(0, 1, 2, 2, 1), (1, 3, 3, 2, 2), (2, 4, 4, 3, 3)])
def test_the_subspace_is_what_the_model_stores_and_its_solve_matches_a_dense_one(seed, quads, dy, tile, R):
    """B maps slots to exactly the textures the eigen-textures decode to; the solve in the
    slots equals the dense regularised normal equations of A·B."""
    rng = np.random.default_rng(seed)
    T = tile * tile
    eig = random_eigen_textures(rng, quads, dy, T, R)
    B = expansion(eig.coefficients, eig.rank, T)
    np.testing.assert_allclose(B.toarray(), expansion_reference(eig.coefficients, eig.rank, T), atol=1e-7)
    z = slots(eig, T)
    decoded = eig.reconstruct().reshape(quads, dy, T, 4)[..., :3].reshape(-1, 3)
    np.testing.assert_allclose(B @ z, decoded, atol=1e-5)
    np.testing.assert_array_equal(slots(with_slots(eig, z), T), z.astype(np.float32))
    prob = problem(lone_quads(quads, 1, dy, tile), random_records(rng, quads, dy, tile, 30 * quads), 0, quads, None)
    sub = subspace(prob, eig)
    fast, history, _ = solve(sub, z, 0.1, iterations=10 * sub.size, clip=False)
    AB = prob.matrix.toarray() @ B.toarray()
    M = AB.T @ AB + 0.1 * np.diag(np.maximum((B.toarray() ** 2).sum(axis=0), FLOOR))
    ref = z + np.linalg.solve(M, AB.T @ (prob.y - AB @ z))
    np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-5)
    assert history[-1] <= history[0] + 1e-9
    # slots beyond a quad's rank stay zero in what is stored
    stored = with_slots(eig, fast)
    assert np.all(stored.basis[np.arange(R)[None, :] >= eig.rank[:, None]] == 0)


def test_taps_follow_the_renderer():
    """Bilinear, the sample point clamped between the outer texel centres of a tile, or of a
    slit's column of tiles (a facade column filters across its blocks' edges)."""
    tile = 4
    rng = np.random.default_rng(0)
    texel = rng.uniform(-1, tile + 1, (500, 2))
    alone = lone_quads(1, 1, 2, tile)
    tap_quad, taps, w = column_taps(alone, np.zeros(500, np.int64), texel)
    np.testing.assert_allclose(w.sum(axis=1), 1, atol=1e-6)
    assert np.all(tap_quad == 0)
    got = (taps * w).sum(axis=1)                        # the texel index row·t + column is linear
    p = np.clip(texel, 0.5, tile - 0.5) - 0.5
    np.testing.assert_allclose(got, p[:, 1] * tile + p[:, 0], atol=1e-4)
    # a column of three facade blocks, listed bottom up: one texture of t × 3t texels, top down
    column = lone_quads(3, 1, 2, tile, kind=FACADE, centres=np.array([[0, 0, 0.25], [0, 0, 0.75], [0, 0, 1.25]]))
    quad = rng.integers(0, 3, 500)
    tap_quad, taps, w = column_taps(column, quad, texel)
    height = (2 - tap_quad) * tile + taps // tile        # row within the column, from the top
    got = ((height * tile + taps % tile) * w).sum(axis=1)
    row = np.clip(texel[:, 1] + (2 - quad) * tile, 0.5, 3 * tile - 0.5) - 0.5
    np.testing.assert_allclose(got, row * tile + p[:, 0], atol=1e-4)
    assert np.any(tap_quad != quad[:, None])             # some taps do cross into the next block


def test_config_refuses_what_cannot_run():
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="transients"):
            FitConfig(transients=bad)
    for bad in (dict(prior=0.0), dict(prior=float("nan")), dict(seconds=-1.0), dict(seconds=float("inf")),
                dict(pixel_stride=0), dict(iterations=-1), dict(iterations=1.5), dict(see_through=True),
                dict(max_rays_side=0)):
        with pytest.raises(ValueError):
            FitConfig(**bad)


def test_large_photos_are_measured_on_a_coarser_grid():
    conf = FitConfig()
    # the demo's 416×736 views and KITTI's 1241×376: every second pixel of every second row
    assert conf.stride((416, 736)) == 2 and conf.stride((1241, 376)) == 2
    # a 2832×2128 photo: every fourth (708 rays along its width); a 4000×3000 one: every fifth
    assert conf.stride((2832, 2128)) == 4 and conf.stride((3000, 4000)) == 5
    assert FitConfig(pixel_stride=1, max_rays_side=10_000).stride((2832, 2128)) == 1


# ----------------------------------------------------------------------------------------------
# through the renderer


TILE, D_YAW = 8, 7
YAW = np.deg2rad(np.linspace(-36, 36, D_YAW))


def wall_textures(rng, blocks: int) -> np.ndarray:
    """(blocks, d, t, t, 3) float view-independent smooth colour patterns in [0.1, 0.9]."""
    y, x = np.mgrid[0:TILE, 0:TILE] / TILE
    phase = rng.uniform(0, 2 * np.pi, (blocks, 3, 2))
    f = rng.uniform(2, 5, (blocks, 3, 1, 1))
    tex = 0.5 + 0.4 * np.sin(f * x + phase[..., 0, None, None]) * np.cos(f * y + phase[..., 1, None, None])
    return np.repeat(np.moveaxis(tex, 1, -1)[:, None], D_YAW, axis=1)


def model_of(textures: np.ndarray, centres: np.ndarray, kind: np.ndarray, base_yaw: np.ndarray,
             block: float) -> BillboardModel:
    """Rank-0 model whose mean tile is each quad's texture (every direction the same)."""
    n = len(centres)
    tiles = np.concatenate([np.rint(textures[:, 0] * 255), np.full((n, TILE, TILE, 1), 255)], axis=-1)
    lo, hi = centres.min(0) - 2, centres.max(0) + 2
    return BillboardModel(
        origin=np.zeros(3), voxel_size=block, tile=TILE, page_size=64, yaw_offsets=YAW,
        pitches=np.zeros(1), pitched_quads=False, tile_mode="u8", coef_mode="f32",
        centres=centres.astype(np.float32), base_yaw=base_yaw.astype(np.float32), rank=np.zeros(n, np.uint8),
        first_slot=np.arange(n, dtype=np.int32), slot_scale=np.ones((n, 4), np.float32),
        slot_offset=np.zeros((n, 4), np.float32), coef_scale=np.ones(n, np.float32),
        coef_offset=np.zeros(n, np.float32), pages=pack_tiles(tiles.astype(np.uint8), 64),
        coef_pages=pack_rows(np.zeros((n, D_YAW), np.float32), 64), node_level=np.zeros(1, np.uint8),
        node_bounds=np.array([[lo, hi]], np.float32), node_children=-np.ones((1, 8), np.int32),
        node_range=np.array([[0, n]], np.int32), info={}, kind=kind.astype(np.uint8), block_size=block)


def wall_scene():
    """A 4 × 3 wall of facade blocks facing −y at y = 3, a row of ground blocks before it (each
    1 cm above the last) and one billboard; cameras on y = −1 looking at the wall (+y) from x = −1.5 … 1.5."""
    block = 0.5
    xs = (np.arange(4) - 1.5) * block
    zs = 0.5 + np.arange(3) * block
    wall = np.array([[x, 3.0, z] for z in zs for x in xs])
    ground = np.array([[x, 2.0, 0.01 * k] for k, x in enumerate(xs)])   # (steps, as on a real road: no ties)
    board = np.array([[0.2, 1.5, 0.6]])
    centres = np.concatenate([wall, ground, board])
    kind = np.array([FACADE] * len(wall) + [GROUND] * len(ground) + [BILLBOARD])
    base_yaw = np.full(len(centres), -np.pi / 2)
    poses = []
    for x in np.linspace(-1.5, 1.5, 9) + 0.0123:       # (no quad edge exactly on a pixel centre)
        pose = np.eye(4)
        pose[:3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)  # x right, y down (−z), z forward (+y)
        pose[:3, 3] = [x, -1.017, 1.037]
        poses.append(pose)
    K = np.array([[120.0, 0, 79.5], [0, 120.0, 59.5], [0, 0, 1]])
    return centres, kind, base_yaw, block, np.array(poses), K, (160, 120)


def model_quads(model: BillboardModel) -> Quads:
    return quads_of(model.origin, model.centres, model.base_yaw, model.kind, model.voxel_size, model.block_size,
                    model.tile, model.yaw_offsets, model.pitches, model.pitched_quads)


def alpha_of(model: BillboardModel) -> np.ndarray:
    return np.full((model.num_billboards, model.num_directions, TILE * TILE), 255, np.uint8)


def test_cast_view_predicts_what_the_renderer_draws(ctx):
    from render.offscreen import render_view

    rng = np.random.default_rng(1)
    centres, kind, base_yaw, block, poses, K, size = wall_scene()
    truth = wall_textures(rng, len(centres))
    model = model_of(truth, centres, kind, base_yaw, block)
    quads = model_quads(model)
    colours = np.rint(truth * 255).reshape(len(centres), D_YAW, TILE * TILE, 3)
    for pose in poses[::4]:
        image = render_view(model, K, pose, size, background=(1.0, 0.0, 1.0))
        hits = cast_view(quads, alpha_of(model), K, pose, size)
        assert len(hits.quad) > 0.1 * size[0] * size[1]
        drawn = np.any(image != [255, 0, 255], axis=-1)
        mask = np.zeros(drawn.shape, bool)
        mask[hits.pixel[:, 1], hits.pixel[:, 0]] = True
        assert (mask & ~drawn).sum() < 0.01 * drawn.sum()         # nothing where the renderer draws nothing
        assert (mask & drawn).sum() > 0.85 * drawn.sum()          # (rays where ground blocks overlap measure nothing)
        predicted = blended(quads, colours, hits.quad, hits.corner, hits.weight, hits.texel)
        observed = image[hits.pixel[:, 1], hits.pixel[:, 0]].astype(np.float64)
        err = np.abs(predicted - observed).max(axis=1)
        # away from the quads' edges, where a ray exactly between two quads may go either way
        inside = np.all((hits.texel > 0.05) & (hits.texel < TILE - 0.05), axis=1) & drawn[hits.pixel[:, 1], hits.pixel[:, 0]]
        assert inside.mean() > 0.8
        assert np.median(err[inside]) <= 1.0 and np.mean(err[inside] <= 2.0) > 0.99


def test_fit_recovers_a_known_texture_through_the_renderer(ctx):
    """Training images drawn by the GL renderer from the true texture; the fit starts from
    the texture blurred and shifted by a texel and must give it back (≥ 35 dB over the
    texels the images measure)."""
    import cv2

    from render.offscreen import render_view

    rng = np.random.default_rng(2)
    centres, kind, base_yaw, block, poses, K, size = wall_scene()
    truth = wall_textures(rng, len(centres))
    model = model_of(truth, centres, kind, base_yaw, block)
    quads = model_quads(model)
    records = []
    for pose in poses:
        image = render_view(model, K, pose, size)
        records.append(view_records(cast_view(quads, alpha_of(model), K, pose, size), image))
    records = np.concatenate(records)
    n, d = len(centres), D_YAW
    start = np.roll(truth, 1, axis=3)                                       # a texel off …
    start = np.stack([cv2.GaussianBlur(t.astype(np.float32), (0, 0), 1.2) for t in start.reshape(-1, TILE, TILE, 3)])
    start = start.reshape(truth.shape)                                      # … and blurred
    prob = problem(quads, records, 0, n, None)
    x, history, _ = solve(prob, start.reshape(-1, 3), prior=0.01, iterations=100)
    measured = prob.diagonal() > 0.5
    fitted = x.reshape(-1, 3)[measured]
    expected = np.rint(truth * 255).reshape(-1, 3)[measured] / 255
    before = start.reshape(-1, 3)[measured]
    assert measured.sum() > 0.3 * measured.size
    assert history[-1] < 0.05 * history[0]
    assert psnr(fitted, expected) >= 35.0
    assert psnr(before, expected) < 30.0
