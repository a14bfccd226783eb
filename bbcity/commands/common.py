"""What several commands share: their common options, as argparse parent parsers
(``parents=[...]``: one definition each, so the commands cannot drift apart in type, check or
help), the models they draw, and the checks of their input and output directories.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
from pathlib import Path
from typing import NamedTuple

from core.errors import InputError
from recon.work import Work

from ..executor import executor_scope
from ..executor_config import DEFAULT_RETRIES, EXECUTORS
from ..options import UsageError, dimension, gpu_budget_mb, nonnegative_int, scheduler_address, size_action, \
    worker_count

#: The log of the commands (one name for all: the lines read ``bbcity: ...``).
logger = logging.getLogger("bbcity")

#: The frame size render, view and fps draw at unless ``--size`` says otherwise (width, height).
FRAME_SIZE = (1280, 720)


def workers_parent() -> argparse.ArgumentParser:
    """``--workers``, ``--executor``, ``--scheduler`` and ``--retries`` of the commands that run
    their tasks in parallel (synth, recon, build): see :func:`executor_options`."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--workers", type=worker_count, default=None,
                   help="parallel processes of the local pool or of the Dask cluster started here (default: one "
                        "per core)")
    p.add_argument("--executor", choices=EXECUTORS, default=None,
                   help="where tasks run: local (a process pool, the default) or dask (a Dask cluster: the one at "
                        "--scheduler, else one started on this machine)")
    p.add_argument("--scheduler", type=scheduler_address, default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, tcp://host:8786 (implies --executor dask; the dataset, work and "
                        "model directories must be at the same path on every worker's machine)")
    p.add_argument("--retries", type=nonnegative_int, default=None,
                   help=f"dask: times a failed task runs again (default {DEFAULT_RETRIES}); a task failing on bad "
                        f"input fails at once")
    return p


def executor_options(args) -> dict:
    """``executor_scope``'s keywords from ``--executor``, ``--scheduler`` and ``--retries``
    (UsageError for a contradiction)."""
    kind = args.executor or ("dask" if args.scheduler is not None else "local")
    if kind == "local" and args.scheduler is not None:
        raise UsageError("--scheduler needs --executor dask")
    if kind == "local" and args.retries is not None:
        raise UsageError("--retries applies to --executor dask")
    if args.scheduler is not None and args.workers is not None:
        raise UsageError("--workers sizes a cluster started here; the cluster at --scheduler has the workers "
                         "started on its machines")
    return dict(kind=kind, scheduler=args.scheduler,
                retries=DEFAULT_RETRIES if args.retries is None else args.retries)


def command_executor(args):
    """The executor scope of a command with :func:`workers_parent`'s options: the local pool
    or the Dask cluster they name, for the length of a ``with`` block."""
    return executor_scope(args.workers, **executor_options(args))


def absolute_paths(args) -> None:
    """Make the path options absolute: Dask tasks carry paths, and a worker elsewhere resolves a
    relative one from its own directory."""
    for name, value in vars(args).items():
        if isinstance(value, Path):
            setattr(args, name, Path(os.path.abspath(value)))


def size_parent(default: tuple[int, int] | None, bytes_per_pixel: int, help: str) -> argparse.ArgumentParser:
    """``--size W H`` of the commands that render (render, view, eval, fps): each edge within
    the OpenGL limit, W·H·``bytes_per_pixel`` within the available memory."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--size", type=dimension, nargs=2, default=default, metavar=("W", "H"),
                   action=size_action(bytes_per_pixel), help=help)
    return p


def gpu_budget_parent() -> argparse.ArgumentParser:
    """``--gpu-budget MB`` of the commands that draw a model (render, view, fps)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--gpu-budget", type=gpu_budget_mb, default=None, metavar="MB",
                   help="GPU memory the model's tiles may hold, MB: a tiled model's tiles are loaded in the "
                        "background and uploaded and released as the eye moves (default: no limit; a plain "
                        "model is then paged as one tile)")
    return p


def paging(args):
    """The PagingConfig of ``--gpu-budget`` (None without it)."""
    from render.paging import MB, PagingConfig

    return None if args.gpu_budget is None else PagingConfig(gpu_budget=int(args.gpu_budget * MB))


def draw_modes_parent() -> argparse.ArgumentParser:
    """``--decode`` and ``--cull`` of the commands that draw a billboard model (render, view)."""
    from render.culling import CULL_MODES

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--decode", choices=("gpu", "cpu"), default="gpu",
                   help="texture decode: in the shader (gpu) or on the CPU (default gpu)")
    p.add_argument("--cull", choices=CULL_MODES, default="frustum",
                   help="culling (default frustum)")
    return p


def load_drawable(path: Path, paged: bool):
    """What render, view, fps and eval draw from the model directory ``path``: a tiled model as
    its ModelSet, a plain one as its BillboardModel (as a ModelSet too when ``paged``)."""
    from billboards.model_reader import load
    from billboards.model_set import is_model_set, load_model_set

    if is_model_set(path) or paged:
        return load_model_set(path)
    return load(path)


def work_dataset(args) -> Path:
    """The dataset of a command on a recon WORK directory (build, texture-sweep, sampling-eval):
    its ``--images``, else the one WORK was built from (its recon_report.json says)."""
    return args.images or Work.open(args.work).dataset()


class OwnOutput(NamedTuple):
    """What a command that writes into a directory of its own may find there from an earlier
    run of itself (hidden names, its own and its killed runs' temporaries, are always its own)."""

    names: re.Pattern  #: the names its runs write
    what: str  #: whose names they are, for the message ("a render's frames")
    why: str  #: what the command does with them ("its frames replace those there")


def check_own_output(out: Path, own: OwnOutput) -> None:
    """UsageError unless ``out`` is new or holds only names ``own`` matches (and hidden ones):
    a command's output mixed into a model, a dataset or anything else would damage both."""
    try:
        if out.is_symlink() or (out.exists() and not out.is_dir()):
            raise UsageError(f"--out {out} is not a directory (a link or a file); give a new directory")
        names = [p.name for p in out.iterdir()] if out.is_dir() else []
    except OSError as e:  # a name too long, a directory not readable
        raise UsageError(f"--out {out}: {e.strerror}") from None
    foreign = sorted(name for name in names if not name.startswith(".") and not own.names.fullmatch(name))
    if foreign:
        raise UsageError(f"--out {out} holds {foreign[0]!r}, not {own.what}; {own.why}: give a new directory")


def refuse_out_over(out: Path, inputs: list[Path]) -> None:
    """UsageError when the output directory ``out`` is one of ``inputs`` or holds one: a
    command writes its output whole in place of ``out``, and would delete what it reads."""
    where = out.resolve()
    for path in inputs:
        source = Path(path).resolve()
        if where == source or where in source.parents:
            raise UsageError(f"--out {out} holds {path}, which this command reads; its output would replace "
                             "it: choose another directory")


def refuse_out_inside(out: Path, model: Path) -> None:
    """InputError when an export's ``out`` lies inside the model directory it reads: it would
    change that directory."""
    if out.resolve().is_relative_to(model.resolve()):
        raise InputError(f"--out {out} lies inside the model directory {model}; write the export elsewhere")


def io_parser(sub, name: str, source: str, source_help: str, out_help: str, **kwargs) -> argparse.ArgumentParser:
    """The parser of a command (or kind) ``name`` that reads the path ``source`` (its first
    argument) and writes ``--out``; ``kwargs`` are ``add_parser``'s (help, description, parents)."""
    p = sub.add_parser(name, **kwargs)
    p.add_argument(source, type=Path, help=source_help)
    p.add_argument("--out", type=Path, required=True, help=out_help)
    return p


def work_report_parser(sub, name: str, images_help: str, **kwargs) -> argparse.ArgumentParser:
    """The parser of a report command on a recon WORK (texture-sweep, sampling-eval): WORK, the
    report directory ``--out`` and ``--images``, the dataset (``images_help`` says which)."""
    p = io_parser(sub, name, "work", "recon work directory (cloud.ply, recon_report.json)", "report directory",
                  **kwargs)
    p.add_argument("--images", type=Path, default=None, help=images_help)
    return p
