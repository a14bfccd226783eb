"""Out-of-core rendering of a tiled model (render.tiled_renderer, render.paging): a set draws what
its tiles draw one after another into one frame, a one-tile set what the single-model renderer
draws, a split model what the whole model draws; paging under a small GPU budget keeps the
measured bytes within it along a walk, loads tiles before they are needed, releases the far
ones, and a view whose tiles are all resident equals the unlimited-budget image."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from billboards.model_set import load_model_set, split_tiles, write_model_set
from billboards.model_writer import save
from billboards.sky import Sky
from render.camera import ClipPlanes, look_at
from render.context import max_texture_size
from render.gpu_bytes import renderer_gpu_bytes, tile_gpu_bound
from render.lod import LodConfig
from render.paging import FrameBudget, PagingConfig, tile_priorities
from render.renderer import BillboardRenderer
from render.sky import SkyPass, render_over_sky
from render.target import OffscreenTargets
from render.tiled_renderer import TiledRenderer

from .test_core_memory import mapped_resident_bytes
from .test_render_cull_draw import octree_model
from .test_render_gpu import intrinsics

SIZE = (200, 150)
K = intrinsics(120.0, *SIZE)
WORLD = np.array([5e5 + 0.3, 4e6 + 0.7, 12.0])
TILE = 15.0
BG = (0.3, 0.5, 0.8)


def street_points(length: float = 59.0, seed: int = 1) -> np.ndarray:
    """World points of two facades (y = ±6) along x in [0, length) and a few things between."""
    gx, gz = np.meshgrid(np.arange(0.25, length, 0.5), np.arange(0.25, 4.5, 0.5))
    walls = [np.stack([gx.ravel(), np.full(gx.size, y), gz.ravel()], 1) for y in (-6.0, 6.0)]
    rng = np.random.default_rng(seed)
    things = np.stack([rng.uniform(0, length, 150), rng.uniform(-4, 4, 150), rng.uniform(0.3, 3, 150)], 1)
    return WORLD + np.concatenate([*walls, things])


@pytest.fixture(scope="module")
def street():
    """(whole model, tiled set root) of a 60 m street in 4 tiles of 15 m."""
    return octree_model(street_points(), base_yaw=lambda c: np.where(c[:, 1] > WORLD[1], -np.pi / 2, np.pi / 2),
                        d_yaw=3, yaw_span_deg=60.0, page_size=256, rank=1, seed=4)


@pytest.fixture(scope="module")
def street_set(street, tmp_path_factory):
    root = tmp_path_factory.mktemp("set") / "street"
    grid = WORLD - [0.0, TILE / 2, 0.0]  # one row of tiles along the street
    entries = split_tiles(street, root, TILE, grid)
    write_model_set(root, grid, TILE, entries)
    return load_model_set(root)


def views() -> list[np.ndarray]:
    return [look_at(WORLD + [5.0, 0.0, 2.0], WORLD + [40.0, 0.0, 2.0]),  # along the street: every tile
            look_at(WORLD + [22.0, -2.0, 2.0], WORLD + [22.0, 6.0, 2.5]),  # one facade, across a tile border
            look_at(WORLD + [52.0, 3.0, 6.0], WORLD + [20.0, -4.0, 0.0])]  # back down the street, from above


def test_the_split_set(street, street_set):
    assert street_set.tiled and len(street_set) == 4
    assert street_set.num_billboards == street.num_billboards
    assert [t.index for t in street_set.tiles] == [(0, 0), (1, 0), (2, 0), (3, 0)]
    for i, t in enumerate(street_set.tiles):
        model = street_set.load_tile(i)
        world = model.origin + model.centres.astype(np.float64)
        cell = np.floor((world[:, :2] - street_set.origin[:2]) / TILE)
        assert np.all(cell == t.index)
        assert np.all(world >= t.lo) and np.all(world <= t.hi)


def test_set_draws_like_its_tiles_one_after_another(ctx, street_set):
    """The tiled renderer's frame equals each visible tile's own renderer drawing into one cleared
    frame, nearest tile first, no clear between: exactly."""
    models = [street_set.load_tile(i) for i in range(len(street_set))]
    tiles = [BillboardRenderer(ctx, m, "gpu", background=BG, cull="frustum") for m in models]
    targets = OffscreenTargets(ctx)
    try:
        with TiledRenderer(ctx, street_set, "gpu", background=BG) as tiled:
            for pose in views():
                image = tiled.render(K, pose, SIZE, wait="all")
                eye = pose[:3, 3]
                order = np.argsort([np.linalg.norm(np.maximum(np.maximum(t.lo - eye, eye - t.hi), 0))
                                    for t in street_set.tiles], kind="stable")
                targets.begin(SIZE, BG)
                drawn = 0
                visible = _drawn_tiles(tiled, pose)
                for i in order:
                    if i in visible:
                        r = tiles[i]
                        r.draw(r.camera(K, pose, SIZE))
                        drawn += 1
                ref = targets.read(SIZE)
                assert drawn == tiled.stats["tiles_drawn"] >= 1
                np.testing.assert_array_equal(image, ref)
                assert np.mean(np.any(image != np.rint(np.array(BG) * 255), axis=-1)) > 0.05
            assert tiled.stats["tiles_drawn"] >= 1
    finally:
        targets.release()
        for r in tiles:
            r.release()


def _drawn_tiles(tiled: TiledRenderer, pose) -> set[int]:
    """Tiles whose bounds meet the frustum of ``pose`` (what the tiled renderer draws when resident)."""
    from render.camera import gl_camera
    from render.culling import boxes_outside, frustum_planes

    cam = gl_camera(K, pose, SIZE, tiled.origin, tiled.clip)
    planes = frustum_planes(cam.projection.astype(np.float64) @ cam.view.astype(np.float64))
    return set(np.flatnonzero(~boxes_outside(planes, tiled.lo - tiled.origin, tiled.hi - tiled.origin)).tolist())


def test_one_tile_set_is_the_single_model_renderer(ctx, street, tmp_path):
    """A plain model (a directory read as a set of one tile, or the model in memory) draws
    exactly what the single-model renderer draws, over the plain background and over a sky."""
    save(street, tmp_path / "plain")
    plain = load_model_set(tmp_path / "plain")
    assert not plain.tiled and len(plain) == 1
    sky = Sky(np.linspace(0.2, 0.9, 24, dtype=np.float32).reshape(8, 3))
    single = BillboardRenderer(ctx, street, "gpu", background=BG, cull="frustum")
    sky_pass = SkyPass(ctx, sky)
    try:
        for source in (plain, street):
            for with_sky in (False, True):
                with TiledRenderer(ctx, source, "gpu", background=BG, sky=sky if with_sky else None) as tiled:
                    for pose in views():
                        got = tiled.render(K, pose, SIZE)
                        want = render_over_sky(single, sky_pass if with_sky else None, K, pose, SIZE)
                        np.testing.assert_array_equal(got, want)
                        assert tiled.stats["tiles"] == 1
                        assert tiled.stats["billboards_drawn"] == single.stats["billboards_drawn"]
    finally:
        single.release()
        sky_pass.release()


def test_split_set_draws_like_the_whole_model(ctx, street, street_set):
    """Split into tiles on their own origins, the street draws the whole model's image up to the
    tiles' float32 origins: a handful of edge pixels."""
    with BillboardRenderer(ctx, street, "gpu", background=BG, cull="frustum") as whole, \
            TiledRenderer(ctx, street_set, "gpu", background=BG) as tiled:
        for pose in views():
            a = whole.render(K, pose, SIZE)
            b = tiled.render(K, pose, SIZE, wait="all")
            differ = np.any(a != b, axis=-1)
            assert differ.mean() < 0.003, f"{differ.mean():.2%} of the pixels differ"
            assert tiled.stats["billboards_drawn"] >= whole.stats["billboards_drawn"] * 0.9


def test_gpu_account_and_bound(ctx, street_set):
    """Every texture and buffer of a tile's renderer is counted, and never more than its bound,
    with and without level of detail (impostors) and with the CPU decode."""
    limit = max_texture_size(ctx)
    model = street_set.load_tile(1)
    for decode, lod in (("gpu", None), ("gpu", LodConfig()), ("cpu", None)):
        bound = tile_gpu_bound(model, decode, lod, limit)
        with BillboardRenderer(ctx, model, decode, lod=lod, cull="frustum") as r:
            for pose in views():
                r.render(K, pose, SIZE)
            parts = renderer_gpu_bytes(r)
            counted = parts["total"] - parts["targets"] - parts["studio"]
            assert 0 < counted <= bound, (decode, lod, parts, bound)
            if decode == "gpu":
                assert parts["pages"] > 0 and parts["decoded_atlas"] > 0 and parts["view_atlas"] > 0
                assert (parts["impostor_atlas"] > 0) == (lod is not None)
            else:
                assert parts["cpu_atlas"] > 0
        r.release()
        assert renderer_gpu_bytes(r)["total"] == 0  # released: nothing left


def _walk(start, end, steps):
    """Poses along the street from ``start`` to ``end`` (world offsets), looking ahead and a
    little sideways."""
    out = []
    for a in np.linspace(0, 1, steps):
        eye = WORLD + np.asarray(start) * (1 - a) + np.asarray(end) * a
        out.append(look_at(eye, eye + [8.0, 3.0 * np.sin(7 * a), 0.0]))
    return out


@pytest.mark.parametrize("tiles_in_budget", [2.2, 3.2])
def test_paging_walk_under_a_small_budget(ctx, street_set, tiles_in_budget):
    """Along the street under a budget of 2.2 or 3.2 tiles (of 4): the measured GPU bytes and the
    reserved bounds stay within the budget every frame, far tiles are released, every image of a
    view whose tiles are all resident equals the unlimited-budget image; with room for the tiles
    a view sees (3 at most here), tiles ahead are resident before they come within the load
    radius (the loader given each frame's time)."""
    limit = max_texture_size(ctx)
    bounds = [tile_gpu_bound(street_set.load_tile(i), "gpu", None, limit) for i in range(len(street_set))]
    budget = int(tiles_in_budget * max(bounds))
    paging = PagingConfig(gpu_budget=budget, load_radius=10.0, prefetch=12.0, drop_radius=12.0, wait_radius=5.0,
                          frame_ms=None)  # every frame pages, however loaded the machine
    clip_far = dict(clip=ClipPlanes(far=14.0))
    poses = _walk([-3.0, 0.0, 2.0], [65.0, 0.0, 2.0], 36)
    with TiledRenderer(ctx, street_set, "gpu", background=BG, paging=paging, **clip_far) as small, \
            TiledRenderer(ctx, street_set, "gpu", background=BG, **clip_far) as free:
        missing, releases, uploads, compared = [], 0, 0, 0
        for k, pose in enumerate(poses):
            image = small.render(K, pose, SIZE)
            s = small.stats
            assert s["gpu_bytes"] <= s["gpu_reserved"] <= budget, s
            for r in small.resident.values():
                assert r.bytes <= r.bound
            missing.append(s["tiles_missing"])
            releases += s["releases"]
            uploads += s["uploads"]
            ref = free.render(K, pose, SIZE, wait="all")
            if s["tiles_drawn"] == s["tiles_visible"]:
                np.testing.assert_array_equal(image, ref, err_msg=f"frame {k}")
                compared += 1
            small.loader.wait_idle()  # the frame's time: the loads queued this frame finish
        assert missing[0] == 0  # the first frame waited for the tiles around the eye
        if tiles_in_budget > 3:
            assert sum(missing) == 0, missing  # prefetched: nothing near was ever missing
        assert compared >= 0.8 * len(poses)
        assert releases >= 2 and uploads >= 4  # walked through all four tiles, dropping those behind
        assert 1 <= small.loader.trims <= releases  # the heap trimmed in the loader after releases
        assert small.peak_bytes <= budget < free.peak_bytes  # the budget bound
        # at the end of the walk, the first tiles are gone
        assert 0 not in small.resident and (len(street_set) - 1) in small.resident


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps"), reason="needs Linux /proc")
def test_loaded_and_resident_tiles_keep_no_mapped_page_resident(ctx, street_set):
    """A tile's memory-mapped pages are read (warmed, uploaded) and then leave the viewer's
    resident set: memory follows what is on the GPU, not how many tiles were loaded ahead."""
    files = sorted(Path(street_set.root).rglob("*.npy"))
    pages = [f for f in files if f.stat().st_size > 64 * 1024]
    assert pages  # the set's atlas and coefficient pages
    with TiledRenderer(ctx, street_set, "gpu", background=BG, paging=PagingConfig(load_radius=1e3, drop_radius=1e3)) as r:
        r.render(K, views()[0], SIZE, wait="all")
        for i in range(len(street_set)):
            r.loader.request(i)
        r.loader.wait_idle()
        assert len(r.resident) == len(street_set) and len(r.loader.indices()) == len(street_set)
        assert sum(mapped_resident_bytes(f) for f in pages) == 0
        mapped = [p for i in r.resident for p in r.resident[i].renderer.model.pages]
        assert mapped and all(isinstance(p, np.memmap) for p in mapped)  # still mapped, only not resident


def test_first_frame_waits_only_for_the_tiles_around_the_eye(ctx, street_set):
    paging = PagingConfig(load_radius=100.0, wait_radius=3.0, uploads_per_frame=1, frame_ms=None)
    pose = look_at(WORLD + [7.0, 0.0, 2.0], WORLD + [7.0, 6.0, 2.0])  # inside tile 0, facing its facade
    with TiledRenderer(ctx, street_set, "gpu", paging=paging) as tiled:
        tiled.render(K, pose, SIZE)
        s = tiled.stats
        assert s["tiles_resident"] <= 1 + paging.uploads_per_frame and s["tiles_drawn"] >= 1
        assert s["tiles_resident"] < len(street_set)
        for _ in range(len(street_set) + 2):  # then the rest arrive, a bounded number per frame
            tiled.loader.wait_idle()
            tiled.render(K, pose, SIZE)
            assert tiled.stats["uploads"] <= paging.uploads_per_frame
        assert tiled.stats["tiles_resident"] == len(street_set)


def test_priorities_prefer_visible_then_near_and_prefetch_ahead():
    lo = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [-10, 0, 0], [100, 0, 0]], float)
    hi = lo + [10, 10, 5]
    eye = np.array([5.0, 5, 1])
    visible = np.array([True, False, True, False, False])
    config = PagingConfig(load_radius=16.0)
    d, wanted, order = tile_priorities(lo, hi, eye, eye, visible, config)
    assert wanted.tolist() == [True, True, True, True, False]
    assert order.tolist() == [0, 2, 1, 3, 4]
    ahead = eye + [20.0, 0, 0]  # moving along +x: the tile 15 m ahead is wanted too, not those 5 m aside
    d, wanted, order = tile_priorities(lo, hi, eye, ahead, np.zeros(5, bool), PagingConfig(load_radius=4.0))
    assert wanted.tolist() == [True, False, True, False, False] and order[:2].tolist() == [0, 2]


def test_paging_config_is_validated():
    for bad in (dict(gpu_budget=0), dict(gpu_budget=1.5), dict(load_radius=-1.0), dict(load_radius=float("nan")),
                dict(drop_radius=10.0, load_radius=20.0), dict(uploads_per_frame=0), dict(loads_in_flight=0),
                dict(warm_tiles_per_frame=-1), dict(warm_frames=0)):
        with pytest.raises(ValueError):
            PagingConfig(**bad)
    PagingConfig(gpu_budget=1 << 20, load_radius=float("inf"), drop_radius=float("inf"))


def test_release_is_idempotent(ctx, street_set):
    tiled = TiledRenderer(ctx, street_set, "gpu")
    tiled.render(K, views()[0], SIZE, wait="all")
    assert tiled.gpu_bytes() > 0
    renderers = [r.renderer for r in tiled.resident.values()]
    tiled.release()
    tiled.release()
    assert tiled.gpu_bytes() == 0 and all(renderer_gpu_bytes(r)["total"] == 0 for r in renderers)
    with pytest.raises(RuntimeError):
        tiled.render(K, views()[0], SIZE)


# ----------------------------------------------------------------------------------------------
# front ends: render_view, bbcity render / fps, the viewer


def test_render_view_of_a_set(street_set):
    from render.offscreen import clear_cache, render_view, shared_context

    with shared_context():
        pass
    pose = views()[1]
    got = render_view(street_set, K, pose, SIZE, background=BG)
    with TiledRenderer(shared_context(), street_set, "gpu", background=BG) as tiled:
        from render.offscreen import _current

        with _current():
            want = tiled.render(K, pose, SIZE, wait="all")
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError):
        render_view(street_set, K, pose, SIZE, visible=[0])
    clear_cache()


def test_bbcity_render_and_fps_of_a_set(street_set, tmp_path, capsys):
    from bbcity.cli import main as cli_main
    from core.fileio import read_png

    root = str(street_set.root)
    assert cli_main(["-q", "render", root, "--path", "orbit", "--frames", "2", "--size", "160", "120",
                     "--out", str(tmp_path / "frames"), "--gpu-budget", "64"]) == 0
    frames = sorted((tmp_path / "frames").glob("frame_*.png"))
    assert len(frames) == 2
    image = read_png(frames[0])
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20  # the street, not a blank frame
    capsys.readouterr()
    assert cli_main(["fps", root, "--size", "160", "120", "--gpu-budget", "8", "--walk-step", "4",
                     "--walk-frames", "12"]) == 0
    out = capsys.readouterr().out
    assert "tiled model: 4 tiles of 15 m" in out and "12 frames 4 m apart" in out
    assert "paging walk, budget 8 MB: first frame" in out and "paging walk, no budget:" in out
    with pytest.raises(SystemExit) as exit_:  # a budget must be positive: a usage error
        cli_main(["fps", root, "--gpu-budget", "0"])
    assert exit_.value.code == 2


def test_viewer_pages_a_set_headless(street_set, tmp_path):
    pytest.importorskip("moderngl_window")
    from render.viewer import ViewerApp, _make_window

    try:
        wnd = _make_window("headless", (320, 240), "bbcity")
    except Exception as e:  # no EGL/GL 3.3 here
        pytest.skip(f"no headless moderngl-window context: {e}")
    budget = 3 * max(tile_gpu_bound(street_set.load_tile(i), "gpu", LodConfig(), max_texture_size(wnd.ctx))
                     for i in range(len(street_set)))
    app = ViewerApp(street_set, ctx=wnd.ctx, wnd=wnd, screenshot_dir=tmp_path,
                    paging=PagingConfig(gpu_budget=budget, frame_ms=None))
    try:
        assert isinstance(app.renderer, TiledRenderer)
        for _ in range(4):
            stats = app.render_frame(1 / 30)
        assert stats["tiles_resident"] >= 1 and stats["gpu_bytes"] <= budget
        lines = app.hud_lines(stats)
        assert lines[1].startswith(f"quads {stats['quads']} | drawn {stats['billboards_drawn']}/"
                                   f"{street_set.num_billboards}")
        assert (f"tiles {stats['tiles_drawn']}/{stats['tiles_visible']} drawn, {stats['tiles_resident']} loaded | "
                f"GPU {stats['gpu_bytes'] / 2**20:.0f}/{budget / 2**20:.0f} MB") in lines[4]
        assert "deferred" not in lines[4]  # no frame_ms: paging never waits
        assert app.hud_lines({**stats, "paging_deferred": 3})[4].endswith(" MB | deferred 3")
        from render.hud import text_image

        assert text_image(lines).shape[1] < 470  # the HUD fits a 480-pixel window
        app.handle_command("I")
        assert not app.renderer.interpolate
        app.handle_command("L")  # rebuilt without level of detail: tiles paged again
        assert app.render_frame(0.0)["tiles_drawn"] >= 1
        assert len(app.renderer.model_set) == len(street_set)
    finally:
        app.on_close()
        wnd.destroy()


def test_bbcity_view_of_a_set_under_xvfb(street_set, tmp_path):
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from core.fileio import read_png

    if shutil.which("xvfb-run") is None:
        pytest.skip("xvfb-run not on PATH")
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "shot.png"
    bbcity = Path(sys.executable).with_name("bbcity")
    cmd = [str(bbcity)] if bbcity.exists() else [sys.executable, "-m", "bbcity.cli"]
    res = subprocess.run(["xvfb-run", "-a", *cmd, "view", str(street_set.root), "--script-frames", "4",
                          "--screenshot", str(out), "--size", "320", "240", "--gpu-budget", "64"],
                         cwd=root, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(root)})
    assert res.returncode == 0, res.stdout + res.stderr
    assert "loaded | GPU" in res.stderr and "/64 MB" in res.stderr  # the HUD's paging figures
    image = read_png(out)
    assert image.shape[:2] == (240, 320) and len(np.unique(image.reshape(-1, 3), axis=0)) > 50


def test_impostor_images_are_shared_among_the_tiles_drawn(ctx, street_set):
    lod = LodConfig()
    with TiledRenderer(ctx, street_set, "gpu", lod=lod) as tiled:
        tiled.render(K, views()[0], SIZE, wait="all")
        for quota in ("updates_per_frame", "in_full_updates_per_frame"):
            drawn = [getattr(r.renderer.impostors.config, quota) for r in tiled.resident.values()]
            assert tiled.stats["tiles_drawn"] == len(drawn) >= 2
            assert sum(drawn) == getattr(lod.impostors, quota) and max(drawn) - min(drawn) <= 1


def test_program_cache_compiles_once_per_file_and_defines(ctx):
    from render.program import ProgramCache

    cache = ProgramCache(ctx)
    a = cache.get("billboard_blend.glsl", {"STORAGE_SLOTS": 2})
    assert cache.get("billboard_blend.glsl", {"STORAGE_SLOTS": 2}) is a
    assert cache.get("billboard_blend.glsl", {"STORAGE_SLOTS": 4}) is not a
    assert len(cache) == 2
    cache.release()
    cache.release()
    with pytest.raises(RuntimeError):
        cache.get("billboard_blend.glsl")


def test_tiles_share_their_programs(ctx, street_set):
    """Every tile's renderer draws with the set's programs: uploading a tile compiles nothing."""
    with TiledRenderer(ctx, street_set, "gpu", lod=LodConfig()) as tiled:
        tiled.render(K, views()[0], SIZE, wait="all")
        renderers = [r.renderer for r in tiled.resident.values()]
        assert len(renderers) >= 2
        compiled = len(tiled.programs)
        first = renderers[0]
        for r in renderers[1:]:
            assert all(r.decoder.programs[key] is p for key, p in first.decoder.programs.items())
            assert r.decoder.decode_program is first.decoder.decode_program
            assert r.impostors.program is first.impostors.program
        tiled._release_tile(next(iter(tiled.resident)))  # a released tile leaves the programs to the set
        tiled.render(K, views()[0], SIZE, wait="all")
        assert len(tiled.programs) == compiled


def test_far_tiles_warm_before_they_are_drawn(ctx, street_set):
    """A tile uploaded beyond ``wait_radius`` is decoded for the view at most
    ``warm_tiles_per_frame`` texture tiles a frame and drawn only once nothing is left to decode;
    then the frame equals the exact one. A warming tile the eye comes near is drawn at once."""
    budget = 40
    paging = PagingConfig(load_radius=100.0, wait_radius=3.0, warm_tiles_per_frame=budget, warm_frames=1000,
                          frame_ms=None)
    pose = views()[0]  # along the street: every tile visible, tile 0 around the eye
    with TiledRenderer(ctx, street_set, "gpu", background=BG, paging=paging) as tiled, \
            TiledRenderer(ctx, street_set, "gpu", background=BG) as exact:
        want = exact.render(K, pose, SIZE, wait="all")
        warmed_frames = {}
        for frame in range(200):
            tiled.loader.wait_idle()
            image = tiled.render(K, pose, SIZE)
            s = tiled.stats
            assert s["warm_decoded_tiles"] <= budget
            assert s["tiles_drawn"] == s["tiles_resident"] - s["tiles_warming"]
            for i in tiled.warming:
                warmed_frames[i] = warmed_frames.get(i, 0) + 1
            if s["tiles_resident"] == len(street_set) and s["tiles_warming"] == 0:
                break
        assert s["tiles_drawn"] == s["tiles_visible"] == len(street_set)
        assert max(warmed_frames.values()) >= 3  # a tile took several frames of the budget
        np.testing.assert_array_equal(tiled.render(K, pose, SIZE), want)

    paging = PagingConfig(load_radius=100.0, wait_radius=3.0, warm_tiles_per_frame=1, warm_frames=1000, frame_ms=None)
    with TiledRenderer(ctx, street_set, "gpu", background=BG, paging=paging) as tiled:
        for _ in range(len(street_set) + 2):
            tiled.loader.wait_idle()
            tiled.render(K, pose, SIZE)
        assert 2 in tiled.warming  # one texture tile a frame: still warming
        near = look_at(WORLD + [37.0, 0.0, 2.0], WORLD + [42.0, 0.5, 2.0])  # inside tile 2
        tiled.render(K, near, SIZE)
        assert 2 not in tiled.warming and tiled.stats["tiles_drawn"] >= 1


def test_the_frame_budget_gives_paging_the_time_a_frame_has_left():
    """Uploads and warm-up go to frames expected to stay under ``frame_ms`` (the last frame's time
    without paging plus each kind of work's measured cost); a frame that skips work is deferred,
    and after ``max_deferred_frames`` in a row the next pages whatever it costs. No budget: always."""
    free = FrameBudget(PagingConfig(frame_ms=None))
    free.begin_frame()
    free.end_frame(10.0)
    free.spent(1.0, uploads=1, warm_tiles=10)
    assert free.forced and free.allow_upload() and free.warm_tiles(2048) == 2048

    budget = FrameBudget(PagingConfig(frame_ms=80.0, max_deferred_frames=2))
    budget.end_frame(0.125)  # a first frame slower than frame_ms: nothing measured pages in the next
    budget.begin_frame()
    assert not budget.allow_upload() and budget.warm_tiles(2048) == 0
    budget.end_frame(0.07)
    assert budget.deferred == 1
    budget.begin_frame()  # 10 ms left: not enough for an upload of unknown cost (a quarter of 80 ms)
    assert not budget.allow_upload()
    budget.end_frame(0.0625)
    assert budget.deferred == 2
    budget.begin_frame()  # forced, nothing measured: an upload, and an eighth of the warm-up as a probe
    assert budget.allow_upload() and budget.warm_tiles(2048) == 256
    budget.spent(0.0078125, uploads=1)  # 2⁻⁷ s
    budget.spent(0.001953125, warm_tiles=256)  # 2⁻¹⁷ s a texture tile
    budget.end_frame(0.0625)  # 62.5 ms without paging
    assert budget.deferred == 0 and budget.cost("upload") == 0.0078125  # the probe was no refusal
    budget.begin_frame()  # 17.5 ms left: an upload fits (and is reserved), then 1 255 tiles of warm-up
    assert budget.left() == pytest.approx(0.0175)
    assert budget.allow_upload() and budget.left() == pytest.approx(0.0175 - 0.0078125)
    budget.spent(0.0078125, uploads=1)
    assert budget.warm_tiles(2048) == int((0.0175 - 0.0078125) * 131072)
    budget.end_frame(0.0625)
    assert budget.deferred == 1  # fewer warm tiles than asked
    budget.begin_frame()
    budget.end_frame(0.0625)
    assert budget.deferred == 1  # nothing to page: the count stays
    budget.begin_frame()
    budget.end_frame(0.079)
    budget.begin_frame()  # 1 ms left: no upload, and no warm-up step for less than 1/8 of the budget
    assert not budget.allow_upload() and budget.warm_tiles(2048) == 0
    budget.end_frame(0.079)
    assert budget.deferred == 2
    budget.begin_frame()  # deferred twice: this one pages regardless
    assert budget.forced and budget.allow_upload() and budget.warm_tiles(2048) == 2048
    budget.spent(0.5, uploads=1)  # a stall counts at most 4× the average
    budget.end_frame(0.079)
    assert budget.deferred == 0 and budget.cost("upload") <= 4 * 0.0078125
    for bad in (dict(frame_ms=0.0), dict(frame_ms=-5.0), dict(frame_ms=True), dict(frame_ms=float("inf")),
                dict(max_deferred_frames=-1), dict(max_deferred_frames=1.5)):
        with pytest.raises(ValueError):
            PagingConfig(**bad)
    PagingConfig(frame_ms=np.float32(50.0), max_deferred_frames=np.int64(3))


def test_paging_waits_for_frames_with_time_left(ctx, street_set):
    """With no time left in any frame, a tiled renderer pages once every ``max_deferred_frames + 1``
    frames (also before any paging cost is measured), and still pages the whole walk."""
    paging = PagingConfig(load_radius=100.0, wait_radius=3.0, frame_ms=1e-6, max_deferred_frames=2,
                          warm_tiles_per_frame=256)
    pose = views()[0]
    paged = []
    with TiledRenderer(ctx, street_set, "gpu", background=BG, paging=paging) as tiled:
        for frame in range(60):
            tiled.loader.wait_idle()
            tiled.render(K, pose, SIZE)
            s = tiled.stats
            paged.append(bool(s["uploads"] or s["warm_decoded_tiles"]))
        assert s["tiles_resident"] == len(street_set) and s["tiles_warming"] == 0
    frames = np.flatnonzero(paged[1:]) + 1
    assert len(frames) >= len(street_set)
    assert np.all(np.diff(frames) >= 3)  # every third frame at most


def test_predecode_leaves_a_draw_only_the_rest(ctx, street):
    """The decoder's bounded predecode decodes what the draw would, the first ``budget`` tiles,
    and the draw after it decodes the rest; the image is the same."""
    pose = views()[0]
    with BillboardRenderer(ctx, street, "gpu", background=BG, cull="frustum") as plain, \
            BillboardRenderer(ctx, street, "gpu", background=BG, cull="frustum") as warmed:
        want = plain.render(K, pose, SIZE)
        total = plain.stats["decoded_tiles"]
        assert total > 100
        camera = warmed.camera(K, pose, SIZE)
        decoded, left = warmed.warm(camera, 100)
        assert (decoded, left) == (100, total - 100)
        assert warmed.warm(camera, 0) == (0, total - 100)
        got = warmed.render(K, pose, SIZE)
        assert warmed.stats["decoded_tiles"] == total - 100
        np.testing.assert_array_equal(got, want)
        assert warmed.warm(camera, 10) == (0, 0)


def test_paging_walk_reports_the_frames_that_page(ctx, street_set, monkeypatch):
    from render.benchmark import paging_walk
    from render.paging import TileLoader

    request = TileLoader.request

    def request_and_wait(self, i):  # each load done before the next frame, whatever the machine's load
        queued = request(self, i)
        self.wait_idle()
        return queued

    monkeypatch.setattr(TileLoader, "request", request_and_wait)
    poses = _walk([-3.0, 0.0, 2.0], [65.0, 0.0, 2.0], 24)
    paging = PagingConfig(load_radius=10.0, prefetch=12.0, drop_radius=12.0, wait_radius=5.0, frame_ms=None)
    walk = paging_walk(ctx, street_set, poses, SIZE, paging, K=K)
    assert walk["frames"] == len(poses) and walk["uploads"] >= 4
    assert 1 <= walk["paging_frames"] <= len(poses) - 1
    assert max(walk["paging_ms_max"], walk["other_ms_max"]) == pytest.approx(walk["ms_max"])
    assert walk["paging_frames_over_100ms"] <= walk["frames_over_100ms"] <= len(poses) - 1


def test_the_frame_refresh_budget_goes_to_the_nearest_tiles_first(ctx, street_set):
    """A set's tiles share LodConfig.refresh_tiles_per_frame: turning round from the street's far
    end, the frame refreshes at most that many tiles over all its tiles, defers the rest, and
    later frames finish the job."""
    budget = 40
    lod = LodConfig(impostors=None, refresh_tiles_per_frame=budget)
    turned = look_at(WORLD + [40.0, 0.0, 2.0], WORLD + [5.0, 0.0, 2.0])
    with TiledRenderer(ctx, street_set, "gpu", lod=lod) as tiled:
        tiled.render(K, views()[0], SIZE, wait="all")
        assert tiled.stats["refreshed_tiles"] == 0  # nothing held yet: decoded, not refreshed
        tiled.render(K, turned, SIZE, wait="all")
        assert tiled.stats["tiles_drawn"] >= 2
        assert tiled.stats["refreshed_tiles"] == budget and tiled.stats["deferred_tiles"] > budget
        for _ in range(100):
            tiled.render(K, turned, SIZE, wait="all")
            assert tiled.stats["refreshed_tiles"] <= budget
            if tiled.stats["deferred_tiles"] == 0:
                break
        assert tiled.stats["deferred_tiles"] == 0
