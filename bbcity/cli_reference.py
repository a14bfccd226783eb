"""The command reference, ``docs/cli.md``, written from the command line's own parsers.

``python -m bbcity.cli_reference > docs/cli.md`` regenerates it; ``tests/test_docs.py``
checks that the file matches, so the reference never drifts from ``bbcity --help``.
Each command (nested ones too, such as ``import kitti`` and ``export web``) gets its
description, a synopsis, its arguments and its options (name, value, default, help), and
its epilog (the viewer's keys) as text.

argparse has no public API for walking a parser: this module reads the attributes its own
help formatter reads (``_actions``, ``_choices_actions``), as documentation tools do.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator

from .cli import build_parser

#: The file this module's output is kept in, relative to the repository root.
REFERENCE_PATH = "docs/cli.md"

#: How to bring the file up to date (printed by the test that checks it).
REGENERATE = f"python -m bbcity.cli_reference > {REFERENCE_PATH}"


def commands(parser: argparse.ArgumentParser, prog: str = "bbcity",
             line: str = "") -> Iterator[tuple[str, argparse.ArgumentParser, str]]:
    """``parser`` and every command under it, depth first in the order ``--help`` lists them:
    ``(full name, its parser, its one-line help)``; ``line`` is ``parser``'s own one-line help."""
    yield prog, parser, line
    for action in parser._actions:
        if isinstance(action.choices, dict):  # a subparsers action: name → parser
            helps = subcommand_help(action)
            for name, sub in action.choices.items():
                yield from commands(sub, f"{prog} {name}", helps[name])


def subcommand_help(action: argparse.Action) -> dict[str, str]:
    """A subparsers action's one-line help of each of its commands, on one line ("" for none)."""
    helps = {choice.dest: choice.help or "" for choice in getattr(action, "_choices_actions", [])}
    return {name: " ".join(helps.get(name, "").split()) for name in action.choices}


def slug(heading: str) -> str:
    """The anchor a Markdown renderer (GitHub's) gives a heading: lower case, punctuation
    other than ``-`` and ``_`` dropped, spaces as ``-``."""
    kept = "".join(ch for ch in heading.lower() if ch.isalnum() or ch in " -_")
    return kept.replace(" ", "-")


def metavar(action: argparse.Action) -> str:
    """The value an option or positional takes, as ``--help`` prints it (``W H``, ``{gpu,cpu}``,
    ``PITCHES [PITCHES ...]``); "" for a flag."""
    if action.nargs == 0:
        return ""
    if action.metavar is not None:
        names = action.metavar
    elif action.choices is not None and not isinstance(action.choices, dict):
        names = "{" + ",".join(str(c) for c in action.choices) + "}"
    elif action.option_strings:
        names = action.dest.upper()
    else:
        names = action.dest
    if isinstance(names, tuple):
        return " ".join(names)
    if action.nargs is None:
        return names
    if action.nargs == argparse.OPTIONAL:
        return f"[{names}]"
    if action.nargs == argparse.ZERO_OR_MORE:
        return f"[{names} ...]"
    if action.nargs == argparse.ONE_OR_MORE:
        return f"{names} [{names} ...]"
    if isinstance(action.nargs, int):
        return " ".join([names] * action.nargs)
    return names


def help_text(action: argparse.Action, prog: str) -> str:
    """An action's help with argparse's ``%(...)s`` fields filled in, on one line."""
    text = action.help or ""
    if "%" in text:
        params = {k: v for k, v in dict(vars(action), prog=prog).items() if v is not argparse.SUPPRESS}
        if params.get("choices") is not None:
            params["choices"] = ", ".join(str(c) for c in params["choices"])
        text = text % params
    return " ".join(text.split())


def default_text(action: argparse.Action) -> str:
    """An option's default as a user types it; "" where there is none to show (None, a flag)."""
    value = action.default
    if action.nargs == 0 or value is None or value is argparse.SUPPRESS:
        return ""
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value) if value else ""
    return str(value)


def cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell."""
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def code(text: str) -> str:
    """``text`` as inline code inside a table cell ("" stays empty)."""
    if not text:
        return ""
    escaped = text.replace("|", "\\|")
    return f"`{escaped}`"


def synopsis(name: str, parser: argparse.ArgumentParser) -> str:
    """``bbcity build [work] --out OUT [options]``: the positionals and required options."""
    words, command = [name], []
    for action in parser._actions:
        if action.dest == "help" or action.help is argparse.SUPPRESS:
            continue
        if isinstance(action.choices, dict):
            command.append((action.metavar or "COMMAND") + " ...")
        elif not action.option_strings:
            words.append(metavar(action))
        elif action.required:
            words.append(f"{action.option_strings[-1]} {metavar(action)}".strip())
    if any(a.option_strings and not a.required and a.dest != "help" for a in parser._actions):
        words.append("[options]")
    return " ".join(words + command)


def command_markdown(name: str, parser: argparse.ArgumentParser, line: str, list_commands: bool = True) -> list[str]:
    """One command's section (``list_commands``: with a table of its subcommands)."""
    out = [f"## {name}", ""]
    description = " ".join((parser.description or line).split())
    if description:
        out += [description, ""]
    out += ["```text", synopsis(name, parser), "```", ""]
    positionals = [a for a in parser._actions if not a.option_strings and a.help is not argparse.SUPPRESS]
    subcommands = [a for a in positionals if isinstance(a.choices, dict)]
    arguments = [a for a in positionals if not isinstance(a.choices, dict)]
    if subcommands and list_commands:
        out += ["| command | what it does |", "|---|---|"]
        for action in subcommands:
            for sub, help_line in subcommand_help(action).items():
                out.append(f"| [`{name} {sub}`](#{slug(f'{name} {sub}')}) | {cell(help_line)} |")
        out.append("")
    if arguments:
        out += ["| argument | help |", "|---|---|"]
        for action in arguments:
            out.append(f"| {code(metavar(action))} | {cell(help_text(action, parser.prog))} |")
        out.append("")
    options = [a for a in parser._actions if a.option_strings and a.dest != "help" and a.help is not argparse.SUPPRESS]
    if options:
        out += ["| option | value | default | help |", "|---|---|---|---|"]
        for action in options:
            names = ", ".join(f"`{o}`" for o in action.option_strings)
            out.append(f"| {names} | {code(metavar(action))} | {code(default_text(action))} "
                       f"| {cell(help_text(action, parser.prog))} |")
        out.append("")
    if parser.epilog:
        out += ["```text", parser.epilog.strip("\n"), "```", ""]
    return out


def cli_markdown(parser: argparse.ArgumentParser) -> str:
    """The whole reference for ``parser`` (``bbcity.cli.build_parser()``) as Markdown."""
    found = list(commands(parser, parser.prog))
    out = ["# Command reference", "",
           f"Written from the command line's parsers by `{REGENERATE}`; edit the help texts in",
           "`bbcity/commands/`, not this file. Every command also prints its own `--help`.", "",
           "| command | what it does |", "|---|---|"]
    for name, _, line in found[1:]:
        out.append(f"| [`{name}`](#{slug(name)}) | {cell(line)} |")
    out.append("")
    for i, (name, sub, line) in enumerate(found):
        out += command_markdown(name, sub, line, list_commands=i > 0)
    return "\n".join(out).rstrip("\n") + "\n"


def main() -> None:
    """Write the reference of ``bbcity``'s command line to standard output, in UTF-8."""
    sys.stdout.buffer.write(cli_markdown(build_parser()).encode("utf-8"))


if __name__ == "__main__":
    main()
