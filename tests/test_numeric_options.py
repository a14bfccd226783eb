"""Every numeric option of every subcommand, driven with 0, -1, nan, inf and 1e300 on VALID
inputs (a tiny dataset, its recon WORK and a built model; issue 35, classes 4 and 5).

tests/test_cli_options.py drives bad values on missing inputs, where any value that passes
still ends at the first input. Here the inputs exist, so a value that passes must also be a
value the command can run with: each case is parsed (the parser's own ``check_options``
included) and must end in a refusal of one line (exit 2) or be accepted; the accepted values
that imply the most work (the huge and infinite ones) of the commands that run on these
inputs without a GPU window or a server are then run end to end in a subprocess under a
memory cap and a timeout, and must end with 0 or 2 within them, without a traceback and with
at most one ERROR line.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bbcity.cli import build_parser, main

#: the values every numeric option is driven with
VALUES = ("0", "-1", "nan", "inf", "1e300")
#: commands whose first argument is a kind with its own parser and options (--scheduler, an
#: address whose type is no str, is counted and driven like the numbers)
NESTED = ("import", "export")
#: memory cap (bytes) and wall-clock limit (s) of an end-to-end run
MEMORY_CAP = 6 << 30
TIMEOUT = 60


def numeric_options() -> dict[str, dict[str, object]]:
    """command name ("build", "import kitti") → {numeric option: its nargs}, from the real parser."""
    subs = build_parser()._subparsers._group_actions[0].choices
    parsers = [*((n, p) for n, p in subs.items() if n not in NESTED),
               *((f"{n} {k}", p) for n in NESTED for k, p in subs[n]._subparsers._group_actions[0].choices.items())]
    return {name: {o: a.nargs for a in p._actions for o in a.option_strings
                   if a.type not in (None, str) and a.type.__name__ != "Path" and o.startswith("--")}
            for name, p in parsers}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Paths of a tiny dataset, its recon WORK and a model built from it, and a scratch dir."""
    root = tmp_path_factory.mktemp("numeric")
    ds, work, model = root / "ds", root / "work", root / "model"
    assert main(["-q", "synth", "street", "--out", str(ds), "--length", "20", "--frames", "3", "--width", "96",
                 "--height", "72", "--spp", "1", "--workers", "1"]) == 0
    assert main(["-q", "recon", str(ds), "--out", str(work), "--voxel-size", "0.1", "--workers", "1"]) == 0
    assert main(["-q", "build", str(work), "--out", str(model), "--voxel-size", "0.5", "--tile", "8",
                 "--directions", "4", "--workers", "1"]) == 0
    return {"D": ds, "W": work, "M": model, "root": root}


def valid_commands(paths) -> dict[str, list[str]]:
    """command name → a valid argv on the tiny inputs (O: an output to be made under root).
    Kinds of import need their own formats of input: their options are parsed against the
    dataset's directory, which the parser accepts (it reads nothing)."""
    d, w, m = (str(paths[k]) for k in "DWM")
    return {
        "synth": ["synth", "street", "--out", "O", "--length", "20", "--frames", "2", "--width", "64", "--height",
                  "48", "--spp", "1", "--workers", "1"],
        "import kitti": ["import", "kitti", d, "--out", "O"],
        "import colmap": ["import", "colmap", d, "--images", d, "--out", "O"],
        "import photos": ["import", "photos", d, "--out", "O"],
        "import video": ["import", "video", d, "--out", "O"],
        "import nerfstudio": ["import", "nerfstudio", d, "--out", "O"],
        "export nerfstudio": ["export", "nerfstudio", w, "--out", "O"],
        "export web": ["export", "web", m, "--out", "O"],
        "export gltf": ["export", "gltf", m, "--out", "O.glb"],
        "export 3dtiles": ["export", "3dtiles", m, "--out", "O"],
        "serve": ["serve", m],
        "recon": ["recon", d, "--out", "O", "--voxel-size", "0.1", "--workers", "1"],
        "build": ["build", w, "--out", "O", "--voxel-size", "0.5", "--tile", "8", "--directions", "4",
                  "--workers", "1"],
        "texture-sweep": ["texture-sweep", w, "--out", "O", "--count", "2", "--tiles", "8"],
        "sampling-eval": ["sampling-eval", w, "--out", "O", "--count", "2"],
        "stereo-sweep": ["stereo-sweep", d, "--out", "O", "--frames", "2"],
        "check": ["check", m],
        "demo": ["demo", "--out", "O"],
        "bench": ["bench", "--out", "O", "--repeats", "1"],
        "view": ["view", m, "--script-frames", "2"],
        "render": ["render", m, "--out", "O", "--frames", "2", "--size", "32", "24"],
        "eval": ["eval", m, d, "--out", "O", "--views", "1", "--size", "32", "24"],
        "fps": ["fps", m, "--size", "32", "24", "--gpu-frames", "1", "--cpu-frames", "1", "--path-frames", "2"],
        "mesh": ["mesh", str(paths["W"] / "cloud.ply"), "--depth", "5"],
    }


#: the accepted values run end to end: the huge and infinite ones of the commands that run on
#: the tiny inputs without a window, a server or another input format, and every accepted value
#: of the headless renderers' (fps's path steps: a tiny one was unbounded; eval's counts)
_HUGE = ("inf", "1e300")
END_TO_END = {**{name: _HUGE for name in ("synth", "recon", "build", "sampling-eval", "export nerfstudio",
                                           "export web", "export gltf", "export 3dtiles")},
              "fps": VALUES, "eval": VALUES, "render": VALUES}


def _cases(paths):
    options = numeric_options()
    bases = valid_commands(paths)
    cases = []
    for name, opts in options.items():
        if not opts:
            continue
        assert name in bases, f"{name} has numeric options {sorted(opts)} but no valid command line here"
        for option, nargs in opts.items():
            count = nargs if isinstance(nargs, int) else 1  # None, "+" or "*": one value
            for value in VALUES:
                base = list(bases[name])
                if option in base:  # the base's own setting is replaced by the value driven
                    i = base.index(option)
                    del base[i:i + 1 + count]
                cases.append((name, option, value, [*base, option, *[value] * count]))
    # every numeric option of every subcommand is driven with every value
    driven = {(n, o) for n, o, _, _ in cases}
    assert driven == {(n, o) for n, opts in options.items() for o in opts}
    return cases


def _with_out(argv, out: Path) -> list[str]:
    return [str(out) if a == "O" else str(out) + ".glb" if a == "O.glb" else a for a in argv]


def _limits():
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))


def test_every_numeric_option_on_valid_inputs(inputs, capsys):
    cases = _cases(inputs)
    assert len(cases) >= 400
    accepted = []
    for i, (name, option, value, argv) in enumerate(cases):
        argv = _with_out(argv, inputs["root"] / f"out{i}")
        start = time.monotonic()
        try:
            build_parser().parse_args(argv)  # the command's check_options included
            code = 0
        except SystemExit as e:
            code = e.code
        except BaseException as e:  # noqa: BLE001 - any escape is the failure reported
            pytest.fail(f"bbcity {' '.join(argv)} raised {e!r}")
        err = capsys.readouterr().err
        assert time.monotonic() - start < 5, (argv, "parsing took too long")
        assert code in (0, 2), (argv, code, err)
        assert "Traceback" not in err and "internal error" not in err, (argv, err)
        if code == 2:
            errors = [line for line in err.splitlines() if ": error: " in line or " ERROR " in line]
            assert len(errors) == 1, (argv, err)
        else:
            accepted.append((name, option, value, argv))
        assert not (inputs["root"] / f"out{i}").exists(), (argv, "parsing wrote its output")

    # the accepted extremes that imply the most work run to their end: 0 or 2, bounded
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    ran = []
    for name, option, value, argv in accepted:
        if value not in END_TO_END.get(name, ()):
            continue
        start = time.monotonic()
        try:
            run = subprocess.run([sys.executable, "-m", "bbcity.cli", "-q", *argv], capture_output=True, text=True,
                                 timeout=TIMEOUT, preexec_fn=_limits, env=env)
        except subprocess.TimeoutExpired:
            pytest.fail(f"bbcity {' '.join(argv)} ran past {TIMEOUT} s")
        took = time.monotonic() - start
        assert run.returncode in (0, 2), (argv, run.returncode, run.stderr[-2000:])
        assert "Traceback" not in run.stderr and "internal error" not in run.stderr, (argv, run.stderr[-2000:])
        errors = [line for line in run.stderr.splitlines() if " ERROR " in line or ": error: " in line]
        assert len(errors) <= (1 if run.returncode == 2 else 0), (argv, run.stderr[-2000:])
        assert took < TIMEOUT, argv
        ran.append((name, option, value, run.returncode))
    assert len(ran) >= 10, ran  # the huge values accepted are run, not skipped


def test_largest_min_points_ends_in_one_line(inputs):
    """issue 35: ``build --min-points`` huge tried to allocate 2.94 PiB; the largest value the
    parser takes ends in one line (no voxel holds that many points), within the limits."""
    from billboards.octree import MAX_MIN_POINTS

    argv = _with_out([*valid_commands(inputs)["build"], "--min-points", str(MAX_MIN_POINTS)], inputs["root"] / "mp")
    run = subprocess.run([sys.executable, "-m", "bbcity.cli", "-q", *argv], capture_output=True, text=True,
                         timeout=TIMEOUT, preexec_fn=_limits, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert run.returncode in (0, 2) and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert len([ln for ln in run.stderr.splitlines() if " ERROR " in ln]) <= 1, run.stderr[-2000:]


def test_huge_block_size_is_refused_naming_it(inputs, caplog, capsys):
    """issue 35 class 5: ``build --block-size 1e300`` ended blaming the voxel size (an octree
    of depth 997); it is refused as it is parsed, naming --block-size."""
    out = inputs["root"] / "huge-block"
    try:
        code = main(["build", str(inputs["W"]), "--out", str(out), "--voxel-size", "0.5", "--tile", "8",
                     "--directions", "4", "--workers", "1", "--block-size", "1e300"])
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert code == 2
    line = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(line) == 1 and "--block-size" in line[0] and "voxel" not in line[0], err
    assert not out.exists()
