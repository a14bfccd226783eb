"""The package layering, read from the source with ``ast`` (imports inside functions included).

core → capture → {data_synth, recon} → billboards → render → share → bbcity: a package
imports only packages below it; data_synth and recon are siblings that produce datasets.
Ground truth is the synthetic generator's: a stage reads it only through its own
ground-truth modules (:data:`GROUND_TRUTH`). No module imports itself back round a
circle, none imports another module's private names, and none outside tests is over
:data:`MAX_LINES` lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Each package and the packages it may import.
ALLOWED = {
    "core": set(),
    "capture": {"core"},
    "data_synth": {"core", "capture"},
    "recon": {"core", "capture"},
    "billboards": {"core", "capture", "recon"},
    "render": {"core", "capture", "billboards"},
    "share": {"core", "capture", "billboards", "render"},
    "bbcity": {"core", "capture", "data_synth", "recon", "billboards", "render", "share"},
}

#: The modules that compare a stage's output with the synthetic ground truth, and what
#: they may import besides their package's :data:`ALLOWED`.
GROUND_TRUTH = {
    "recon.evaluate": {"data_synth"},
    "billboards.truth": {"data_synth"},
    "billboards.facade_truth": {"data_synth"},
    "billboards.evaluate": {"data_synth"},
    "render.evaluate": {"data_synth", "recon"},
}

MAX_LINES = 600


def modules() -> dict[str, Path]:
    """Every module of the project's packages: dotted name → file."""
    found = {}
    for package in ALLOWED:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> list[tuple[str, str | None]]:
    """``(module, imported name or None)`` for every import of a project module in ``path``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            for alias in node.names:
                sub = f"{module}.{alias.name}"
                found.append((sub, None) if sub in known else (module, alias.name))
    return [(m, n) for m, n in found if m.split(".")[0] in ALLOWED]


def graph() -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    """Module → modules it imports, and every ``(importer, module, name)`` of a private name."""
    known = modules()
    edges: dict[str, set[str]] = {}
    private = []
    for name, path in known.items():
        edges[name] = set()
        for module, imported in imports(name, path, known):
            edges[name].add(module)
            if imported and imported.startswith("_") and not imported.startswith("__"):
                private.append((name, module, imported))
    return edges, private


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in edges:
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for nxt in successors:
                if nxt not in edges:
                    continue
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(edges[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def test_packages_import_only_those_below_them():
    edges, _ = graph()
    wrong = []
    for name, targets in edges.items():
        package = name.split(".")[0]
        allowed = ALLOWED[package] | {package} | GROUND_TRUTH.get(name, set())
        wrong += [f"{name} imports {t}" for t in sorted(targets) if t.split(".")[0] not in allowed]
    assert not wrong, "\n".join(wrong)


def test_no_import_circles():
    edges, _ = graph()
    assert not cycles(edges)


def test_cycle_finder_finds_a_circle():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(edges) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_private_names_across_modules():
    _, private = graph()
    assert not private, "\n".join(f"{a} imports {n} from {m}" for a, m, n in private)


def test_no_module_over_the_line_limit():
    long = {name: len(path.read_text().splitlines()) for name, path in modules().items()}
    assert not {name: n for name, n in long.items() if n > MAX_LINES}
