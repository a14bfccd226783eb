"""Interactive viewer: a real window (moderngl-window) around :class:`BillboardRenderer`.

Fly with the mouse and WASD/QE, or drive along the capture path; toggle GPU/CPU
decode, level of detail (on by default), cycle the culling modes, view interpolation,
wireframe, hide synthesised ground; a HUD over the frame (and the title bar) shows the frame time and fps, the
draw and cull times, quads and billboards drawn (and culled), quads per level of detail,
tiles decoded, and the decode and cull modes (:meth:`ViewerApp.hud_lines`), and the GPU memory
the model holds; a tiled model (:class:`billboards.model_set.ModelSet`) is paged by a
:class:`~render.tiled_renderer.TiledRenderer` under a GPU budget, and the HUD shows its tiles
drawn, visible and loaded and the GPU MB used of the budget. F12 or P saves a screenshot.

:class:`FlyCamera` is pure numpy (world coordinates, z up, float64) so it can be tested
without a window; the drive path is :class:`render.paths.DrivePath`. ``run_viewer(..., script_frames=N)``
renders N frames along the drive path with a fixed time step, saves the last one and
exits (for tests and automation; works under ``xvfb-run``); ``script_keys`` presses
keys through the window's key-event handler, one per frame, on the way.
"""

from __future__ import annotations

import io
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import write_bytes

from .camera import default_intrinsics, look_at
from .hud import HudOverlay
from .paths import drive_path_for
from .culling import CULL_MODES
from .lod import LodConfig
from .gpu_bytes import renderer_gpu_bytes
from .paging import MB, PagingConfig
from .renderer import DECODE_MODES, BillboardRenderer
from .sky import SkyPass
from .target import OffscreenTargets
from .tiled_renderer import TiledRenderer, path_model

logger = logging.getLogger(__name__)

KEYS_HELP = """\
keys:
  mouse drag     look around (fly mode)
  W/A/S/D        fly forward / left / back / right
  Q/E            fly down / up            (hold Shift: 5x faster)
  M              toggle fly / drive (follow the capture path)
  + / -          drive speed up / down    (also fly speed)
  G              toggle GPU / CPU decode
  L              toggle level of detail (GPU decode: fewer eigen images where a texel is under a pixel)
  C              cycle culling: none, frustum, occlusion, hzb, auto
  I              toggle view interpolation (blend sampled directions / nearest)
  F              toggle wireframe (billboard outlines)
  Y              hide / show synthesised ground (what no camera of the capture saw)
  U              toggle the on-screen HUD
  F12 or P       save a screenshot PNG to --screenshot-dir
  H              print this help
  Esc            quit"""

#: the moderngl-window key names the viewer answers (every key of KEYS_HELP)
KEY_NAMES = ("W", "A", "S", "D", "Q", "E", "M", "G", "L", "C", "I", "U", "F", "Y", "P", "H", "F12", "ESCAPE",
             "LEFT_SHIFT", "RIGHT_SHIFT", "EQUAL", "MINUS", "NUMPAD_ADD", "NUMPAD_SUBTRACT")

UP = np.array([0.0, 0.0, 1.0])
MAX_PITCH = np.deg2rad(89.0)


# ----------------------------------------------------------------------------------------------
# pure-numpy camera model


@dataclass
class FlyCamera:
    """A free-flying camera: ``position`` (world, float64), ``yaw`` about +z (0 looks
    along +x, π/2 along +y) and ``pitch`` (positive looks up), radians."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float = 0.0
    pitch: float = 0.0
    speed: float = 5.0  # m/s
    sensitivity: float = 0.003  # radians per pixel of mouse drag

    def __post_init__(self):
        self.position = np.asarray(self.position, np.float64).reshape(3).copy()

    @property
    def forward(self) -> np.ndarray:
        cp = np.cos(self.pitch)
        return np.array([cp * np.cos(self.yaw), cp * np.sin(self.yaw), np.sin(self.pitch)])

    @property
    def right(self) -> np.ndarray:
        return np.array([np.sin(self.yaw), -np.cos(self.yaw), 0.0])

    def rotate(self, dx: float, dy: float) -> None:
        """Mouse drag by (dx, dy) pixels: right turns right, down looks down."""
        self.yaw -= dx * self.sensitivity
        self.pitch = float(np.clip(self.pitch - dy * self.sensitivity, -MAX_PITCH, MAX_PITCH))

    def step(self, dt: float, keys) -> np.ndarray:
        """Move for ``dt`` seconds with the held ``keys`` (letters "w a s d q e", "shift"); returns the pose."""
        keys = {str(k).lower() for k in keys}
        move = np.zeros(3)
        move += self.forward * (("w" in keys) - ("s" in keys))
        move += self.right * (("d" in keys) - ("a" in keys))
        move += UP * (("e" in keys) - ("q" in keys))
        n = np.linalg.norm(move)
        if n > 0:
            speed = self.speed * (5.0 if "shift" in keys else 1.0)
            self.position = self.position + move / n * speed * dt
        return self.pose()

    def pose(self) -> np.ndarray:
        """world_from_cam (4, 4) float64, OpenCV convention."""
        return look_at(self.position, self.position + self.forward)

    def look_from(self, world_from_cam: np.ndarray) -> None:
        """Take position and viewing direction from an OpenCV pose."""
        T = np.asarray(world_from_cam, np.float64)
        self.position = T[:3, 3].copy()
        z = T[:3, 2]
        self.yaw = float(np.arctan2(z[1], z[0]))
        self.pitch = float(np.clip(np.arcsin(np.clip(z[2], -1, 1)), -MAX_PITCH, MAX_PITCH))


# ----------------------------------------------------------------------------------------------
# the window


def _window_class(name: str):
    from moderngl_window import get_local_window_cls

    return get_local_window_cls(name)


class WindowError(InputError):
    """No window of the kind asked for could be opened (no display, a backend not installed)."""


#: moderngl-window's window backends ("auto": pyglet, else headless)
WINDOWS = ("auto", "pyglet", "glfw", "sdl2", "pyside2", "pyqt5", "tk", "headless")


def _make_window(kind: str, size, title: str):
    """A moderngl-window window; "auto" tries pyglet (needs a display) then headless."""
    import moderngl_window

    order = ["pyglet", "headless"] if kind == "auto" else [kind]
    errors = []
    for name in order:
        try:
            cls = _window_class(name)
            extra = {"backend": "egl"} if name == "headless" else {}  # no X display needed
            wnd = cls(title=title, size=tuple(size), gl_version=(3, 3), vsync=False, resizable=True,
                      visible=True, **extra)
            moderngl_window.activate_context(window=wnd)
            if wnd.ctx.version_code < 330:
                raise RuntimeError(f"OpenGL {wnd.ctx.version_code} < 330")
            if name != order[0]:
                logger.warning("window %s unavailable (%s); using %s", order[0], "; ".join(errors), name)
            return wnd
        except Exception as e:
            errors.append(f"{name}: {e}")
    raise WindowError(f"--window {kind}: no window could be opened ({'; '.join(errors)}); without a display run "
                      "under xvfb-run, or give --window headless with --script-frames N")


try:
    from moderngl_window import WindowConfig as _WindowConfig
except ImportError:  # pragma: no cover - moderngl-window is a dependency of the viewer only
    _WindowConfig = object


class ViewerApp(_WindowConfig):
    """The viewer's moderngl-window config: event handlers plus one :meth:`on_render` per frame."""

    title = "bbcity"
    gl_version = (3, 3)

    def __init__(self, model, decode: str = "gpu", cull: str = "frustum", background=(0.55, 0.7, 0.9),
                 screenshot_dir: Path = Path("."), mode: str = "drive", sky=None, lod: bool = True,
                 paging: PagingConfig | None = None, **kwargs):
        super().__init__(**kwargs)
        if decode not in DECODE_MODES:
            raise InputError(f"decode must be one of {DECODE_MODES}")
        if cull not in CULL_MODES:
            raise InputError(f"cull must be one of {CULL_MODES}")
        self.model = model  # a BillboardModel, or a ModelSet (paged)
        self.paging = paging
        self.tiled = paging is not None or not hasattr(model, "centres")
        self.decode = decode
        self.cull = cull
        self.background = background
        self.screenshot_dir = Path(screenshot_dir)
        self.path = drive_path_for(path_model(model))
        self.fly = FlyCamera()
        self.fly.look_from(self.path.pose())
        self.mode = mode
        self.held: set[str] = set()
        self.wireframe = False
        self.hide_synthesised = False
        self.interpolate = True
        self.lod = bool(lod)  # level of detail of the GPU decode (render.lod.LodConfig's defaults)
        self.show_hud = True
        self.overlay = HudOverlay(self.ctx)
        self.targets = OffscreenTargets(self.ctx)
        self.sky_pass = SkyPass(self.ctx, sky) if sky is not None else None  # drawn behind the model
        self.renderer: BillboardRenderer | TiledRenderer | None = None
        self._rebuild()
        self.fps = 0.0
        self._fps_frames, self._fps_t0 = 0, time.perf_counter()
        self._title_t = 0.0
        self._hud_lines: list[str] = []
        self.shots: list[Path] = []

    # -- state
    def _rebuild(self) -> None:
        if self.renderer is not None:
            self.renderer.release()
        options = dict(cull=self.cull, background=self.background, interpolate=self.interpolate,
                       lod=LodConfig() if self.lod else None)
        if self.tiled:
            self.renderer = TiledRenderer(self.ctx, self.model, self.decode, paging=self.paging or PagingConfig(),
                                          **options)
        else:
            self.renderer = BillboardRenderer(self.ctx, self.model, self.decode, **options)

    def pose(self, dt: float) -> np.ndarray:
        if self.mode == "drive":
            return self.path.step(dt)
        return self.fly.step(dt, self.held)

    # -- rendering
    def on_render(self, time_s: float, frame_time: float) -> None:
        self.render_frame(min(float(frame_time), 0.1))

    def render_frame(self, dt: float) -> dict:
        wnd = self.wnd
        w, h = wnd.buffer_size
        pose = self.pose(dt)
        r = self.renderer
        # The frame is drawn offscreen and copied to the window: culling reads the depth back, and
        # a window's framebuffer may not give it (multisampled, or not the buffer being drawn).
        target = self.targets.begin((w, h), r.background)
        self.ctx.wireframe = False
        K = default_intrinsics(w, h)
        if self.sky_pass is not None:
            self.sky_pass.draw(K, pose, (w, h))
        self.ctx.wireframe = self.wireframe
        try:
            if self.tiled:  # paged: what is resident (the first frame waits for the tiles around the eye)
                stats = r.draw(K, pose, (w, h))
            elif self.hide_synthesised:   # every other quad, unculled
                keep = np.flatnonzero(self.model.synthesised == 0)
                stats = r.draw(r.camera(K, pose, (w, h)), keep)
                stats.setdefault("billboards_drawn", len(keep))
            else:
                stats = r.draw(r.camera(K, pose, (w, h)))
        finally:
            self.ctx.wireframe = False
        self.ctx.copy_framebuffer(wnd.fbo, target)
        wnd.use()
        self.ctx.viewport = (0, 0, w, h)
        self._fps_frames += 1
        now = time.perf_counter()
        if now - self._fps_t0 >= 0.5:
            self.fps = self._fps_frames / (now - self._fps_t0)
            self._fps_frames, self._fps_t0 = 0, now
        if now - self._title_t > 0.25:
            self._title_t = now
            self._hud_lines = self.hud_lines(stats)
            wnd.title = " | ".join(self._hud_lines)
        if self.show_hud:
            self.overlay.draw(self._hud_lines, (w, h))
        return stats

    def hud_lines(self, stats: dict | None = None) -> list[str]:
        """The HUD's lines from a frame's renderer stats (missing keys count 0): frame time and
        fps (over the last half second), draw and cull time (frustum plus occlusion) of the
        frame; quads and billboards drawn; quads per level of detail and tiles decoded (GPU
        decode) and impostors drawn and remade; the modes; the GPU memory held (a tiled model:
        tiles drawn / visible, loaded, MB used of the budget, and the frames in a row whose
        paging waited for time, if any)."""
        s = self.renderer.stats if stats is None else stats
        total = self.model.num_billboards
        drawn = int(s.get("billboards_drawn", s.get("instances", total)))
        frame_ms = 1000.0 / self.fps if self.fps > 0 else 0.0
        cull_ms = 1000.0 * (s.get("frustum_s", 0.0) + s.get("cull_s", 0.0))
        if self.decode == "gpu":
            full, reduced, mean = (list(s.get("lod", [])) + [0, 0, 0])[:3]
            quads = int(s.get("quads", 0))
            detail = (f"LOD {'on' if self.lod else 'off'}: full {full} reduced {reduced} mean {mean} | "
                      f"impostors {int(s.get('impostors', 0))}, {int(s.get('impostor_updates', 0))} new")
            deferred = int(s.get("deferred_tiles", 0))  # refreshes left for later frames (a turn)
            decoded = f" | decoded {int(s.get('decoded_tiles', 0))} tiles" + (f", {deferred} deferred" if deferred else "")
        else:
            quads = drawn  # the CPU decode draws a quad per billboard
            detail = "CPU decode of every drawn billboard (no level of detail)"
            decoded = ""
        extra = f" speed {self.path.speed:.0f} m/s" if self.mode == "drive" else ""
        draw_ms = 1000.0 * s.get("draw_s", 0.0)
        if self.tiled:
            budget = s.get("gpu_budget")
            memory = (f" | tiles {int(s.get('tiles_drawn', 0))}/{int(s.get('tiles_visible', 0))} drawn, "
                      f"{int(s.get('tiles_resident', 0))} loaded | GPU {s.get('gpu_bytes', 0) / MB:.0f}/"
                      + ("-" if budget is None else f"{budget / MB:.0f}") + " MB")
            if s.get("paging_deferred", 0):  # paging waiting for a frame with time left
                memory += f" | deferred {int(s['paging_deferred'])}"
        else:
            memory = f" | GPU {self.gpu_bytes() / MB:.0f} MB"
        return [f"bbcity | {self.fps:5.1f} fps, {frame_ms:5.1f} ms/frame | draw {draw_ms:.1f} ms, cull {cull_ms:.1f} ms",
                f"quads {quads} | drawn {drawn}/{total} culled {total - drawn}{decoded}",
                detail,
                f"decode {self.decode} | cull {self.cull} | interpolation {'on' if self.interpolate else 'off'}",
                f"{self.mode}{extra}" + (" | wireframe" if self.wireframe else "")
                + (" | synthesised hidden" if self.hide_synthesised and not self.tiled else "") + memory]

    def gpu_bytes(self) -> int:
        """Bytes the model holds on the GPU (every texture and buffer of its renderer or tiles)."""
        r = self.renderer
        if r is None:
            return 0
        if isinstance(r, TiledRenderer):
            return r.gpu_bytes()
        parts = renderer_gpu_bytes(r)
        return parts["total"] - parts["targets"]

    def hud(self, stats: dict | None = None) -> str:
        """The HUD's lines as one line (the title bar and the log)."""
        return " | ".join(self.hud_lines(stats))

    def read_image(self) -> np.ndarray:
        """The window's current colour buffer as (h, w, 3) uint8, row 0 at the top."""
        w, h = self.wnd.buffer_size
        data = self.wnd.fbo.read(viewport=(0, 0, w, h), components=3, alignment=1)
        return np.frombuffer(data, np.uint8).reshape(h, w, 3)[::-1].copy()

    def screenshot(self, path: Path | None = None) -> Path:
        if path is None:
            self.screenshot_dir.mkdir(parents=True, exist_ok=True)
            path = self.screenshot_dir / time.strftime(f"bbcity-%Y%m%d-%H%M%S-{len(self.shots):03d}.png")
        out = save_image(path, self.read_image())
        self.shots.append(Path(out))
        logger.info("screenshot %s", out)
        return Path(out)

    # -- input
    def _name(self, key) -> str | None:
        k = self.wnd.keys
        for name in KEY_NAMES:
            if getattr(k, name, None) == key and key != "undefined":
                return name
        return None

    def on_key_event(self, key, action, modifiers) -> None:
        name = self._name(key)
        if name is None:
            return
        held = {"LEFT_SHIFT": "shift", "RIGHT_SHIFT": "shift"}.get(name, name.lower())
        if action == self.wnd.keys.ACTION_RELEASE:
            self.held.discard(held)
            return
        if action != self.wnd.keys.ACTION_PRESS:
            return
        self.held.add(held)
        self.handle_command(name, shift=bool(getattr(modifiers, "shift", False)))

    def handle_command(self, name: str, shift: bool = False) -> None:
        """One key press (by moderngl-window key name); also used by scripts and tests."""
        if name == "M":
            if self.mode == "drive":
                self.fly.look_from(self.path.pose())
                self.mode = "fly"
            else:
                self.mode = "drive"
        elif name == "G":
            self.decode = "cpu" if self.decode == "gpu" else "gpu"
            self._rebuild()
        elif name == "L":
            self.lod = not self.lod
            self._rebuild()
        elif name == "C":
            self.cull = CULL_MODES[(CULL_MODES.index(self.cull) + 1) % len(CULL_MODES)]
            self._rebuild()
        elif name == "I":
            self.interpolate = not self.interpolate
            self.renderer.interpolate = self.interpolate
        elif name == "U":
            self.show_hud = not self.show_hud
        elif name == "F":
            self.wireframe = not self.wireframe
        elif name == "Y":
            self.hide_synthesised = not self.hide_synthesised
        elif name in ("F12", "P"):
            self.screenshot()
        elif name == "H":
            print(KEYS_HELP, flush=True)
        elif name in ("EQUAL", "NUMPAD_ADD") or (name == "EQUAL" and shift):
            self.path.speed *= 1.5
            self.fly.speed *= 1.5
        elif name in ("MINUS", "NUMPAD_SUBTRACT"):
            self.path.speed /= 1.5
            self.fly.speed /= 1.5
        elif name == "ESCAPE":
            self.wnd.close()
        logger.info("%s", self.hud())

    def on_mouse_drag_event(self, x, y, dx, dy) -> None:
        if self.mode == "fly":
            self.fly.rotate(dx, dy)

    def on_close(self) -> None:
        if self.renderer is not None:
            self.renderer.release()
            self.renderer = None
        if self.sky_pass is not None:
            self.sky_pass.release()
        self.overlay.release()
        self.targets.release()


class _Modifiers:
    shift = ctrl = alt = False


_NO_MODIFIERS = _Modifiers()


#: Screenshot suffixes → the Pillow format written (the suffix says what the file holds).
IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".bmp": "BMP", ".tif": "TIFF", ".tiff": "TIFF",
                 ".webp": "WEBP"}


def image_format(path: Path | str) -> str:
    """The Pillow format ``path``'s suffix names; ValueError for any other suffix."""
    from PIL import Image

    suffix = Path(path).suffix.lower()
    fmt = IMAGE_FORMATS.get(suffix)
    Image.init()
    if fmt is None or fmt not in Image.SAVE:
        raise InputError(f"{path}: cannot write an image as {suffix or 'a file without a suffix'!r}; "
                         f"use one of {', '.join(s for s, f in IMAGE_FORMATS.items() if f in Image.SAVE)}")
    return fmt


def save_image(path: Path | str, rgb: np.ndarray) -> Path:
    """Atomically write (h, w, 3) uint8 RGB in the format of ``path``'s suffix (PNG, JPEG, …)."""
    from PIL import Image

    fmt = image_format(path)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format=fmt, **({"quality": 95} if fmt == "JPEG" else {}))
    return write_bytes(path, buf.getvalue())


def run_viewer(model, *, size=(1280, 720), decode: str = "gpu", cull: str = "frustum", window: str = "auto",
               screenshot_dir: Path = Path("."), script_frames: int = 0, screenshot: Path | None = None,
               script_dt: float = 1 / 30, mode: str = "drive", script_keys=(), sky=None,
               lod: bool = True, paging: PagingConfig | None = None) -> Path | None:
    """Open the viewer on ``model`` (a BillboardModel, or a ModelSet paged under ``paging``; a
    BillboardModel with ``paging`` is paged as a set of one tile) over ``sky``, a
    :class:`billboards.sky.Sky`, when given (else a plain background), GPU decode with level of
    detail unless ``lod`` is False. With
    ``script_frames`` > 0: render that many frames along the drive path with a fixed ``script_dt``, pressing the moderngl-window key names in
    ``script_keys`` (e.g. "C", "I") one per frame from the first, through the window's
    key-event handler; save the last frame to ``screenshot`` (in the format its suffix
    names, see :data:`IMAGE_FORMATS`; or as PNG in the screenshot dir) and return its path. Otherwise run until the window closes."""
    from moderngl_window.timers.clock import Timer

    if screenshot is not None:
        image_format(screenshot)  # a bad suffix is refused before a window opens
    wnd = _make_window(window, size, "bbcity")
    logger.info("window %s, %s", type(wnd).__module__, wnd.ctx.info["GL_RENDERER"])
    timer = Timer()
    app = ViewerApp(model, decode=decode, cull=cull, screenshot_dir=screenshot_dir, mode=mode, sky=sky, lod=lod,
                    paging=paging, ctx=wnd.ctx, wnd=wnd, timer=timer)
    wnd.config = app
    out = None
    try:
        if script_frames > 0:
            keys = wnd.keys
            for frame in range(int(script_frames)):
                if frame < len(script_keys):
                    name = str(script_keys[frame]).strip().upper()
                    if not hasattr(keys, name):
                        raise InputError(f"unknown key {script_keys[frame]!r} in script_keys")
                    key = getattr(keys, name)
                    if key in (None, "undefined"):  # a headless window has no keyboard
                        app.handle_command(name)
                    else:
                        app.on_key_event(key, keys.ACTION_PRESS, _NO_MODIFIERS)
                        app.on_key_event(key, keys.ACTION_RELEASE, _NO_MODIFIERS)
                app.render_frame(script_dt)
                if hasattr(wnd, "process_events"):
                    wnd.process_events()
            app.ctx.finish()
            out = app.screenshot(screenshot)
            if not wnd.headless:
                wnd.swap_buffers()
            logger.info("%s", app.hud())
        else:
            print(KEYS_HELP, flush=True)
            timer.start()
            while not wnd.is_closing:
                _, dt = timer.next_frame()
                wnd.use()
                wnd.render(0.0, dt)
                if not wnd.is_closing:
                    wnd.swap_buffers()
            timer.stop()
    finally:
        app.on_close()
        wnd.destroy()
    return out
