"""The model's sky: estimation from capture images, its files, and the sky pass of the renderer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core import DataFormatError
from core.fileio import write_png
from billboards.views import Views
from billboards.sky import (Sky, SkyConfig, estimate_sky, pixel_elevations, read_sky, write_sky)
from render.camera import look_at

W, H = 160, 120
K = np.array([[100.0, 0.0, (W - 1) / 2], [0.0, 100.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
HORIZON, ZENITH = np.array([0.80, 0.86, 0.92]), np.array([0.45, 0.60, 0.85])


def true_sky(elevation: np.ndarray) -> np.ndarray:
    """A sky linear in elevation: horizon colour at 0°, zenith colour at 40°."""
    t = np.clip(np.asarray(elevation) / np.deg2rad(40.0), 0, 1)[..., None]
    return HORIZON * (1 - t) + ZENITH * t


def sky_view(tmp_path, name: str, pose: np.ndarray) -> tuple[Views, np.ndarray]:
    """A capture image whose upper half is the sky gradient and whose lower half is a wall
    (bright uniform grey, which would pass for sky), plus that wall's points, but for a
    hole (a window stereo found no points on) in its middle."""
    elevation = pixel_elevations(K, pose, (W, H))
    image = true_sky(elevation)
    image[H // 2:] = 0.7
    path = tmp_path / f"{name}.png"
    write_png(path, np.clip(np.rint(image * 255), 0, 255).astype(np.uint8))
    # wall points: every pixel of the lower half back-projected to 10 m depth, less the hole
    u, v = np.meshgrid(np.arange(0, W, 0.5), np.arange(H // 2, H, 0.5))
    hole = (u > 40) & (u < 120) & (v > H // 2 + 15) & (v < H - 15)
    u, v = u[~hole], v[~hole]
    rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T
    points = (rays * 10.0) @ pose[:3, :3].T + pose[:3, 3]
    views = Views(K[None].copy(), pose[None].copy(), np.array([[W, H]]), (path,))
    return views, points


def test_sky_from_a_view_with_a_covered_lower_half(tmp_path):
    pose = look_at(np.array([100.0, 50.0, 2.0]), np.array([100.0, 60.0, 2.0]))  # level, looking along +y
    views, points = sky_view(tmp_path, "level", pose)
    config = SkyConfig(bins=16, elevation_deg=(-10.0, 90.0), upper=1.0)
    sky = estimate_sky(views, points, config=config)
    assert sky is not None and sky.colours.shape == (16, 3) and sky.colours.dtype == np.float32
    assert np.all(np.isfinite(sky.colours)) and sky.colours.min() >= 0 and sky.colours.max() <= 1
    elevation = pixel_elevations(K, pose, (W, H))
    upper = elevation[: H // 2 - 12]  # the sky the estimate could see, away from the wall's margin
    err = np.abs(sky.colour(upper) - true_sky(upper))
    assert err.max() < 6 / 255 and err.mean() < 2 / 255
    # the grey wall (and its pointless window) below the cloud's horizon was not taken for
    # sky: below 0° the lowest sky bins' colour
    below = sky.colour(np.deg2rad([-5.0]))[0]
    assert np.abs(below - true_sky(np.deg2rad(5.0))).max() < 0.02 and np.abs(below - 0.7).max() > 0.1
    # without a cloud there is no horizon to be above: no sky
    assert estimate_sky(views, np.zeros((0, 3)), config=config) is None


def test_a_bright_smooth_warm_wall_above_the_cloud_is_not_sky(tmp_path):
    """Brick that stereo left without points (the end wall of a short street) is bright, smooth
    and above the cloud's horizon, but warm: no bin takes its colour; the bins it alone reached
    are interpolated from the blue ones."""
    pose = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 10.0, 2.0]))
    views, points = sky_view(tmp_path, "v", pose)
    image = np.asarray(views.image(0)).copy()
    brick = np.array([150, 110, 80], np.uint8)                 # luma 0.47, red − blue 0.27
    image[H // 2 - 20:H // 2, :] = brick                      # the lowest sky rows, every column
    write_png(views.paths[0], image)
    config = SkyConfig(bins=16, upper=1.0)
    sky = estimate_sky(views, points, config=config)
    colours = np.rint(sky.colours * 255)
    assert np.all(colours[:, 2] > colours[:, 0] + 20), colours      # every bin blue, none brick
    assert np.abs(colours - brick).sum(axis=1).min() > 60
    # the same wall counts as sky when warmth is allowed (what the test guards against)
    warm = estimate_sky(views, points, config=SkyConfig(bins=16, upper=1.0, max_warmth=1.0))
    assert np.abs(np.rint(warm.colours * 255) - brick).sum(axis=1).min() < 30
    with pytest.raises(ValueError, match="max_warmth"):
        SkyConfig(max_warmth=2.0)


def test_sky_bins_without_pixels_are_interpolated_and_nothing_gives_none(tmp_path):
    pose = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 10.0, 2.0]))
    views, points = sky_view(tmp_path, "v", pose)
    sky = estimate_sky(views, points, config=SkyConfig(bins=32, upper=1.0))
    assert np.all(np.isfinite(sky.colours)) and sky.info["bins_measured"] < 32
    np.testing.assert_allclose(sky.colours[-1], sky.colours[-2])  # above what the camera saw: constant
    dark = tmp_path / "dark.png"
    write_png(dark, np.zeros((H, W, 3), np.uint8))
    assert estimate_sky(Views(K[None], pose[None], np.array([[W, H]]), (dark,)), points) is None


def test_sky_files_round_trip_and_bad_files_name_themselves(tmp_path):
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    assert read_sky(model_dir) is None  # no sky.npy: no sky
    sky = Sky(np.linspace(0.2, 0.9, 24, dtype=np.float32).reshape(8, 3), (-5.0, 60.0), {"pixels": 10})
    write_sky(model_dir, sky)
    back = read_sky(model_dir)
    assert np.array_equal(back.colours, sky.colours) and back.elevation_deg == (-5.0, 60.0)
    assert back.info["pixels"] == 10
    meta = json.loads((model_dir / "sky.json").read_text())
    assert write_sky(model_dir, None) is None and read_sky(model_dir) is None  # no sky found: none kept
    assert not (model_dir / "sky.json").exists()
    write_sky(model_dir, sky)
    assert meta["format"] == "bbcity-sky" and meta["bins"] == 8

    def broken(npy=None, **changes):
        if npy is not None:
            np.save(model_dir / "sky.npy", npy)
        (model_dir / "sky.json").write_text(json.dumps({**meta, **changes}))
        with pytest.raises(DataFormatError) as e:
            read_sky(model_dir)
        return str(e.value)

    assert "sky.npy" in broken(np.full((8, 3), np.nan, np.float32))
    assert "sky.npy" in broken(np.full((8, 3), 1.5, np.float32)) and "[0, 1]" in broken()
    assert "sky.npy" in broken(np.zeros((7, 3), np.float32))
    assert "sky.npy" in broken(np.zeros((8, 3), np.float64))
    np.save(model_dir / "sky.npy", sky.colours)
    assert "sky.json" in broken(elevation_deg=[30, 10])
    assert "sky.json" in broken(bins="8")
    assert "sky.json" in broken(format="other")
    (model_dir / "sky.json").unlink()
    with pytest.raises(DataFormatError, match="sky.json"):
        read_sky(model_dir)
    with pytest.raises(ValueError):
        Sky(np.zeros((1, 3), np.float32))
    with pytest.raises(ValueError):
        SkyConfig(elevation_deg=(10.0, 10.0))


@pytest.mark.parametrize("decode", ["gpu", "cpu"])
def test_a_view_with_nothing_in_it_shows_the_sky_by_elevation(decode):
    from render.offscreen import clear_cache, render_view

    from .test_render_gpu import make_model

    sky = Sky(np.random.default_rng(1).uniform(0, 1, (16, 3)).astype(np.float32), (-10.0, 90.0))
    model = make_model(np.zeros((0, 3)), origin=(5.0e5, 4.0e6, 30.0))
    size = (96, 64)
    Kv = np.array([[60.0, 0.0, 47.5], [0.0, 60.0, 31.5], [0.0, 0.0, 1.0]])
    pose = look_at(model.origin + [0.0, 0.0, 2.0], model.origin + [10.0, 3.0, 6.0])  # tilted up
    try:
        image = render_view(model, Kv, pose, size, decode=decode, sky=sky)
        plain = render_view(model, Kv, pose, size, decode=decode)
    finally:
        clear_cache()
    expected = sky.colour(pixel_elevations(Kv, pose, size)) * 255
    assert np.abs(image.astype(np.float64) - expected).max() <= 2
    assert np.all(plain == 0)  # without a sky: the black background as before


def test_billboards_are_drawn_over_the_sky(ctx):
    from render.renderer import BillboardRenderer
    from render.sky import SkyPass, render_over_sky

    from .test_render_gpu import make_model

    model = make_model([[0.0, 0.0, 1.0]], base_yaw=0.0, rank=1, origin=(1.0e6, 2.0e6, 0.0))
    sky = Sky(np.full((4, 3), 0.5, np.float32), (-10.0, 90.0))
    Kv = np.array([[100.0, 0.0, 39.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]])
    pose = look_at(model.origin + [4.0, 0.0, 1.0], model.origin + [0.0, 0.0, 1.0])
    with BillboardRenderer(ctx, model, "gpu", cull="occlusion") as renderer, SkyPass(ctx, sky) as sky_pass:
        plain = renderer.render(Kv, pose, (80, 60))
        over = render_over_sky(renderer, sky_pass, Kv, pose, (80, 60))
        sky_pass.release()
        sky_pass.release()  # idempotent
        with pytest.raises(RuntimeError):
            sky_pass.draw(Kv, pose, (80, 60))
    drawn = np.any(plain != 0, -1)
    assert 0.05 < drawn.mean() < 0.95
    assert np.array_equal(over[drawn], plain[drawn])  # the billboard is unchanged, with culling on
    assert np.all(over[~drawn] == 128)


def test_render_cli_and_viewer_draw_the_models_sky(tmp_path):
    from bbcity.cli import main as cli_main
    from billboards.model_writer import save
    from core.fileio import read_png

    from .test_render_gpu import make_model

    rng = np.random.default_rng(1)
    centres = np.stack([rng.uniform(0, 20, 60), rng.uniform(-2, 2, 60), rng.uniform(0, 5, 60)], 1)
    model = make_model(centres, voxel_size=1.0, yaw_span_deg=360.0, origin=(1e6, 2e6, 0.0))
    model_dir = save(model, tmp_path / "model")
    green = np.array([0.2, 0.8, 0.3], np.float32)
    write_sky(model_dir, Sky(np.tile(green, (4, 1)), (-10.0, 90.0)))
    green_u8 = np.rint(green * 255).astype(int)
    out = tmp_path / "frames"
    assert cli_main(["-q", "render", str(model_dir), "--path", "orbit", "--frames", "2", "--size", "96", "64",
                     "--out", str(out)]) == 0
    for f in sorted(out.glob("frame_*.png")):
        image = read_png(f, (96, 64)).astype(int)
        sky = np.all(np.abs(image - green_u8) <= 1, -1)
        assert 0.2 < sky.mean() < 0.98  # the sky around the billboards

    pytest.importorskip("moderngl_window")
    from billboards.model_reader import load
    from render.viewer import ViewerApp, _make_window

    try:
        wnd = _make_window("headless", (160, 120), "bbcity")
    except Exception as e:  # no EGL/GL 3.3 here
        pytest.skip(f"no headless moderngl-window context: {e}")
    app = ViewerApp(load(model_dir), ctx=wnd.ctx, wnd=wnd, sky=read_sky(model_dir), mode="fly")
    try:
        app.fly.look_from(look_at(model.origin + [10.0, -30.0, 8.0], model.origin + [10.0, 0.0, 2.0]))
        app.handle_command("U")  # no HUD
        app.render_frame(0.0)
        image = app.read_image().astype(int)
    finally:
        app.on_close()
        wnd.destroy()
    sky = np.all(np.abs(image - green_u8) <= 1, -1)
    assert 0.2 < sky.mean() < 0.98
