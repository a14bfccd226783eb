"""``bbcity mesh``: a fused cloud → its screened Poisson mesh, the baseline ``bbcity eval`` scores
the model against, kept in the cloud's cache (:mod:`render.poisson_cache`) so that eval finds it
made; ``--out`` also writes it as a PLY mesh for other tools."""

from __future__ import annotations

from pathlib import Path

from core.errors import InputError

from ..options import int_range
from .common import logger


def add(sub) -> None:
    """The ``mesh`` command on the subcommands ``sub``."""
    from render.eval_config import EvalConfig

    p = sub.add_parser("mesh", help="cloud → screened Poisson mesh (eval's baseline), kept beside the cloud for eval",
                       description="""Mesh CLOUD by Open3D's screened Poisson reconstruction (vertex colours, the
                                      lowest-density vertices trimmed), as bbcity eval meshes its baseline, and keep
                                      the mesh in CLOUD's directory, under cache/poisson/, keyed by the cloud's
                                      bytes: an eval of the same cloud and depth takes it from there instead of
                                      meshing. A mesh already kept is not made again. recon's clouds carry normals;
                                      a cloud without them is meshed with unoriented normals, which eval, turning
                                      them toward its cameras, does not reuse.""")
    p.add_argument("cloud", type=Path, help="fused cloud (recon's WORK/cloud.ply, or a PLY/PCD with colours)")
    p.add_argument("--depth", type=int_range(1, 16), default=EvalConfig.poisson_depth,
                   help=f"Poisson octree depth (default {EvalConfig.poisson_depth}, eval's --poisson-depth)")
    p.add_argument("--out", type=Path, default=None, help="also write the mesh here: a binary PLY (.ply)")
    p.set_defaults(func=run, check_options=check, writes_file=True)


def check(args) -> None:
    """With --out, a .ply to write."""
    if args.out is not None and args.out.suffix.lower() != ".ply":
        raise InputError(f"--out {args.out}: the mesh is written as PLY; name it *.ply")


def run(args) -> int:
    """Mesh the cloud (or take the kept mesh), keep it, and write --out when given."""
    from render.eval_config import EvalConfig
    from render.baselines import write_poisson_ply
    from render.evaluate import mesh_cloud_file
    from render.poisson_cache import PoissonCache

    if not args.cloud.is_file():
        raise InputError(f"{args.cloud}: no such cloud file")
    cache = PoissonCache.of(args.cloud)
    trim = EvalConfig.trim_quantile
    mesh = mesh_cloud_file(cache, None, args.depth, trim)
    if args.out is not None:
        write_poisson_ply(args.out, mesh)
        logger.info("wrote %s", args.out)
    kept = cache.path(args.depth, trim)
    if not kept.is_file():  # (the cache's warning said why)
        if args.out is None:
            raise InputError(f"{kept}: the mesh could not be kept there, and no --out was given")
        return 0
    logger.info("Poisson mesh of %s, depth %d: %d vertices, %d triangles%s → %s", args.cloud, args.depth,
                len(mesh["vertices"]), len(mesh["triangles"]), " (kept from before)" if mesh.get("cached") else "",
                kept)
    return 0
