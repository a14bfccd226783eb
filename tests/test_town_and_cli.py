"""The dense town for culling, and the command line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from bbcity.cli import main
from capture import load_dataset
from data_synth import Kind, RigConfig, SynthConfig, TownConfig, build_town, write_dataset


def test_town_has_thirty_thousand_separate_objects():
    scene = build_town(TownConfig())
    houses = np.flatnonzero(scene.object_kind == Kind.HOUSE)
    assert len(houses) >= 30_000
    lo, hi = scene.object_bounds[houses, 0], scene.object_bounds[houses, 1]
    assert np.all(hi > lo)
    extent = scene.object_bounds[:, 1].max(axis=0) - scene.object_bounds[:, 0].min(axis=0)
    assert extent[0] >= 2000 and extent[1] >= 2000
    # houses are separate: no two boxes of one block overlap
    pitch = TownConfig().block_size + TownConfig().street_width
    centre = 0.5 * (lo + hi)[:, :2]
    block = np.floor((centre + 1000.0) / pitch).astype(np.int64) @ np.array([100_000, 1])
    order = np.argsort(block, kind="stable")
    block, lo, hi = block[order], lo[order], hi[order]
    starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
    counts = np.diff(np.r_[starts, len(block)])
    slot = np.arange(len(block)) - np.repeat(starts, counts)
    grid_lo = np.full((len(starts), counts.max(), 2), np.nan)
    grid_hi = np.full((len(starts), counts.max(), 2), np.nan)
    row = np.repeat(np.arange(len(starts)), counts)
    grid_lo[row, slot], grid_hi[row, slot] = lo[:, :2], hi[:, :2]
    overlap = np.all((grid_lo[:, :, None] < grid_hi[:, None, :]) & (grid_lo[:, None, :] < grid_hi[:, :, None]), axis=-1)
    overlap &= ~np.eye(counts.max(), dtype=bool)[None]
    assert not overlap.any()


def test_town_dataset_renders(tmp_path):
    cfg = SynthConfig(scene="town", town=TownConfig(size=300.0), rig=RigConfig(width=64, height=48),
                      frames=1, town_path_length=20.0, spp=1)  # one frame per pass
    ds = load_dataset(write_dataset(cfg, tmp_path / "town", progress=False))
    ids = ds.gt_ids(0, 0)
    kinds = np.load(tmp_path / "town" / "gt" / "objects" / "kind.npy")
    for frame in (0, 1):  # out and back: houses on both sides of the middle street
        ids = ds.gt_ids(frame, 0)
        assert np.mean(kinds[ids[ids >= 0]] == Kind.HOUSE) > 0.3


def test_town_roofs_render_from_above():
    from data_synth import make_rig
    from data_synth.raycast import Renderer

    scene = build_town(TownConfig(size=300.0))
    rig = make_rig(RigConfig(width=64, height=48, pitch_deg=-60.0))  # looking down over the roofs
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [10.0, 10.0, 25.0]
    result = Renderer(scene).render(rig.intrinsics[0], rig.world_from_cam(world_from_rig, 0), (64, 48))
    houses = (result.ids >= 0) & (scene.object_kind[np.maximum(result.ids, 0)] == Kind.HOUSE)
    assert houses.mean() > 0.3
    assert result.rgb[houses].std() > 10  # tiles, walls and windows, not a flat colour


def test_help_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "bbcity.cli", "--help"], capture_output=True, text=True, check=True)
    commands = ("synth", "recon", "stereo-sweep", "check", "bench")
    for cmd in commands:
        assert cmd in out.stdout
    for cmd in commands:
        with pytest.raises(SystemExit) as e:
            main([cmd, "--help"])
        assert e.value.code == 0


def test_synth_and_check_from_the_command_line(tmp_path, capsys, caplog):
    out = tmp_path / "s"
    assert main(["-q", "synth", "street", "--out", str(out), "--frames", "1", "--length", "20",
                 "--width", "48", "--height", "32", "--workers", "1", "--no-return"]) == 0
    assert main(["check", str(out), "--deep"]) == 0
    assert "1 frames × 3 cameras, 48x32" in capsys.readouterr().out
    (out / "rig.json").write_text("{")
    assert main(["check", str(out)]) == 2
    assert f"{out / 'rig.json'}: not valid JSON" in caplog.text
