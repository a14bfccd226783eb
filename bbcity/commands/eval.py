"""``bbcity eval``: novel-view quality of a model against the synthetic ground truth or held-out
real images, with the fused cloud's baselines; a report directory (eval.json, eval.md, plots)."""

from __future__ import annotations

import re
from pathlib import Path

from core.errors import InputError

from ..executor import process_scope
from ..options import EVAL_BYTES_PER_PIXEL, MAX_FRAMES, MAX_PANEL_WIDTH, int_range
from .common import OwnOutput, check_own_output, load_drawable, logger, size_parent

#: What an eval report directory holds (it is replaced whole by the next report).
REPORT_FILES = OwnOutput(
    re.compile(r"eval\.json|eval\.md|workprecision\.png|view_\d+_(on_path|off_path|training)\.png"),
    "an eval report's", "the report replaces its directory whole")


def add(sub) -> None:
    """The ``eval`` command on the subcommands ``sub``."""
    from render.eval_config import EvalConfig

    p = sub.add_parser("eval", help="novel-view quality of a model against ground truth or held-out real images",
                       description="""Render MODEL at capture viewpoints of DATASET (its held-out frames when built
                                      with --holdout). A real capture (no gt/): compare with those frames' images,
                                      PSNR and SSIM over the pixels each method covers and the whole image, coverage
                                      of the pixels below the horizon. A synthetic dataset: also at the same
                                      viewpoints moved 2 m sideways and 1 m up; compare with the ground-truth
                                      renderer: PSNR and SSIM over the image, over geometry pixels and over seen
                                      pixels (a surface a capture camera used for the textures saw). With --cloud, the
                                      fused cloud is the baseline twice: meshed by Open3D's screened Poisson
                                      reconstruction (ray cast, vertex colours) and projected point by point. Writes
                                      eval.json, eval.md, workprecision.png (bytes against seen-pixel PSNR: Poisson
                                      depths, the model(s), the points) and one side-by-side PNG per view.""",
                       parents=[size_parent(None, EVAL_BYTES_PER_PIXEL, "default: the camera's")])
    p.add_argument("model", type=Path, help="billboard model directory (or a tiled model's: every tile a view sees)")
    p.add_argument("dataset", type=Path,
                   help="the dataset: synthetic with gt/, or a real capture (scored against its held-out images)")
    p.add_argument("--out", type=Path, required=True,
                   help="report directory: new, or an earlier eval report (replaced whole)")
    p.add_argument("--cloud", type=Path, default=None, help="fused cloud for the Poisson-mesh and point baselines")
    p.add_argument("--billboards-only", type=Path, default=None, metavar="MODEL",
                   help="a model of the same cloud built with --layer none, scored as 'billboards only'")
    p.add_argument("--models", type=Path, nargs="+", default=[], metavar="MODEL",
                   help="more model directories (other build settings): more points of the work-precision diagram")
    p.add_argument("--views", type=int_range(1, MAX_FRAMES), default=EvalConfig.views,
                   help="viewpoints (default: 8, each also off path; a real capture: every held-out frame)")
    p.add_argument("--training-views", type=int_range(0, MAX_FRAMES), default=EvalConfig.training_views,
                   help="also this many viewpoints of frames the textures came from, scored as 'training' (the "
                        f"ceiling; default EvalConfig's, {EvalConfig.training_views}; only when the model held "
                        "frames out)")
    p.add_argument("--poisson-depth", type=int_range(1, 16), default=EvalConfig.poisson_depth,
                   help=f"octree depth of the Poisson-mesh baseline ({EvalConfig.poisson_depth})")
    depths = EvalConfig.workprecision_depths
    p.add_argument("--workprecision-depths", type=int_range(1, 16), nargs="*", default=list(depths), metavar="D",
                   help=f"Poisson depths of the work-precision diagram (default {' '.join(map(str, depths))}; "
                        "none: only --poisson-depth)")
    p.add_argument("--panel-width", type=int_range(0, MAX_PANEL_WIDTH), default=EvalConfig.panel_width,
                   help=f"width of each panel of the side-by-side images (default {EvalConfig.panel_width}; "
                        "0: no images)")
    p.add_argument("--no-sky", action="store_true",
                   help="draw the model(s) on black like the baselines, not over their sky")
    p.set_defaults(func=run, check_options=check)


def check(args) -> None:
    """The eval options, and an --out that is new or an earlier eval report (it is replaced whole)."""
    config_from_args(args)
    check_own_output(args.out, REPORT_FILES)


def config_from_args(args):
    """The EvalConfig the ``eval`` options describe."""
    from render.eval_config import EvalConfig

    return EvalConfig(views=args.views, size=None if args.size is None else tuple(args.size),
                      poisson_depth=args.poisson_depth, workprecision_depths=tuple(args.workprecision_depths),
                      panel_width=args.panel_width, model_sky=not args.no_sky, training_views=args.training_views)


def _eval_dataset(model, dataset_dir: Path):
    """The dataset to evaluate ``model`` on: with the poses the model was built with (its
    info "poses": a recon's WORK/poses.json, e.g. from SfM) instead of the dataset's own."""
    from capture.dataset import load_dataset

    info = model.info if isinstance(model.info, dict) else {}
    poses = info.get("poses")
    if not isinstance(poses, str):
        ds = load_dataset(dataset_dir)
        if not ds.posed.any():
            raise InputError(f"{dataset_dir}: no frame has a pose, and the model records no poses file (build it "
                             "from the WORK of `bbcity recon --poses sfm`)")
        return dataset_dir
    logger.info("poses: %s (the model's)", poses)
    return load_dataset(dataset_dir, poses=poses)


def run(args) -> int:
    """Evaluate the model(s) into the report directory (written whole); log each one's scores."""
    from billboards.sky import read_sky
    from core.fileio import atomic_dir
    from render.eval_report import write_report
    from render.evaluate import evaluate_views

    config = config_from_args(args)
    labels = [m.name if [x.name for x in args.models].count(m.name) == 1 else str(m) for m in args.models]
    extra = {label: (load_drawable(m, False), read_sky(m)) for label, m in zip(labels, args.models)}
    only = None if args.billboards_only is None else (load_drawable(args.billboards_only, False),
                                                      read_sky(args.billboards_only))
    model = load_drawable(args.model, False)
    # the Poisson baseline is meshed in a worker process while this one prepares the views
    with atomic_dir(args.out) as report_dir, process_scope(1) as pool:
        report = evaluate_views(model, _eval_dataset(model, args.dataset), args.cloud, sky=read_sky(args.model),
                                extra_models=extra, billboards_only=only, config=config, out_dir=report_dir,
                                executor=pool)
        write_report(report, report_dir)
    _log_summary(report)
    logger.info("wrote %s", args.out / "eval.md")
    return 0


def _log_summary(report: dict) -> None:
    """One line per method of the report's summary: its PSNR, SSIM (and a real capture's coverage)."""
    for name, m in report["summary"].items():
        if report.get("real"):
            logger.info("%s: PSNR %s dB over covered pixels (%s over the image), SSIM %s, %s of the pixels below "
                        "the horizon covered", name, _num(m["psnr_covered"]), _num(m["psnr"]),
                        _num(m["ssim_covered"], ".3f"), _num(m["coverage_seen"], ".1%"))
        else:
            logger.info("%s: PSNR %s dB over seen pixels (%s over the image), SSIM %s", name, _num(m["psnr_seen"]),
                        _num(m["psnr"]), _num(m["ssim_seen"], ".3f"))


def _num(value, spec: str = ".2f") -> str:
    """``value`` formatted by ``spec``; "n/a" for a measurement that is missing."""
    return "n/a" if value is None else format(value, spec)
