"""The exported web site in a real browser (Debian's Chromium, headless, through Playwright): its
frames against render.offscreen.render_view at the same camera and size, the view in the link, a
tiled set streamed within its GPU budget, refusals of bbcity export web and bbcity serve."""

from __future__ import annotations

import shutil
import socket

import numpy as np
import pytest

from billboards.model_reader import load
from billboards.model_set import load_model_set, split_model
from billboards.model_writer import save
from billboards.sky import Sky, read_sky, write_sky
from bbcity.cli import main
from core.fileio import DataFormatError
from core.metrics import psnr
from render.offscreen import render_view
from share.browser import open_site, page_image
from share.web_camera import view_camera
from share.web_site import WebConfig, export_web

from .test_export_gltf import ORIGIN, street_model

SIZE = (320, 240)
#: Views of street_model (x, y, z relative to its origin; yaw°, pitch°, fov°): from the ground's
#: side, along the quads, from behind the facade looking down.
VIEWS = [(2.0, -3.0, 1.2, 90.0, -10.0, 70.0), (5.5, 1.0, 1.5, 175.0, -15.0, 75.0), (1.5, 7.0, 3.0, -95.0, -35.0, 80.0)]


def world_view(view):
    return (view[0] + ORIGIN[0], view[1] + ORIGIN[1], view[2] + ORIGIN[2], *view[3:])


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    out = save(street_model(), tmp_path_factory.mktemp("web") / "model")
    colours = np.linspace([0.55, 0.45, 0.40], [0.35, 0.55, 0.90], 8).astype(np.float32)
    write_sky(out, Sky(colours, (-10.0, 90.0)))
    return out


@pytest.fixture(scope="module")
def site(model_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("site") / "site"
    report = export_web(model_dir, out)
    assert report["tiles"] == 1 and (out / "model" / "model.json").is_file()
    return out


def reference(model_dir, view, size=SIZE, sky: bool = True):
    K, T = view_camera(world_view(view), size)
    return render_view(load(model_dir), K, T, size, sky=read_sky(model_dir) if sky else None)


@pytest.mark.parametrize("gl", ["llvmpipe", "swiftshader"])
def test_frames_match_the_desktop_renderer(model_dir, site, gl):
    """Same decode, same camera: ≥ 30 dB against render_view at each view (measured: llvmpipe, the
    desktop's rasterizer under ANGLE, 55–75 dB; SwiftShader 35–45 dB, its rasterization rules)."""
    with open_site(site, SIZE, gl=gl) as page:
        assert page.first_frame_ms > 0
        for view in VIEWS:
            page.evaluate("(v) => window.bbcity.setView(v)", list(world_view(view)))
            web = page_image(page, SIZE)
            ref = reference(model_dir, view)
            drawn = (reference(model_dir, view, sky=False) != 0).any(axis=2)
            assert drawn.mean() > 0.1, "the view shows too little of the model to compare"
            score, on_model = psnr(web, ref), psnr(web, ref, mask=drawn)
            print(f"{gl} view {view}: {score:.1f} dB, {on_model:.1f} dB on the model's {drawn.mean():.0%} of pixels")
            assert score >= 30.0 and on_model >= 25.0
        stats = page.evaluate("window.bbcity.stats()")
        assert stats["quads"] > 0 and stats["resident"] == 1


def test_nearest_filter_and_culling_off_draw_the_same(model_dir, site):
    view = VIEWS[0]
    with open_site(site, SIZE, view=world_view(view), query="&filter=nearest&cull=none") as page:
        web = page_image(page, SIZE)
    K, T = view_camera(world_view(view), SIZE)
    from render.offscreen import renderer_for, shared_context
    from render.sky import render_over_sky

    model = load(model_dir)
    renderer = renderer_for(model, linear=False)
    with shared_context():
        ref = render_over_sky(renderer, None, K, T, SIZE)
    covered = (ref != 0).any(axis=2)  # the plain background: compare where the model drew
    assert covered.mean() > 0.1
    assert psnr(web, ref, mask=covered) >= 30.0


def test_the_view_is_in_the_link(site):
    """A link with #x,y,z,yaw,pitch,fov opens at that view; moving the view rewrites the link."""
    view = world_view(VIEWS[1])
    with open_site(site, SIZE, view=view) as page:
        first = page_image(page, SIZE)
        shown = page.evaluate("window.bbcity.stats()")
        assert shown["quads"] > 0
        moved = world_view(VIEWS[2])
        page.evaluate("(v) => window.bbcity.setView(v)", list(moved))
        page.wait_for_function("(x) => location.hash.startsWith('#' + x)", arg=f"{moved[0]:.3f}".rstrip("0").rstrip("."))
        numbers = [float(v) for v in page.evaluate("location.hash")[1:].split(",")]
        np.testing.assert_allclose(numbers, moved, atol=1e-3)
        page.keyboard.down("w")  # fly forward along the line of sight: the link follows
        page.wait_for_timeout(400)
        page.keyboard.up("w")
        page.wait_for_timeout(300)
        flown = [float(v) for v in page.evaluate("location.hash")[1:].split(",")]
        forward = np.array([np.cos(np.radians(moved[4])) * np.cos(np.radians(moved[3])),
                            np.cos(np.radians(moved[4])) * np.sin(np.radians(moved[3])), np.sin(np.radians(moved[4]))])
        step = np.subtract(flown[:3], moved[:3])
        assert step @ forward > 0.3 and np.linalg.norm(np.cross(step, forward)) < 1e-2 * np.linalg.norm(step)
        page.evaluate("(v) => { location.hash = v.join(','); }", list(view))
        page.wait_for_function("(x) => window.bbcity.stats().quads > 0 && location.hash.length > 1", arg=0)
        page.wait_for_timeout(100)
        again = page_image(page, SIZE)
    assert psnr(first, again) >= 60.0


def test_a_tiled_set_streams_within_its_budget(model_dir, tmp_path):
    """Tiles are loaded nearest first and released beyond the budget as the eye walks along the
    street; what is resident never exceeds the budget. With every tile resident, the frame matches
    the desktop's tiled renderer (each tile at its own origin)."""
    tiled = split_model(model_dir, tmp_path / "tiled", tile_size=2.0)
    model_set = load_model_set(tiled)
    assert len(model_set) >= 5
    probe = export_web(tiled, tmp_path / "probe")
    import json

    sizes = [t["gpu_bytes"] for t in json.loads((tmp_path / "probe" / "site.json").read_text())["tiles"]]
    budget = 2.5 * max(sizes)
    site = tmp_path / "site"
    export_web(tiled, site, WebConfig(gpu_budget_mb=budget / 1e6))
    assert probe["tiles"] == len(model_set)
    walk = [(x, 0.0, 3.0, 0.0, -30.0, 60.0) for x in np.linspace(-6.0, 16.0, 12)]
    with open_site(site, SIZE, view=world_view(walk[0])) as page:
        for view in walk:
            page.evaluate("(v) => window.bbcity.setView(v)", list(world_view(view)))
            page.evaluate("window.bbcity.idle()")
            page.evaluate("window.bbcity.render()")
        stats = page.evaluate("window.bbcity.stats()")
    view = VIEWS[0]
    with open_site(tmp_path / "probe", SIZE, view=world_view(view)) as page:  # every tile within its budget
        page.evaluate("window.bbcity.idle()")
        web = page_image(page, SIZE)
        assert page.evaluate("window.bbcity.stats()")["resident"] == len(model_set)
    print("tiled walk:", stats)
    assert stats["peakMB"] <= stats["budgetMB"] + 1e-9
    assert stats["loads"] > stats["resident"] and stats["releases"] > 0
    K, T = view_camera(world_view(view), SIZE)
    ref = render_view(model_set, K, T, SIZE, sky=read_sky(tiled))
    drawn = (render_view(model_set, K, T, SIZE) != 0).any(axis=2)
    assert drawn.mean() > 0.1
    covered_by_resident = psnr(web, ref, mask=drawn)
    print(f"tiled frame: {covered_by_resident:.1f} dB where the model drew")
    assert covered_by_resident >= 30.0


def test_export_web_refusals(model_dir, site, tmp_path, capsys):
    with pytest.raises(FileExistsError, match="already exists"):
        export_web(model_dir, site)
    with pytest.raises(DataFormatError):
        export_web(tmp_path, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="gpu_budget_mb"):
        WebConfig(gpu_budget_mb=float("nan"))
    assert main(["export", "web", str(model_dir), "--out", str(site)]) == 2
    assert main(["export", "web", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    with pytest.raises(SystemExit) as exit_:
        main(["export", "web", str(model_dir), "--out", str(tmp_path / "y"), "--fov", "0"])
    assert exit_.value.code == 2
    assert not (tmp_path / "y").exists()


def test_export_refuses_nan_pages_and_out_inside_the_model(model_dir, tmp_path):
    damaged = tmp_path / "damaged"
    shutil.copytree(model_dir, damaged)
    page = np.load(damaged / "coef_000.npy")
    page[0, 0] = np.nan
    np.save(damaged / "coef_000.npy", page)
    with pytest.raises(DataFormatError, match="coef_000.npy: contains NaN"):
        export_web(damaged, tmp_path / "site")
    assert main(["export", "gltf", str(damaged), "--out", str(tmp_path / "x.glb")]) == 2
    copy = tmp_path / "copy"
    shutil.copytree(model_dir, copy)
    before = sorted(p.name for p in copy.iterdir())
    for kind, out in (("web", "site"), ("gltf", "x.glb"), ("3dtiles", "tiles")):
        assert main(["export", kind, str(copy), "--out", str(copy / out)]) == 2
    assert sorted(p.name for p in copy.iterdir() if not p.name.startswith(".")) == before


def test_fps_refuses_a_site_of_another_model_before_timing(site, tmp_path, capsys):
    other = save(street_model(seed=1), tmp_path / "other")
    assert main(["fps", str(other), "--web", str(site), "--gpu-frames", "1", "--cpu-frames", "1"]) == 2
    assert "fps" not in capsys.readouterr().out  # no row was timed


def test_serve_refusals(site, tmp_path):
    assert main(["serve", str(tmp_path)]) == 2  # not a site
    assert main(["serve", str(site), "--host", ""]) == 2
    broken = tmp_path / "broken"
    shutil.copytree(site, broken)
    (broken / "site.json").write_text("{bad")
    assert main(["serve", str(broken)]) == 2
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["serve", str(site), "--port", str(port)]) == 2
