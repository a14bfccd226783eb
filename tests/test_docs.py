"""The documentation works: every code block of README.md and docs/**/*.md runs or parses,
every relative link and image points at a file (and heading) that exists, and docs/cli.md
is what the command line's parsers say.

- ```python blocks are executed in a temporary directory holding ``demo/street`` (a tiny
  synthetic street) and ``demo/model`` (its model), the names ``make demo`` gives them;
- ```sh / ```bash / ```shell blocks: every ``bbcity ...`` command (also after a wrapper
  such as ``xvfb-run -a``) is parsed by the real parser, placeholders such as KITTI_DIR
  being plain words; every ``make X`` names a target of the Makefile; nothing is run;
- ```text blocks are output or listings, not run; a block without a language is refused.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

from bbcity.cli import build_parser
from bbcity.cli import main as cli_main
from bbcity.cli_reference import REFERENCE_PATH, REGENERATE, cli_markdown, slug
from data_synth import write_dataset

from .conftest import tiny_config, write_ground_truth_cloud

ROOT = Path(__file__).resolve().parents[1]

#: Every Markdown file of the documentation.
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

#: Languages a fenced block may have, and what the tests do with it.
PYTHON = {"python"}
SHELL = {"sh", "bash", "shell"}
TEXT = {"text"}

#: The README is for users: what it is, how to run it, where to read on.
README_MAX_LINES = 200

FENCE = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*(?P<lang>[^\s`]*)")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\((?P<target><[^>]*>|[^)\s]+)(?:\s+\"[^\"]*\")?\)")
INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+\1")
HEADING = re.compile(r"^(#{1,6})\s+(?P<title>.+?)\s*#*\s*$")


@dataclass(frozen=True)
class Block:
    """A fenced code block: its file, the line of its opening fence, language and text."""

    path: Path
    line: int
    lang: str
    text: str

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def split_markdown(path: Path) -> tuple[list[Block], list[tuple[int, str]]]:
    """The fenced blocks of ``path`` and its other lines (number, text)."""
    blocks, prose = [], []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m is None:
            prose.append((i + 1, lines[i]))
            i += 1
            continue
        fence, indent, start = m["fence"], len(m["indent"]), i
        body = []
        i += 1
        while i < len(lines) and not (lines[i].strip().startswith(fence[0] * len(fence))
                                      and lines[i].strip().strip(fence[0]) == ""):
            body.append(lines[i][indent:] if lines[i][:indent].strip() == "" else lines[i])
            i += 1
        blocks.append(Block(path, start + 1, m["lang"].lower(), "\n".join(body) + "\n"))
        i += 1
    return blocks, prose


ALL_BLOCKS = [b for path in DOCUMENTS for b in split_markdown(path)[0]]
PYTHON_BLOCKS = [b for b in ALL_BLOCKS if b.lang in PYTHON]
SHELL_BLOCKS = [b for b in ALL_BLOCKS if b.lang in SHELL]


def commands(block: Block) -> list[tuple[int, list[str]]]:
    """The simple commands of a shell block: (line, words), continuation lines joined,
    comments dropped, split at ``&&``, ``||``, ``;`` and ``|``, leading ``VAR=value`` dropped."""
    found = []
    logical, first = "", None
    for number, line in enumerate(block.text.splitlines(), block.line + 1):
        first = number if first is None else first
        if line.rstrip().endswith("\\"):
            logical += line.rstrip()[:-1] + " "
            continue
        logical += line
        lexer = shlex.shlex(logical, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        lexer.commenters = "#"
        words: list[str] = []
        for token in [*lexer, ";"]:
            if token in {"&&", "||", ";", "|", "&"}:
                while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
                    words.pop(0)
                if words:
                    found.append((first, words))
                words = []
            else:
                words.append(token)
        logical, first = "", None
    return found


def make_targets() -> set[str]:
    """The targets the Makefile defines."""
    targets = set()
    for line in (ROOT / "Makefile").read_text().splitlines():
        m = re.match(r"^([^\s:=#][^:=]*?)\s*::?(?!=)", line)  # "a b: deps", not "A := value"
        if m:
            targets.update(m[1].split())
    return targets


def heading_anchors(path: Path) -> set[str]:
    """The anchors of a Markdown file's headings (GitHub's: duplicates numbered)."""
    anchors, seen = set(), {}
    for _, line in split_markdown(path)[1]:
        m = HEADING.match(line)
        if m is None:
            continue
        base = slug(m["title"])
        n = seen.get(base, 0)
        seen[base] = n + 1
        anchors.add(base if n == 0 else f"{base}-{n}")
    return anchors


def links(path: Path) -> list[tuple[int, str]]:
    """The link and image targets of a Markdown file's prose (not code blocks, not inline code)."""
    found = []
    for number, line in split_markdown(path)[1]:
        for m in LINK.finditer(INLINE_CODE.sub("", line)):
            found.append((number, m["target"].strip("<>")))
    return found


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    """A directory holding ``demo/street`` (a tiny street) and ``demo/model`` (its model, built
    through the command line from the street's ground-truth cloud), as ``make demo`` names them."""
    root = tmp_path_factory.mktemp("docs")
    street = write_dataset(tiny_config(), root / "demo" / "street", progress=False)
    cloud = write_ground_truth_cloud(street, root / "demo" / "cloud.ply")
    code = cli_main(["-q", "build", "--cloud", str(cloud), "--images", str(street), "--out", str(root / "demo" / "model"),
                     "--fit", "off", "--directions", "8", "--spacing", "10", "--max-rank", "4", "--workers", "1"])
    assert code == 0
    return root


def test_every_block_has_a_known_language():
    unknown = [f"{b.where}: ```{b.lang}" for b in ALL_BLOCKS if b.lang not in PYTHON | SHELL | TEXT]
    assert not unknown, ("fence every code block as python (run), sh (parsed) or text (shown): "
                         + ", ".join(unknown))


def test_the_documents_have_code_to_check():
    assert PYTHON_BLOCKS and SHELL_BLOCKS
    readme = [b.lang for b in ALL_BLOCKS if b.path.name == "README.md" and b.path.parent == ROOT]
    assert "python" in readme and "sh" in readme


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=lambda b: b.where)
def test_python_block_runs(block, demo, monkeypatch):
    monkeypatch.chdir(demo)
    code = compile(block.text, block.where, "exec")
    exec(code, {"__name__": "__docs__"})


@pytest.mark.parametrize("block", SHELL_BLOCKS, ids=lambda b: b.where)
def test_shell_block_parses(block):
    parser = build_parser()
    targets = make_targets()
    problems = []
    found = commands(block)
    for line, words in found:
        names = [i for i, w in enumerate(words) if w == "bbcity" or w.endswith("/bbcity")]
        if names:
            argv = words[names[0] + 1:]
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                try:
                    parser.parse_args(argv)
                except SystemExit as e:
                    if e.code:
                        said = err.getvalue().strip().splitlines() or ["(nothing said)"]
                        problems.append(f"line {line}: bbcity {shlex.join(argv)}\n    {said[-1]}")
        elif words[0] == "make":
            missing = [w for w in words[1:] if not w.startswith("-") and "=" not in w and w not in targets]
            if missing:
                problems.append(f"line {line}: make {' '.join(missing)}: no such target in the Makefile")
    assert found, f"{block.where}: a shell block without a command"
    assert not problems, f"{block.where}:\n" + "\n".join(problems)


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_point_at_files(path):
    broken = []
    for line, target in links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        resolved = path if not file else (path.parent / file)
        if not resolved.exists():
            broken.append(f"line {line}: {target}: no such file")
        elif anchor and resolved.suffix == ".md" and anchor not in heading_anchors(resolved):
            broken.append(f"line {line}: {target}: no heading #{anchor} in {resolved.relative_to(ROOT)}")
    assert not broken, f"{path.relative_to(ROOT)}:\n" + "\n".join(broken)


def test_readme_is_short():
    lines = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines; move details into docs/"


def test_cli_reference_is_current():
    expected = cli_markdown(build_parser())
    actual = (ROOT / REFERENCE_PATH).read_text(encoding="utf-8")
    if actual != expected:
        old, new = actual.splitlines(), expected.splitlines()
        first = next((i for i, (a, b) in enumerate(zip(old, new)) if a != b), min(len(old), len(new)))
        pytest.fail(f"{REFERENCE_PATH} is not what the parsers say (first difference at line {first + 1}); "
                    f"regenerate it: {REGENERATE}")
