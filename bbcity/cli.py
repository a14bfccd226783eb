"""The ``bbcity`` command line: its grammar, one command per module of :mod:`bbcity.commands`,
run by :mod:`bbcity.lifecycle` (logging, signals, the output lock, exit codes)."""

from __future__ import annotations

import argparse
from pathlib import Path

from . import __version__, lifecycle
from .commands import bench, build, check, demo, export, fps, import_, mesh, recon, render, sampling_eval, \
    serve, stereo_sweep, synth, texture_sweep, view
from .commands import eval as eval_
from .options import CommandParser

#: The commands in the order ``bbcity --help`` lists them.
COMMANDS = (synth, import_, export, recon, build, texture_sweep, sampling_eval, stereo_sweep, check, bench, fps,
            view, render, mesh, eval_, serve, demo)


def build_parser() -> argparse.ArgumentParser:
    """The parser of the whole command line: the global options and every command's."""
    parser = argparse.ArgumentParser(
        prog="bbcity", description="Street captures from a camera rig to a compact billboard city model.")
    parser.add_argument("--version", action="version", version=f"bbcity {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    parser.add_argument("--profile", type=Path, metavar="DIR",
                        help="profile the command and its workers (cProfile) into DIR: one .prof per process and "
                             "profile.md, the functions with the most time of their own")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=CommandParser)
    for command in COMMANDS:
        command.add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The ``bbcity`` command on ``argv`` (default: the process's arguments); its exit code."""
    return lifecycle.run(build_parser, argv)


def entry_point() -> None:
    """The ``bbcity`` console script: :func:`main`, then exit with its code."""
    lifecycle.exit_process(main())


if __name__ == "__main__":
    entry_point()
