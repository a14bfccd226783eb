"""The interactive viewer: fly camera and drive path (pure numpy), key toggles on a
headless moderngl-window window, and `bbcity view --script-frames` in a real window
under Xvfb."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from billboards.model_writer import save
from render.culling import CULL_MODES
from render.paths import DrivePath, drive_path_for
from render.viewer import KEYS_HELP, FlyCamera

from .test_render_gpu import make_model

ROOT = Path(__file__).resolve().parents[1]
BG_U8 = np.rint(np.array((0.55, 0.7, 0.9)) * 255).astype(int)


def street_model():
    g = np.stack(np.meshgrid(np.arange(5, 30, 2.0), np.arange(-4, 5, 2.0), np.arange(0, 5, 1.0), indexing="ij"),
                 -1).reshape(-1, 3)
    return make_model(g, rank=2, origin=(1e5 + 0.25, 2e5, 10.0))


# ----------------------------------------------------------------------------------------------
# pure numpy


def test_fly_camera_wasd_moves_in_world():
    cam = FlyCamera(position=(10.0, 20.0, 2.0), yaw=0.0, speed=2.0)  # looking along +x
    p0 = cam.position.copy()
    cam.step(0.5, {"w"})
    np.testing.assert_allclose(cam.position - p0, [1.0, 0, 0], atol=1e-12)
    cam.step(0.5, {"a"})  # left of +x is +y (z up)
    np.testing.assert_allclose(cam.position - p0, [1.0, 1.0, 0], atol=1e-12)
    cam.step(0.5, {"d"})
    cam.step(0.5, {"s"})
    np.testing.assert_allclose(cam.position, p0, atol=1e-12)
    cam.step(0.5, {"e"})
    np.testing.assert_allclose(cam.position - p0, [0, 0, 1.0], atol=1e-12)
    cam.step(0.5, {"q", "shift"})
    np.testing.assert_allclose(cam.position - p0, [0, 0, -4.0], atol=1e-12)
    cam.yaw = np.pi / 2  # looking along +y: forward is +y, right is +x
    cam.position = p0.copy()
    pose = cam.step(0.5, {"w", "d"})
    np.testing.assert_allclose(cam.position - p0, np.array([1.0, 1.0, 0]) / np.sqrt(2), atol=1e-12)
    np.testing.assert_allclose(pose[:3, 2], [0, 1, 0], atol=1e-12)  # OpenCV +z = viewing direction
    np.testing.assert_allclose(pose[:3, 3], cam.position)
    assert pose[2, 1] < 0  # image down (+y_cam) points to world -z


def test_fly_camera_mouse_and_look_from():
    cam = FlyCamera()
    cam.rotate(100, 0)  # drag right: turn right (clockwise seen from above)
    assert cam.yaw < 0
    cam.rotate(0, 1e6)
    assert cam.pitch == pytest.approx(-np.deg2rad(89))
    other = FlyCamera(position=(1, 2, 3), yaw=0.7, pitch=0.2)
    cam.look_from(other.pose())
    np.testing.assert_allclose([cam.yaw, cam.pitch], [0.7, 0.2], atol=1e-12)
    np.testing.assert_allclose(cam.position, [1, 2, 3])


def test_drive_path_interpolates_and_loops():
    path = DrivePath([[0, 0, 2], [10, 0, 2], [10, 10, 2]], speed=4.0, lookahead=1.0)
    assert path.length == pytest.approx(20)
    np.testing.assert_allclose(path.position(5), [5, 0, 2])
    np.testing.assert_allclose(path.position(15), [10, 5, 2])
    np.testing.assert_allclose(path.position(25), [5, 0, 2])  # loops
    np.testing.assert_allclose(path.heading(2), [1, 0, 0])
    np.testing.assert_allclose(path.heading(12), [0, 1, 0])
    pose = path.step(0.5)
    np.testing.assert_allclose(pose[:3, 3], [2, 0, 2])
    np.testing.assert_allclose(pose[:3, 2], [1, 0, 0], atol=1e-12)
    for _ in range(10):
        path.step(0.5)
    assert path.s == pytest.approx(22 % 20)


def test_drive_path_for_model_without_dataset():
    model = street_model()
    path = drive_path_for(model)
    c = model.origin + model.centres.astype(np.float64)
    assert path.points[0][0] < c[:, 0].min() < c[:, 0].max() < path.points[-1][0]
    assert path.points[0][2] == pytest.approx(c[:, 2].min() + 2.0)
    assert "F12" in KEYS_HELP and "W/A/S/D" in KEYS_HELP


# ----------------------------------------------------------------------------------------------
# in-process, headless window: the key toggles


def test_every_key_the_help_names_reaches_the_viewer():
    """A key in the help that the window's key handler does not map is a key that does nothing."""
    import re

    from render.viewer import KEY_NAMES, KEYS_HELP

    named = set()
    for line in KEYS_HELP.splitlines()[1:]:
        keys = line.strip().split("  ")[0]
        named |= {k for k in re.split(r"[/ ]+", keys) if re.fullmatch(r"[A-Z]|F\d+", k)}
    assert {"Y", "F", "U", "P", "F12"} <= named
    assert named <= set(KEY_NAMES), sorted(named - set(KEY_NAMES))


def test_viewer_toggles_headless(tmp_path):
    mglw = pytest.importorskip("moderngl_window")
    from render.viewer import ViewerApp, _make_window

    try:
        wnd = _make_window("headless", (480, 270), "bbcity")
    except Exception as e:  # no EGL/GL 3.3 here
        pytest.skip(f"no headless moderngl-window context: {e}")
    app = ViewerApp(street_model(), ctx=wnd.ctx, wnd=wnd, screenshot_dir=tmp_path)
    try:
        app.render_frame(1 / 30)
        app._title_t = 0.0  # the HUD text refreshes every 0.25 s
        app.render_frame(0.0)
        ref = app.read_image()
        assert (np.abs(ref.astype(int) - BG_U8).sum(-1) > 6).mean() > 0.05
        app.handle_command("U")  # HUD off: only its corner changes
        app.render_frame(0.0)
        bare = app.read_image()
        changed = np.any(bare != ref, axis=-1)
        ys, xs = np.nonzero(changed)
        from render.hud import text_image

        text = text_image(app.overlay._lines)  # the HUD's pure white text pixels land upright, 1:1
        assert changed.mean() > 0.01 and ys.min() < 5 and xs.min() < 5
        assert ys.max() < text.shape[0] <= 120 and xs.max() < text.shape[1] < 470  # the top-left corner only
        white = np.all(text[..., :3] == 255, axis=-1) & (text[..., 3] == 255)
        shown = np.all(ref[:text.shape[0], :text.shape[1]] == 255, axis=-1)
        assert white.sum() > 50 and np.array_equal(shown, white)
        assert not changed[-10:].any() and not changed[:, -10:].any()
        app.handle_command("U")
        # the HUD: frame time, draw and cull time, quads and billboards, levels of detail, tiles decoded
        assert app.overlay._lines == app._hud_lines  # what the last refresh drew
        lines = app.hud_lines()
        assert app.hud() == " | ".join(lines)
        stats = app.renderer.stats
        assert app.lod and app.renderer.decoder.lod is not None  # level of detail on by default
        total = app.model.num_billboards
        assert f"quads {stats['quads']} | drawn {stats['billboards_drawn']}/{total}" in lines[1]
        assert lines[1].endswith(f" | decoded {stats['decoded_tiles']} tiles")
        full, reduced, mean = stats["lod"]
        assert lines[2] == (f"LOD on: full {full} reduced {reduced} mean {mean} | "
                            f"impostors {stats['impostors']}, {stats['impostor_updates']} new")
        assert "fps," in lines[0] and " ms/frame | draw " in lines[0] and ", cull " in lines[0]
        fake = {"draw_s": 0.0125, "frustum_s": 0.001, "cull_s": 0.0025, "quads": 7, "billboards_drawn": 9,
                "lod": [4, 2, 1], "decoded_tiles": 3, "impostors": 5, "impostor_updates": 2}
        app.fps = 50.0
        lines = app.hud_lines(fake)
        assert lines[0].endswith("50.0 fps,  20.0 ms/frame | draw 12.5 ms, cull 3.5 ms")
        assert lines[1] == f"quads 7 | drawn 9/{total} culled {total - 9} | decoded 3 tiles"
        assert lines[2] == "LOD on: full 4 reduced 2 mean 1 | impostors 5, 2 new"
        assert app.hud_lines({**fake, "deferred_tiles": 40})[1].endswith(" | decoded 3 tiles, 40 deferred")
        assert app.hud_lines({})[2] == "LOD on: full 0 reduced 0 mean 0 | impostors 0, 0 new"  # .get defaults
        app.handle_command("L")  # level of detail off: every eigen image
        assert not app.lod and app.renderer.decoder.lod is None and "LOD off" in app.hud()
        stats = app.render_frame(0.0)
        assert stats["lod"][1:] == [0, 0] and stats["quads"] > 0
        app.handle_command("L")
        assert app.lod and app.renderer.decoder.lod is not None and "LOD on" in app.hud()
        app.handle_command("I")
        assert not app.interpolate and not app.renderer.interpolate and "interpolation off" in app.hud()
        app.handle_command("I")
        app.handle_command("G")
        assert app.decode == "cpu"
        stats = app.render_frame(0.0)
        assert f"quads {stats['billboards_drawn']} | drawn" in app.hud() and "CPU decode" in app.hud()
        app.handle_command("G")
        seen = []
        for _ in CULL_MODES:
            app.handle_command("C")
            seen.append(app.cull)
            stats = app.render_frame(0.0)
            assert stats["instances"] > 0
        assert sorted(seen) == sorted(CULL_MODES) and "frustum" in seen
        app.handle_command("F")
        app.render_frame(0.0)
        assert app.wireframe and "wireframe" in app.hud()
        app.handle_command("F")
        flags = app.model.synthesised
        try:   # Y hides the quads marked synthesised (here every other one)
            app.model.synthesised = (np.arange(total) % 2).astype(np.uint8)
            app.handle_command("Y")
            stats = app.render_frame(0.0)
            assert "synthesised hidden" in app.hud() and stats["billboards_drawn"] == total - total // 2
            app.handle_command("Y")
            assert "synthesised" not in app.hud()
        finally:
            app.model.synthesised = flags
        app.handle_command("M")
        assert app.mode == "fly"
        p0 = app.fly.position.copy()
        app.held = {"w"}
        app.render_frame(0.5)
        assert app.fly.position[0] > p0[0]
        speed = app.path.speed
        app.handle_command("EQUAL")
        assert app.path.speed > speed
        app.handle_command("P")
        assert len(app.shots) == 1 and app.shots[0].exists()
    finally:
        app.on_close()
        wnd.destroy()


# ----------------------------------------------------------------------------------------------
# the real window under Xvfb


def test_bbcity_view_script_screenshot_under_xvfb(tmp_path):
    if shutil.which("xvfb-run") is None:
        pytest.skip("xvfb-run not on PATH")
    from core.fileio import read_png

    save(street_model(), tmp_path / "model")
    out = tmp_path / "out.png"
    bbcity = Path(sys.executable).with_name("bbcity")
    cmd = [str(bbcity)] if bbcity.exists() else [sys.executable, "-m", "bbcity.cli"]
    res = subprocess.run(["xvfb-run", "-a", *cmd, "view", str(tmp_path / "model"), "--script-frames", "4",
                          "--script-keys", "C,I,L", "--screenshot", str(out), "--size", "320", "240"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert res.returncode == 0, res.stdout + res.stderr
    assert "pyglet" in res.stderr  # a real window, not the headless fallback
    # the keys went through the window's key handler: frustum → occlusion, interpolation off, level of detail off
    assert "cull occlusion | interpolation on" in res.stderr and "LOD on:" in res.stderr
    assert "cull occlusion | interpolation off" in res.stderr and "LOD off:" in res.stderr
    img = read_png(out)
    assert img.shape[:2] == (240, 320)
    rgb = img[..., :3].reshape(-1, 3).astype(int)
    assert len(np.unique(rgb, axis=0)) > 50  # not blank
    assert (np.abs(rgb - BG_U8).sum(-1) > 6).mean() > 0.05  # billboards over the sky
    assert (np.abs(rgb - BG_U8).sum(-1) <= 6).mean() > 0.1  # and the sky around them


def test_culling_in_a_window_draws_what_frustum_culling_draws(tmp_path):
    """In a real window (xvfb) the frame is drawn offscreen and copied in, so the HZB's depth
    read-back works: hzb and auto give frustum culling's screenshot (the HUD hidden)."""
    if shutil.which("xvfb-run") is None:
        pytest.skip("xvfb-run not on PATH")
    from core.fileio import read_png

    save(street_model(), tmp_path / "model")
    bbcity = Path(sys.executable).with_name("bbcity")
    cmd = [str(bbcity)] if bbcity.exists() else [sys.executable, "-m", "bbcity.cli"]
    shots = {}
    for cull in ("frustum", "hzb", "auto"):
        out = tmp_path / f"{cull}.png"
        res = subprocess.run(["xvfb-run", "-a", *cmd, "view", str(tmp_path / "model"), "--cull", cull,
                              "--script-frames", "3", "--script-keys", "U", "--screenshot", str(out),
                              "--size", "320", "240"],
                             cwd=ROOT, capture_output=True, text=True, timeout=60,
                             env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert res.returncode == 0, res.stdout + res.stderr
        shots[cull] = read_png(out)[..., :3]
    assert np.mean(np.abs(shots["frustum"].astype(int) - BG_U8).sum(-1) > 6) > 0.05
    for cull in ("hzb", "auto"):
        assert np.array_equal(shots[cull], shots["frustum"]), cull


def test_no_display_is_one_line_naming_the_window(tmp_path, monkeypatch, caplog):
    """Issue 35: pyglet without a display ended in a traceback; it is one line naming --window."""
    from bbcity.cli import main

    save(street_model(), tmp_path / "model")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(tmp_path / "model"), "--window", "pyglet"]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and errors[0].startswith("--window pyglet: no window could be opened"), errors
