"""Every command-line option is checked when it is parsed (bbcity.options).

A bad value ends the command with exit 2 and one error line naming the option, before
anything is read, written or allocated: focused cases for each kind of refusal, the
configs' own checks, and a seeded fuzz of every subcommand with bad values, one option
at a time on an otherwise valid command line whose first input is missing (so a value
that passes never starts real work).
"""

from __future__ import annotations

import argparse
import math
import random

import numpy as np
import pytest

from bbcity import options
from bbcity.cli import build_parser, main
from bbcity.options import GL_MAX_SIZE, float_range, int_range, max_workers


def run_cli(argv: list[str]) -> int:
    """main(argv)'s exit status, argparse's SystemExit included."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def usage_error(capsys) -> str:
    """The one error line of an argparse refusal (after its usage lines)."""
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if ": error: " in line]
    assert len(errors) == 1 and errors[0] == err[-1], err
    return errors[0]


# ----------------------------------------------------------------------------------------------
# the refusals found by an adversarial run


#: (argv, the option its error names); M, D and O stand for a model, a dataset and an output
#: under the test's temporary directory, none of which exists
FINDINGS = [
    *((["recon", "D", "--out", "O", "--voxel-size", v], "--voxel-size") for v in ("0", "-1", "nan")),
    *((["recon", "D", "--out", "O", "--frame-stride", v], "--frame-stride") for v in ("0", "-1")),
    (["view", "M", "--script-frames", "-1"], "--script-frames"),
    (["view", "M", "--window", "headless"], "--script-frames"),  # would never close
    (["view", "M", "--window", "nosuch"], "--window"),  # issue 35: a traceback
    (["view", "M", "--script-frames", "2", "--script-keys", "ESCAPE"], "--script-keys"),  # closed, then a traceback
    (["view", "M", "--script-frames", "2", "--script-keys", "C,NOSUCH"], "--script-keys"),
    (["recon", "D", "--out", "O", "--voxel-size", "1e-320"], "--voxel-size"),  # denormal: an infinite grid
    (["recon", "D", "--out", "O", "--min-depth", "1e-320"], "--min-depth"),
    (["eval", "M", "D", "--out", "O", "--views", "99999999999"], "--views"),
    (["bench", "--out", "O", "--repeats", "99999999999"], "--repeats"),
    (["bench", "--out", "O", "--street-length", "1e-320"], "--street-length"),
    *((["render", "M", "--out", "O", "--fps", v], "--fps") for v in ("0", "-30")),
    (["eval", "M", "D", "--out", "O", "--views", "0"], "--views"),
    *((["synth", "street", "--out", "O", "--length", v], "--length") for v in ("0", "nan")),
    (["synth", "street", "--out", "O", "--workers", "1000"], "--workers"),
    (["recon", "D", "--out", "O", "--workers", "1000"], "--workers"),
    (["build", "D", "--out", "O", "--workers", "1000"], "--workers"),
    (["view", "M", "--size", "100000", "100000"], "--size"),
    (["render", "M", "--out", "O", "--size", "100000", "100000"], "--size"),
    (["eval", "M", "D", "--out", "O", "--size", "20000", "100"], "--size"),
    (["synth", "street", "--out", "O", "--width", "100000"], "--width"),
    (["synth", "street", "--out", "O", "--height", "100000"], "--height"),
    (["build", "D", "--out", "O", "--tile", "4096"], "--tile"),
    (["build", "D", "--out", "O", "--page-size", "20000"], "--page-size"),
    (["build", "D", "--out", "O", "--tile", "64", "--page-size", "32"], "--tile"),
    (["build", "D", "--out", "O", "--directions", "40", "--spacing", "1", "--page-size", "32"], "--directions"),
]


def _in(tmp_path, argv: list[str]) -> list[str]:
    return [str(tmp_path / a) if a in ("M", "D", "O", "W") else a for a in argv]


@pytest.mark.parametrize("argv, option", FINDINGS)
def test_finding_is_refused_at_parse_time(tmp_path, capsys, argv, option):
    assert run_cli(_in(tmp_path, argv)) == 2
    line = usage_error(capsys)
    assert line.startswith(f"bbcity {argv[0]}: error:") and option in line, line
    assert list(tmp_path.iterdir()) == []  # nothing written, not even the output's lock


def test_recon_pose_source_is_one_value_before_or_after_the_dataset(tmp_path, capsys):
    p = build_parser()
    for argv in (["recon", "--poses", "sfm", "D", "--out", "W"], ["recon", "D", "--poses", "sfm", "--out", "W"]):
        a = p.parse_args(argv)
        assert (a.dataset.name, a.poses, a.colmap_model) == ("D", "sfm", None)
    a = p.parse_args(["recon", "--poses", "colmap", "--colmap-model", "sparse/0", "D", "--out", "W"])
    assert (a.dataset.name, a.poses, str(a.colmap_model)) == ("D", "colmap", "sparse/0")
    assert p.parse_args(["recon", "D", "--out", "W"]).poses == "given"
    for argv, message in ((["--poses", "colmap"], "--poses colmap needs --colmap-model DIR"),
                          (["--poses", "sfm", "--colmap-model", "M"], "--colmap-model goes with --poses colmap"),
                          (["--poses", "colmap", "M"], "--poses colmap needs --colmap-model DIR"),  # old spelling
                          (["--poses", "icp"], "invalid choice: 'icp'")):
        assert run_cli(["recon", str(tmp_path / "D"), "--out", str(tmp_path / "W"), *argv]) == 2
        line = usage_error(capsys)
        assert line.startswith("bbcity recon: error:") and message in line, line
    assert list(tmp_path.iterdir()) == []


def test_workers_limit_is_four_times_the_cores(capsys):
    limit = max_workers()
    assert build_parser().parse_args(["synth", "street", "--out", "x", "--workers", str(limit)]).workers == limit
    with pytest.raises(SystemExit):
        build_parser().parse_args(["synth", "street", "--out", "x", "--workers", str(limit + 1)])
    assert f"must be at most {limit} (4 × the usable cores)" in usage_error(capsys)


@pytest.mark.parametrize("argv", [
    ["render", "M", "--out", "O", "--size", "16384", "16384"],
    ["view", "M", "--size", "16384", "16384"],
    ["eval", "M", "D", "--out", "O", "--size", "8192", "8192"],
    ["synth", "street", "--out", "O", "--width", "16384", "--height", "16384", "--workers", "1"],
    ["build", "W", "--out", "O", "--tile", "128", "--workers", "1"],
])
def test_sizes_beyond_the_available_memory_are_refused(monkeypatch, tmp_path, capsys, argv):
    argv = _in(tmp_path, argv)
    monkeypatch.setattr(options, "available_memory", lambda: 1 << 30)  # 1 GiB
    assert run_cli(argv) == 2
    line = usage_error(capsys)
    assert "GiB of memory, more than the 1.0 GiB available" in line, line
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(options, "available_memory", lambda: None)  # unknown: not refused for memory
    build_parser().parse_args(argv)


def test_shared_options_are_defined_once():
    subs = build_parser()._subparsers._group_actions[0].choices

    def option(command, name):
        return next(a for a in subs[command]._actions if name in a.option_strings)

    for name, commands in (("--workers", ("synth", "recon", "build")), ("--decode", ("render", "view")),
                           ("--cull", ("render", "view")), ("--size", ("render", "view", "eval", "fps"))):
        actions = [option(c, name) for c in commands]
        assert len({(a.type, a.nargs, str(a.choices)) for a in actions}) == 1, name
    assert [option(c, "--size").default for c in ("render", "view", "eval", "fps")] == [(1280, 720), (1280, 720),
                                                                                     None, (1280, 720)]


def test_usage_errors_after_parsing_are_one_line_and_verbose_adds_the_traceback(tmp_path, capsys, caplog):
    assert run_cli(["fps"]) == 2  # neither a model nor --town: refused as the options are parsed
    assert "give a model directory, --town, or both" in usage_error(capsys)
    argv = ["build", "--out", str(tmp_path / "model")]  # neither WORK nor --cloud: refused by the command
    assert run_cli(argv) == 2
    assert "give a recon WORK directory or --cloud" in caplog.text and "Traceback" not in caplog.text
    caplog.clear()
    assert run_cli(["-v", *argv]) == 2
    assert "Traceback" in caplog.text and "UsageError: give a recon WORK directory or --cloud" in caplog.text
    assert issubclass(options.UsageError, ValueError)


def test_memory_estimates():
    assert options.available_memory() > 0
    # a render target of 16384² holds RGBA8 colour and float depth: at least 8 bytes a pixel
    assert options.RENDER_BYTES_PER_PIXEL * GL_MAX_SIZE ** 2 >= 8 * GL_MAX_SIZE ** 2
    pinhole = options.synth_bytes(416, 736, 2, False, 1)
    assert 416 * 736 * 11 < pinhole < 416 * 736 * 40  # RGB + depth + ids, and a row chunk of rays
    assert options.synth_bytes(416, 736, 4, True, 3) > 3 * 416 * 736 * 17 * 16  # a lens's ray grid, per worker
    assert options.build_bytes(8, 32, 128, 2) == 2 * 128 * 32 * 64 * 4 * options.BUILD_BYTES_PER_TEXEL


def test_defaults_and_valid_values_are_unchanged():
    p = build_parser()
    a = p.parse_args(["recon", "D", "--out", "W"])
    assert (a.voxel_size, a.frame_stride, a.holdout, a.workers, a.min_depth, a.max_depth) == (0.02, 1, 0, None,
                                                                                             None, None)
    assert p.parse_args(["recon", "D", "--out", "W", "--max-depth", "inf"]).max_depth == math.inf
    a = p.parse_args(["build", "W", "--out", "M", "--tile", "16", "--pitches", "-10", "0", "20", "--max-error", "0"])
    assert (a.tile, a.page_size, a.pitches, a.max_error, a.holdout) == (16, 8192, [-10.0, 0.0, 20.0], 0.0, None)
    a = p.parse_args(["render", "M", "--out", "O", "--size", "640", "480", "--fps", "24"])
    assert tuple(a.size) == (640, 480) and a.fps == 24.0 and tuple(p.parse_args(["view", "M"]).size) == (1280, 720)
    a = p.parse_args(["synth", "town", "--out", "O", "--pitch", "-90", "--hfov", "169.5", "--seed", "7"])
    assert (a.pitch, a.hfov, a.seed, a.frames, a.length, a.spp) == (-90.0, 169.5, 7, 100, 300.0, 2)
    a = p.parse_args(["eval", "M", "D", "--out", "O", "--panel-width", "0", "--workprecision-depths"])
    assert a.panel_width == 0 and a.workprecision_depths == []


def test_type_functions():
    with pytest.raises(argparse.ArgumentTypeError, match="at most 8 \\(why\\)"):
        int_range(1, 8, "why")("9")
    for bad in ("1.5", "1e3", "true", "", "abc"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected an integer"):
            int_range(0)(bad)
    for bad in ("nan", "inf", "-inf", "1e309"):
        with pytest.raises(argparse.ArgumentTypeError, match="finite"):
            float_range()(bad)
    assert float_range(0.0, allow_inf=True)("inf") == math.inf
    with pytest.raises(argparse.ArgumentTypeError, match="finite"):
        float_range(0.0, allow_inf=True)("nan")
    assert float_range(-90.0, 90.0, lo_open=False)("-90") == -90.0
    with pytest.raises(argparse.ArgumentTypeError, match=r"must lie in \(-90, 90\)"):
        float_range(-90.0, 90.0, hi_open=True)("90")
    with pytest.raises(argparse.ArgumentTypeError, match="0 \\(none\\) or at least 2"):
        options.holdout("1")


def test_configs_refuse_what_the_options_refuse():
    from billboards.atlas import atlas_layout
    from billboards.octree import OctreeConfig
    from billboards.sampling import SamplingConfig
    from data_synth import RigConfig, StreetConfig, TownConfig
    from recon.fusion import FusionConfig
    from render.eval_config import EvalConfig

    for make in (lambda: RigConfig(width=True), lambda: RigConfig(height=False), lambda: SamplingConfig(tile=True),
                 lambda: EvalConfig(size=(True, 8)), lambda: EvalConfig(views=True),
                 lambda: OctreeConfig(voxel_size=None, depth=True), lambda: StreetConfig(length=0.0),
                 lambda: StreetConfig(length=math.nan), lambda: StreetConfig(seed=-1), lambda: TownConfig(seed=-1),
                 lambda: FusionConfig(voxel_size=0.0), lambda: FusionConfig(voxel_size=math.nan),
                 lambda: FusionConfig(voxel_size=math.inf), lambda: FusionConfig(tile_size=-1.0),
                 lambda: FusionConfig(min_observations=0)):
        with pytest.raises(ValueError):
            make()
    with pytest.raises(TypeError):
        atlas_layout(4, True, 64)
    FusionConfig(voxel_size=0.05, min_observations=1), StreetConfig(length=20.0, seed=3)  # valid ones still are


# ----------------------------------------------------------------------------------------------
# fuzz: every subcommand, every numeric option, one bad value at a time

#: values a careless or hostile caller passes for a number
BAD = ["0", "-1", "nan", "inf", "-inf", "1e309", "abc", "", "99999999", "true", "1.5", "-0.0", "1e-300",
       "16385", "4096", "257", "2", "0x10", " 3", "1_000", "-99999999"]


def _commands(tmp):
    """subcommand argv that fails at its first input (missing, or an output it may not take)
    → its numeric options and how many values each takes."""
    nx, out = str(tmp / "missing"), str(tmp / "out")
    taken = tmp / "taken"  # synth refuses a directory that holds something else
    taken.mkdir(exist_ok=True)
    (taken / "x").write_text("x")
    bench_out = tmp / "file"  # bench cannot make its report directory where a file is
    bench_out.write_text("x")
    return {
        ("synth", "street", "--out", str(taken)): {"--frames": 1, "--frame-spacing": 1, "--length": 1, "--width": 1,
                                                   "--height": 1, "--seed": 1, "--hfov": 1, "--pitch": 1,
                                                   "--cameras": 1, "--spp": 1, "--workers": 1,
                                                   "--scheduler": 1, "--retries": 1, "--orbit-radius": 1},
        ("import", "kitti", nx, "--out", out): {"--camera-height": 1, "--first": 1, "--count": 1, "--step": 1},
        ("import", "colmap", nx, "--images", nx, "--out", out): {},
        ("import", "photos", nx, "--out", out): {"--sensor-width": 1, "--step-length": 1},
        ("import", "video", nx, "--out", out): {"--fps": 1, "--frames": 1, "--step-length": 1},
        ("import", "nerfstudio", nx, "--out", out): {},
        ("export", "nerfstudio", nx, "--out", out): {"--holdout": 1},
        ("export", "web", nx, "--out", out): {"--gpu-budget": 1, "--fov": 1},
        ("export", "gltf", nx, "--out", str(tmp / "out.glb")): {},
        ("export", "3dtiles", nx, "--out", out): {"--lonlat-height": 3},
        ("serve", nx): {"--port": 1},
        ("recon", nx, "--out", out): {"--voxel-size": 1, "--min-depth": 1, "--max-depth": 1, "--frame-stride": 1,
                                      "--min-agree": 1, "--holdout": 1, "--workers": 1,
                                      "--scheduler": 1, "--retries": 1, "--max-image-size": 1},
        ("build", nx, "--out", out): {"--voxel-size": 1, "--depth": 1, "--min-points": 1, "--directions": 1,
                                      "--spacing": 1, "--pitches": "+", "--tile": 1, "--ratio": 1,
                                      "--max-error": 1, "--rank": 1, "--max-rank": 1, "--page-size": 1,
                                      "--holdout": 1, "--block-size": 1, "--workers": 1,
                                      "--scheduler": 1, "--retries": 1, "--tile-metres": 1,
                                      "--fit-seconds": 1, "--ground-reach": 1, "--ground-splits": 1,
                                      "--wall-reach": 1, "--wall-rise": 1},
        ("texture-sweep", nx, "--out", out): {"--count": 1, "--tiles": "+"},
        ("sampling-eval", nx, "--out", out): {"--count": 1, "--voxel-size": 1},
        ("stereo-sweep", nx, "--out", out): {"--frames": 1},
        ("check", nx): {},
        ("demo", "--out", str(bench_out)): {},
        ("bench", "--out", str(bench_out)): {"--repeats": 1, "--street-length": 1, "--city-scales": "+",
                                             "--gpu-budget": 1},
        ("view", nx): {"--size": 2, "--script-frames": 1, "--gpu-budget": 1},
        ("render", nx, "--out", out): {"--size": 2, "--frames": 1, "--fps": 1, "--gpu-budget": 1},
        ("eval", nx, nx, "--out", out): {"--views": 1, "--size": 2, "--poisson-depth": 1,
                                         "--workprecision-depths": "+", "--panel-width": 1,
                                         "--training-views": 1},
        ("mesh", nx): {"--depth": 1},
        ("fps", nx): {"--size": 2, "--gpu-frames": 1, "--cpu-frames": 1, "--path-step": 1, "--path-frames": 1,
                      "--gpu-budget": 1, "--walk-step": 1, "--walk-frames": 1},
    }


def test_every_subcommand_refuses_bad_numbers(tmp_path, capsys, caplog):
    commands = _commands(tmp_path)
    # every subcommand and every numeric option of the parser is driven
    parser = build_parser()
    subs = parser._subparsers._group_actions[0].choices
    nested = ("import", "export")  # commands whose first argument is a kind with its own options
    kinds = {n: subs[n]._subparsers._group_actions[0].choices for n in nested}
    numeric = {(name,): {o for a in p._actions for o in a.option_strings
                         if a.type not in (None, str) and a.type.__name__ != "Path" and o.startswith("--")}
               for name, p in [*((n, p) for n, p in subs.items() if n not in nested),
                               *((f"{n} {k}", p) for n in nested for k, p in kinds[n].items())]}
    driven = {}
    for base, opts in commands.items():
        name = " ".join(base[:2]) if base[0] in nested else base[0]
        driven[(name,)] = set(opts)
    assert driven == numeric

    rng = random.Random(0)
    np_rng = np.random.default_rng(0)
    before = list(tmp_path.iterdir())
    for base, opts in commands.items():
        runs = [list(base)] + [[*base, option, *values] for option, nargs in opts.items()
                               for values in _bad_values(rng, np_rng, nargs)]
        for argv in runs:
            try:
                code = run_cli(argv)
            except BaseException as e:  # noqa: BLE001 - any escape is the failure reported
                pytest.fail(f"bbcity {' '.join(argv)} raised {e!r}")
            captured = capsys.readouterr()
            assert code in (0, 2), (argv, code, captured.err)
            text = captured.out + captured.err + caplog.text
            assert "Traceback" not in text, (argv, text)
            caplog.clear()
    # no value that passes starts real work: the missing input ends it, before anything is written
    after = [p for p in tmp_path.iterdir() if not p.name.endswith(".lock")]  # outputs' locks stay, empty of meaning
    assert sorted(after) == sorted(before)


def _bad_values(rng: random.Random, np_rng: np.random.Generator, nargs) -> list[list[str]]:
    """Eight draws of bad values for an option taking ``nargs`` values (1, 2 or "+")."""
    draws = []
    for _ in range(8):
        if nargs == 2:  # a size: bad edges, or a huge pair
            pair = rng.choice([[rng.choice(BAD), "480"], ["640", rng.choice(BAD)],
                               [str(int(x)) for x in np_rng.integers(GL_MAX_SIZE // 2, 10 * GL_MAX_SIZE, 2)]])
            draws.append(pair)
        elif nargs == "+":
            draws.append([rng.choice(BAD) for _ in range(rng.randint(1, 3))])
        else:
            draws.append([rng.choice(BAD)])
    return draws


@pytest.mark.parametrize("argv, marker", [
    (["render", "{model}", "--out", "{out}", "--frames", "1", "--size", "16", "16"], "manifest.json"),
    (["recon", "{dataset}", "--out", "{out}"], "rig.json"),
    (["texture-sweep", "{work}", "--out", "{out}"], "notes.txt")])
def test_outputs_are_not_mixed_into_foreign_directories(tmp_path, caplog, argv, marker):
    """render's frames, recon's WORK and texture-sweep's report go into a new directory or an
    earlier one of their own kind: one holding a model's, a dataset's or anybody's files is
    refused before any work (issue 35: they were mixed into it), and left as it was."""
    out = tmp_path / "taken"
    out.mkdir()
    (out / marker).write_text("theirs")
    (out / ".hidden").write_text("hidden names are a run's own temporaries")
    paths = {"model": tmp_path / "missing", "dataset": tmp_path / "missing", "work": tmp_path / "missing", "out": out}
    assert main([a.format(**paths) for a in argv]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and f"holds '{marker}'" in errors[0]
    assert sorted(p.name for p in out.iterdir()) == [".hidden", marker]
    caplog.clear()
    (out / marker).unlink()  # only its own kind of file, or nothing: the command goes on to its input
    assert main([a.format(**paths) for a in argv]) == 2
    assert not any("holds" in r.getMessage() for r in caplog.records)
