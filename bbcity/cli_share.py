"""The command line of sharing a model: ``export web|gltf|3dtiles``, ``serve`` and ``fps --web``.

Each option's default comes from its config dataclass (share.web_site.WebConfig,
share.gltf.GltfConfig, share.tiles3d.Tiles3dConfig); bad values are refused by them in one line
before any work (exit 2).
"""

from __future__ import annotations

import logging
from pathlib import Path

from core.errors import InputError

from .options import float_range, gpu_budget_mb, int_range

logger = logging.getLogger(__name__)


def add_export_kinds(kinds) -> None:
    """``export web``, ``export gltf`` and ``export 3dtiles`` on the ``export`` command's kinds."""
    from share.tiles3d import REFINES, Tiles3dConfig
    from share.web_site import WebConfig

    w = kinds.add_parser(
        "web", help="a model or tiled set → a static web site (WebGL2 viewer, the view in the link)",
        description="Write SITE: index.html, the viewer's JavaScript, the desktop's shaders as GLSL ES 3.00 "
                    "(shaders.json), the model's arrays and atlases as raw binary files, and site.json. Any static "
                    "HTTP server serves it (bbcity serve SITE for a local look); a link to a view ends in "
                    "#x,y,z,yaw,pitch[,fov] (world metres, degrees). A tiled set's tiles are streamed nearest "
                    "first within --gpu-budget. The site is written whole or not at all; an existing SITE is "
                    "refused.")
    w.add_argument("model", type=Path, help="billboard model directory, plain or tiled (tiles.json)")
    w.add_argument("--out", type=Path, required=True, help="new site folder")
    w.add_argument("--dataset", type=Path, default=None, metavar="DIR",
                   help="dataset whose camera-0 poses are the start view and the capture path played on P "
                        "(default: the model's, when it is still there)")
    w.add_argument("--gpu-budget", type=gpu_budget_mb, default=WebConfig.gpu_budget_mb, metavar="MB",
                   help="GPU memory a tiled set's resident tiles may take in the browser "
                        f"(default {WebConfig.gpu_budget_mb:g})")
    w.add_argument("--fov", type=float_range(1.0, 170.0, lo_open=False), default=WebConfig.fov_deg,
                   metavar="DEG", help=f"vertical field of view (default {WebConfig.fov_deg:g})")
    w.set_defaults(func=_run_export_web, check_options=_web_config)

    g = kinds.add_parser(
        "gltf", help="a model → one binary glTF (.glb): textured quads for Blender, three.js, model-viewer",
        description="Write one .glb: the facade layer and ground as textured quads (the sampled direction "
                    "looking straight at each, or the mean texture), billboards as alpha-masked quads facing the "
                    "capture path, unlit, in glTF's y-up axes with the model's origin on the root node.")
    g.add_argument("model", type=Path, help="billboard model directory")
    g.add_argument("--out", type=Path, required=True, help="new .glb file")
    _texture_option(g)
    g.set_defaults(func=_run_export_gltf, check_options=_gltf_config, writes_file=True)

    t = kinds.add_parser(
        "3dtiles", help="a tiled set (or a model) → 3D Tiles 1.1: tileset.json and one GLB per tile (Cesium)",
        description="Write DIR/tileset.json and DIR/tiles/NAME.glb: one tile per model tile, box bounding volumes "
                    "from the tiles' quads, geometric errors from their texel size. The folder is written whole "
                    "or not at all; an existing DIR is refused.")
    t.add_argument("model", type=Path, help="tiled model set (tiles.json) or plain model directory")
    t.add_argument("--out", type=Path, required=True, help="new tileset folder")
    t.add_argument("--refine", choices=REFINES, default=Tiles3dConfig.refine,
                   help=f"the root's refinement (default {Tiles3dConfig.refine})")
    t.add_argument("--lonlat-height", type=float_range(allow_inf=False), nargs=3, default=None,
                   metavar=("LON", "LAT", "H"),
                   help="place the world's (0, 0, 0) at this WGS84 longitude, latitude (degrees) and height (m) "
                        "on the globe (default: local coordinates)")
    _texture_option(t)
    t.set_defaults(func=_run_export_3dtiles, check_options=_tiles3d_config)


def _texture_option(p) -> None:
    from share.gltf import TEXTURES, GltfConfig

    p.add_argument("--texture", choices=TEXTURES, default=GltfConfig.texture,
                   help=f"each quad's texture (default {GltfConfig.texture})")


def _web_config(args):
    from share.web_site import WebConfig

    return WebConfig(gpu_budget_mb=args.gpu_budget, fov_deg=args.fov)


def _refuse_out_inside(out: Path, model: Path) -> None:
    """An export's --out inside the model directory it reads would change that directory."""
    if out.resolve().is_relative_to(model.resolve()):
        raise InputError(f"--out {out} lies inside the model directory {model}; write the export elsewhere")


def _run_export_web(args) -> int:
    from share.web_site import export_web

    _refuse_out_inside(args.out, args.model)
    report = export_web(args.model, args.out, _web_config(args), dataset=args.dataset)
    print(f"wrote {report['site']}: {report['tiles']} tile(s), {report['site_bytes'] / 1e6:.1f} MB "
          f"({report['size_ratio']:.2f}× the model), {report['path_poses']} capture-path poses, "
          f"{report['seconds']:.1f} s; look at it with: bbcity serve {report['site']}")
    return 0


def _gltf_config(args):
    from share.gltf import GltfConfig

    return GltfConfig(texture=args.texture)


def _run_export_gltf(args) -> int:
    from billboards.model_set import is_model_set
    from share.gltf import export_gltf

    _refuse_out_inside(args.out, args.model)
    if is_model_set(args.model):
        raise InputError(f"{args.model} is a tiled model set: export gltf writes one model "
                         f"(export 3dtiles writes a set, a GLB per tile)")
    r = export_gltf(args.model, args.out, _gltf_config(args))
    print(f"wrote {args.out}: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                            for k, v in r.items() if not isinstance(v, (list, dict))))
    return 0


def _tiles3d_config(args):
    from share.gltf import GltfConfig
    from share.tiles3d import Tiles3dConfig

    return Tiles3dConfig(gltf=GltfConfig(texture=args.texture), refine=args.refine,
                         lonlat_height=None if args.lonlat_height is None else tuple(args.lonlat_height))


def _run_export_3dtiles(args) -> int:
    from share.tiles3d import export_3dtiles

    _refuse_out_inside(args.out, args.model)
    r = export_3dtiles(args.model, args.out, _tiles3d_config(args))
    print(f"wrote {args.out}: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                            for k, v in r.items() if not isinstance(v, (list, dict))))
    return 0


def add_serve(sub) -> None:
    p = sub.add_parser("serve", help="serve an exported site over HTTP for a local look",
                       description="Serve SITE (written by bbcity export web) at http://HOST:PORT/ until Ctrl-C. "
                                   "Any static HTTP server does the same; this one sends no cache headers.")
    p.add_argument("site", type=Path, help="site folder (bbcity export web)")
    p.add_argument("--port", type=int_range(0, 65535), default=8000, help="TCP port (default 8000; 0: any free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    p.set_defaults(func=_run_serve)


def _run_serve(args) -> int:
    from share.serve import make_server, site_url

    server = make_server(args.site, args.port, args.host)
    print(f"serving {args.site} at {site_url(args.host, server.server_port)} (Ctrl-C to stop)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:  # the way to stop a server: not an error
        print("stopped")
    finally:
        server.server_close()
    return 0


def add_fps_web_options(p) -> None:
    """``fps --web SITE --browser-gl KIND``: the same capture path in a browser."""
    from share.browser import BROWSER_GL

    p.add_argument("--web", type=Path, default=None, metavar="SITE",
                   help="also walk the capture path in headless Chromium through SITE (bbcity export web of MODEL) "
                        "and print its frame rate beside this renderer's")
    p.add_argument("--browser-gl", choices=list(BROWSER_GL), default="llvmpipe",
                   help="Chromium's software WebGL2: llvmpipe (Mesa, the rasterizer this renderer uses) or "
                        "swiftshader (default llvmpipe)")


def check_fps_web(args) -> None:
    """Before any timing: ``--web`` is a site exported from ``MODEL``."""
    if args.web is None:
        return
    from share.serve import check_site
    from share.web_site import check_site_of

    if args.model is None:
        raise InputError("--web needs MODEL: the site's frames are compared with MODEL's")
    check_site_of(check_site(args.web), args.model)


def print_web_fps(args, model, views: dict, poses, K, size, rows: dict) -> None:
    """The browser's frames against this renderer's: PSNR at each of ``views`` (name → (4, 4)
    world_from_cam, with the model's sky) and the frame rate along ``poses`` (n, 4, 4), both with
    ``K`` at ``size``, beside ``rows`` (name → this renderer's path_fps row of the same walk)."""
    from billboards.sky import read_sky
    from core.metrics import psnr
    from render.benchmark import frame_time_stats
    from render.offscreen import render_view
    from share.browser import browser_fps, browser_memory, open_site, page_image

    sky = read_sky(args.model)
    with open_site(args.web, size, gl=args.browser_gl) as page:
        for name, pose in views.items():
            ours = render_view(model, K, pose, size, sky=sky)
            print(f"{'web':>9} {name:>12}: {psnr(page_image(page, size, pose, K), ours):5.1f} dB against this renderer "
                  f"(same camera, {size[0]}×{size[1]}, sky on)")
        stats = frame_time_stats(browser_fps(page, poses, K))
        memory = browser_memory()
        first = page.first_frame_ms
    ratios = ", ".join(f"{stats['fps'] / r['fps']:.2f}× {name}" for name, r in rows.items())
    print(f"{'web':>9} {'capture path':>12}: {stats['fps']:6.1f} fps median, {stats['fps_p5']:6.1f} p5 "
          f"(Chromium, {args.browser_gl} WebGL2, each frame drawn and read back; sky on), first frame "
          f"{first / 1000:.2f} s from page load, browser memory {memory / 1e6:.0f} MB; web/this renderer: {ratios}")
