"""``bbcity export KIND``: a dataset in another tool's format (nerfstudio), or a model shared: a
static web site, one binary glTF, 3D Tiles.

Each option's default comes from its config dataclass (NerfstudioExportConfig,
share.web_site.WebConfig, share.gltf.GltfConfig, share.tiles3d.Tiles3dConfig); bad values are
refused by them in one line before any work (exit 2).
"""

from __future__ import annotations

from pathlib import Path

from core.errors import InputError

from ..options import float_range, gpu_budget_mb, holdout
from .common import io_parser, refuse_out_inside


def add(sub) -> None:
    """The ``export`` command and its kinds on the subcommands ``sub``."""
    p = sub.add_parser(
        "export", help="a dataset → another tool's format (nerfstudio), to compare methods on the same capture",
        description="Write a dataset in another tool's format. The new directory is written whole or not at all.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    _add_nerfstudio(kinds)
    _add_web(kinds)
    _add_gltf(kinds)
    _add_3dtiles(kinds)


def _add_nerfstudio(kinds) -> None:
    from recon.importers.nerfstudio_export import NerfstudioExportConfig

    n = io_parser(kinds, "nerfstudio", "dataset", "dataset directory (rig.json, poses.json, images/)",
                  "new nerfstudio dataset directory",
                  help="transforms.json and images/ for nerfstudio (nerfacto, splatfacto …)",
                  description="""Write OUT/transforms.json and OUT/images/: every posed frame's image of every camera,
                                 undistorted, with its camera's pose (camera-to-world, OpenGL axes, the dataset's z-up
                                 world) and pinhole intrinsics. Frames without a pose are left out. --holdout N lists
                                 the frames recon/build --holdout N leave out as nerfstudio's test_filenames (camera
                                 0, the views bbcity eval compares).""")
    n.add_argument("--poses", type=Path, default=None,
                   help="a poses.json to use instead of the dataset's (e.g. WORK/poses.json of recon --poses sfm)")
    n.add_argument("--holdout", type=holdout, default=NerfstudioExportConfig.holdout,
                   help="hold every n-th frame out of training, as recon/build --holdout (default "
                        f"{NerfstudioExportConfig.holdout}: none; nerfstudio then splits by its own rule)")
    n.set_defaults(func=_run_nerfstudio, check_options=_nerfstudio_config)


def _nerfstudio_config(args):
    from recon.importers.nerfstudio_export import NerfstudioExportConfig

    return NerfstudioExportConfig(holdout=args.holdout)


def _run_nerfstudio(args) -> int:
    from recon.importers.nerfstudio_export import export_nerfstudio

    export_nerfstudio(args.dataset, args.out, _nerfstudio_config(args), poses=args.poses)
    return 0


def _add_web(kinds) -> None:
    from share.web_site import WebConfig

    w = io_parser(
        kinds, "web", "model", "billboard model directory, plain or tiled (tiles.json)", "new site folder",
        help="a model or tiled set → a static web site (WebGL2 viewer, the view in the link)",
        description="""Write SITE: index.html, the viewer's JavaScript, the desktop's shaders as GLSL ES 3.00
                       (shaders.json), the model's arrays and atlases as raw binary files, and site.json. Any static
                       HTTP server serves it (bbcity serve SITE for a local look); a link to a view ends in
                       #x,y,z,yaw,pitch[,fov] (world metres, degrees). A tiled set's tiles are streamed nearest first
                       within --gpu-budget. The site is written whole or not at all; an existing SITE is refused.""")
    w.add_argument("--dataset", type=Path, default=None, metavar="DIR",
                   help="dataset whose camera-0 poses are the start view and the capture path played on P "
                        "(default: the model's, when it is still there)")
    w.add_argument("--gpu-budget", type=gpu_budget_mb, default=WebConfig.gpu_budget_mb, metavar="MB",
                   help="GPU memory a tiled set's resident tiles may take in the browser "
                        f"(default {WebConfig.gpu_budget_mb:g})")
    w.add_argument("--fov", type=float_range(1.0, 170.0, lo_open=False), default=WebConfig.fov_deg,
                   metavar="DEG", help=f"vertical field of view (default {WebConfig.fov_deg:g})")
    w.set_defaults(func=_run_web, check_options=_web_config)


def _web_config(args):
    from share.web_site import WebConfig

    return WebConfig(gpu_budget_mb=args.gpu_budget, fov_deg=args.fov)


def _run_web(args) -> int:
    from share.web_site import export_web

    refuse_out_inside(args.out, args.model)
    report = export_web(args.model, args.out, _web_config(args), dataset=args.dataset)
    print(f"wrote {report['site']}: {report['tiles']} tile(s), {report['site_bytes'] / 1e6:.1f} MB "
          f"({report['size_ratio']:.2f}× the model), {report['path_poses']} capture-path poses, "
          f"{report['seconds']:.1f} s; look at it with: bbcity serve {report['site']}")
    return 0


def _texture_option(p) -> None:
    from share.gltf import TEXTURES, GltfConfig

    p.add_argument("--texture", choices=TEXTURES, default=GltfConfig.texture,
                   help=f"each quad's texture (default {GltfConfig.texture})")


def _print_wrote(out: Path, report: dict) -> int:
    """Print what an export wrote: its report's numbers and words; exit code 0."""
    print(f"wrote {out}: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                       for k, v in report.items() if not isinstance(v, (list, dict))))
    return 0


def _add_gltf(kinds) -> None:
    g = io_parser(
        kinds, "gltf", "model", "billboard model directory", "new .glb file",
        help="a model → one binary glTF (.glb): textured quads for Blender, three.js, model-viewer",
        description="""Write one .glb: the facade layer and ground as textured quads (the sampled direction looking
                       straight at each, or the mean texture), billboards as alpha-masked quads facing the capture
                       path, unlit, in glTF's y-up axes with the model's origin on the root node.""")
    _texture_option(g)
    g.set_defaults(func=_run_gltf, check_options=_gltf_config, writes_file=True)


def _gltf_config(args):
    from share.gltf import GltfConfig

    return GltfConfig(texture=args.texture)


def _run_gltf(args) -> int:
    from billboards.model_set import is_model_set
    from share.gltf import export_gltf

    refuse_out_inside(args.out, args.model)
    if is_model_set(args.model):
        raise InputError(f"{args.model} is a tiled model set: export gltf writes one model "
                         f"(export 3dtiles writes a set, a GLB per tile)")
    return _print_wrote(args.out, export_gltf(args.model, args.out, _gltf_config(args)))


def _add_3dtiles(kinds) -> None:
    from share.tiles3d import REFINES, Tiles3dConfig

    t = io_parser(
        kinds, "3dtiles", "model", "tiled model set (tiles.json) or plain model directory", "new tileset folder",
        help="a tiled set (or a model) → 3D Tiles 1.1: tileset.json and one GLB per tile (Cesium)",
        description="""Write DIR/tileset.json and DIR/tiles/NAME.glb: one tile per model tile, box bounding volumes
                       from the tiles' quads, geometric errors from their texel size. The folder is written whole or
                       not at all; an existing DIR is refused.""")
    t.add_argument("--refine", choices=REFINES, default=Tiles3dConfig.refine,
                   help=f"the root's refinement (default {Tiles3dConfig.refine})")
    t.add_argument("--lonlat-height", type=float_range(allow_inf=False), nargs=3, default=None,
                   metavar=("LON", "LAT", "H"),
                   help="place the world's (0, 0, 0) at this WGS84 longitude, latitude (degrees) and height (m) "
                        "on the globe (default: local coordinates)")
    _texture_option(t)
    t.set_defaults(func=_run_3dtiles, check_options=_tiles3d_config)


def _tiles3d_config(args):
    from share.gltf import GltfConfig
    from share.tiles3d import Tiles3dConfig

    return Tiles3dConfig(gltf=GltfConfig(texture=args.texture), refine=args.refine,
                         lonlat_height=None if args.lonlat_height is None else tuple(args.lonlat_height))


def _run_3dtiles(args) -> int:
    from share.tiles3d import export_3dtiles

    refuse_out_inside(args.out, args.model)
    return _print_wrote(args.out, export_3dtiles(args.model, args.out, _tiles3d_config(args)))
