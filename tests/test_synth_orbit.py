"""The orbit capture path: one loop round the free-standing building of a street's square
(``SynthConfig(path="orbit")``, ``bbcity synth street --path orbit``), and what recon's
motion stereo makes of it and of a one-camera walk, found by SfM from the bare photos."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bbcity.cli import main
from capture import load_dataset
from data_synth import (Kind, RigConfig, StreetConfig, SynthConfig, TownConfig, build_street, frames_for_spacing,
                        make_rig, write_dataset)
from data_synth.config import ORBIT_CLEARANCE_M, capture_path, config_from_json
from data_synth.street import free_building, street_settings

#: One level camera, small landscape images.
ONE_CAMERA = dict(width=320, height=240, hfov_deg=75.0, pitch_deg=0.0, baselines=(0.0,))
SURFACES = (Kind.GROUND, Kind.ROAD, Kind.SIDEWALK)


def orbit_config(radius: float = 25.0, frames: int = 72, rig: dict = ONE_CAMERA, **overrides) -> SynthConfig:
    """An orbit of ``frames`` frames round the building in the middle of a 60 m street."""
    street = StreetConfig(length=60.0, seed=0, square=radius + ORBIT_CLEARANCE_M)
    return SynthConfig(path="orbit", orbit_radius=radius, street=street, frames=frames, rig=RigConfig(**rig),
                       spp=1, **overrides)


def run_cli(argv: list[str]) -> int:
    """main(argv)'s exit status, argparse's SystemExit included."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def _building(cfg: SynthConfig):
    """The street's scene, the id of the orbit's building and the building's centre (3,)."""
    scene = build_street(cfg.street)
    lo, hi = free_building(cfg.street)
    bounds = scene.object_bounds
    ids = np.flatnonzero((scene.object_kind == Kind.BUILDING) & np.all(np.abs(bounds[:, 0, :2] - lo) < 1e-9, axis=1)
                         & np.all(np.abs(bounds[:, 1, :2] - hi) < 1e-9, axis=1))
    assert len(ids) == 1
    return scene, int(ids[0]), bounds[ids[0]].mean(axis=0)


def _project(K: np.ndarray, world_from_cam: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(u, v, z) of the world point X (3,) in a camera."""
    c = np.linalg.solve(world_from_cam, np.append(X, 1.0))[:3]
    return np.array([*(K @ c)[:2] / c[2], c[2]])


# --------------------------------------------------------------------------- the path


@pytest.mark.parametrize("rig", [ONE_CAMERA, {}], ids=["one level camera", "default rig"])
def test_the_orbit_circles_the_building_looking_at_its_centre(rig):
    cfg = orbit_config(frames=72, rig=rig)
    poses, passes = capture_path(cfg)
    assert poses.dtype == np.float64 and poses.shape == (72, 4, 4) and (passes == 0).all()  # one pass
    scene, building, centre = _building(cfg)
    r, n = cfg.orbit_radius, cfg.frames
    # the rig walks the circle at its height, evenly spaced (the loop closed: the last frame's next is the first)
    xy = poses[:, :2, 3] - centre[:2]
    np.testing.assert_allclose(np.hypot(*xy.T), r, rtol=0, atol=1e-9)
    np.testing.assert_allclose(poses[:, 2, 3], 0.0, atol=1e-12)
    steps = np.linalg.norm(np.roll(poses[:, :3, 3], -1, axis=0) - poses[:, :3, 3], axis=1)
    np.testing.assert_allclose(steps, 2 * r * math.sin(math.pi / n), rtol=1e-9)
    heading = np.degrees(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    np.testing.assert_allclose(np.diff(np.unwrap(heading, period=360)), -360 / n, atol=1e-9)  # clockwise
    assert xy[0, 1] == pytest.approx(r) and poses[0, 0, 0] == pytest.approx(1.0)  # starts north, heading +x
    # every camera sees the building's centre (at its mid-height too) inside its image, near the middle column
    cameras = make_rig(cfg.rig)
    for c in range(cameras.num_cameras):
        K, (w, h) = cameras.intrinsics[c], cameras.sizes[c]
        for T in poses:
            cam = cameras.world_from_cam(T, c)
            for X in (np.array([*centre[:2], cam[2, 3]]), centre):
                u, v, z = _project(K, cam, X)
                assert z > 0 and 0 <= u <= w - 1 and 0 <= v <= h - 1
                assert abs(u - K[0, 2]) < (1e-6 if c == 0 else 0.05 * w)  # cam0 on the circle, the others beside it
    # the path is free: within the circle's clearance nothing stands but the building and the ground's surfaces
    lo, hi = scene.object_bounds[:, 0, :2], scene.object_bounds[:, 1, :2]
    gap = np.maximum(np.maximum(lo - centre[:2], centre[:2] - hi), 0.0)
    near = np.flatnonzero(np.hypot(*gap.T) < r + ORBIT_CLEARANCE_M)
    assert [i for i in near if scene.object_kind[i] not in SURFACES] == [building]
    corners = np.array([[x, y] for x in (lo[building, 0], hi[building, 0]) for y in (lo[building, 1], hi[building, 1])])
    assert np.hypot(*(corners - centre[:2]).T).max() <= r - ORBIT_CLEARANCE_M


def test_a_square_only_takes_objects_away_from_the_street():
    plain, square = StreetConfig(length=60.0, seed=2), StreetConfig(length=60.0, seed=2, square=20.0)
    a, b = build_street(plain), build_street(square)
    assert 0 < b.num_objects < a.num_objects
    # the square's street is the plain one less some objects, in the same order (the same random sequence)
    rows = {(int(k), int(s), tuple(x.ravel())): i for i, (k, s, x) in
            enumerate(zip(a.object_kind, a.object_seed, a.object_bounds))}
    order = [rows[(int(k), int(s), tuple(x.ravel()))] for k, s, x in zip(b.object_kind, b.object_seed, b.object_bounds)]
    assert order == sorted(order)
    # a street without a square keeps its settings' bytes
    assert "square" not in street_settings(plain) and street_settings(square)["square"] == 20.0
    assert a.config == street_settings(plain) and b.config == street_settings(square)


def test_frames_from_spacing_round_a_loop():
    assert frames_for_spacing(2 * math.pi * 25.0, 2.0, closed=True) == 79  # 1.99 m apart, no frame repeated
    assert frames_for_spacing(30.0, 3.0) == 11  # an open pass keeps both ends
    assert orbit_config().path_length == pytest.approx(2 * math.pi * 25.0) and orbit_config().passes == 1


def test_the_cli_makes_an_orbit_with_its_defaults_from_the_config(tmp_path):
    out = tmp_path / "orbit"
    argv = ["-q", "synth", "street", "--path", "orbit", "--frame-spacing", "2", "--lazy", "--out", str(out)]
    assert run_cli(argv) == 0
    manifest = json.loads((out / "dataset.json").read_text())
    cfg = config_from_json(manifest["synth"])
    assert cfg.path == "orbit" and cfg.orbit_radius == SynthConfig.orbit_radius and manifest["frames"] == 79
    assert cfg.street.square == cfg.orbit_radius + ORBIT_CLEARANCE_M and manifest["lazy"]["reach_m"] is None
    assert all(frame["pass"] == 0 for frame in json.loads((out / "poses.json").read_text())["frames"])


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize("settings, message", [
    (dict(path="loop"), r"SynthConfig\.path must be one of \('drive', 'orbit'\)"),
    (dict(path="orbit", scene="town", town=TownConfig(size=200.0)), r"path \"orbit\" needs the street scene"),
    (dict(path="orbit"), r"needs the street's open square \(StreetConfig\.square\) to reach at least 27 m"),
    (dict(path="orbit", street=StreetConfig(square=26.0)), r"StreetConfig\.square.* at least 27 m"),
    (dict(path="orbit", orbit_radius=8.0, street=StreetConfig(square=30.0)),
     r"orbit_radius \(--orbit-radius\) 8 m passes within 2 m of the free-standing building's corners"),
    (dict(orbit_radius=-1.0), r"SynthConfig\.orbit_radius must be positive"),
    (dict(orbit_radius=float("nan")), r"SynthConfig\.orbit_radius must be a finite number"),
    (dict(orbit_radius=True), r"SynthConfig\.orbit_radius must be a finite number"),
    (dict(orbit_radius="25"), r"SynthConfig\.orbit_radius must be a finite number"),
])
def test_bad_orbit_settings_are_refused(settings, message):
    with pytest.raises(ValueError, match=message):
        SynthConfig(**settings)


@pytest.mark.parametrize("square", [-1.0, float("inf"), float("nan"), True, "10"])
def test_a_bad_square_is_refused(square):
    with pytest.raises(ValueError, match=r"StreetConfig\.square must be a finite number of metres ≥ 0"):
        StreetConfig(square=square)


@pytest.mark.parametrize("argv, message", [
    (["town", "--path", "orbit"], "--path orbit needs the street scene"),
    (["street", "--orbit-radius", "20"], "--orbit-radius applies to --path orbit"),
    (["street", "--path", "orbit", "--orbit-radius", "8"], "(--orbit-radius) 8 m passes within 2 m"),
    (["street", "--path", "circle"], "argument --path: invalid choice: 'circle'"),
])
def test_the_cli_refuses_bad_orbits_in_one_line(tmp_path, capsys, argv, message):
    assert run_cli(["-q", "synth", *argv, "--lazy", "--out", str(tmp_path / "d")]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and message in errors[0]
    assert not (tmp_path / "d").exists()


# --------------------------------------------------------------------------- the dataset


def test_an_orbit_dataset_round_trips_and_casts_lazily_the_same_frames(tmp_path):
    tiny = dict(ONE_CAMERA, width=64, height=48)
    cfg = orbit_config(frames=6, rig=tiny)
    stored = load_dataset(write_dataset(cfg, tmp_path / "stored", progress=False))
    lazy = load_dataset(write_dataset(orbit_config(frames=6, rig=tiny, lazy=True), tmp_path / "lazy", progress=False))
    manifest = json.loads((stored.root / "dataset.json").read_text())
    assert config_from_json(manifest["synth"]) == cfg and manifest["synth"]["path"] == "orbit"
    assert json.loads((stored.root / "gt" / "scene.json").read_text())["config"]["square"] == cfg.street.square
    np.testing.assert_array_equal(stored.world_from_rig, capture_path(cfg)[0])
    np.testing.assert_array_equal(lazy.world_from_rig, stored.world_from_rig)
    assert json.loads((lazy.root / "dataset.json").read_text())["lazy"]["reach_m"] is None  # cast from the whole street
    _, building, _ = _building(cfg)
    for f in (0, 3):
        np.testing.assert_array_equal(lazy.image(f, 0), stored.image(f, 0))
        # ground truth as for a drive: the image's centre is the building's wall, farther than its corners
        depth, ids = stored.gt_depth(f, 0), stored.gt_ids(f, 0)
        np.testing.assert_array_equal(depth, lazy.gt_depth(f, 0))
        assert ids[24, 32] == building and cfg.orbit_radius - 13.0 < depth[24, 32] < cfg.orbit_radius


def test_a_dataset_json_without_the_path_loads_as_a_drive(tmp_path):
    cfg = SynthConfig(street=StreetConfig(length=30.0), rig=RigConfig(width=64, height=48), frames=2, lazy=True)
    root = write_dataset(cfg, tmp_path / "drive", progress=False)
    synth = json.loads((root / "dataset.json").read_text())["synth"]
    # a drive's settings are those written before orbits: no path, radius or square
    assert not {"path", "orbit_radius"} & set(synth) and "square" not in synth["street"]
    assert "square" not in json.loads((root / "gt" / "scene.json").read_text())["config"]
    old = config_from_json(synth)
    assert old == cfg and old.path == "drive" and old.street.square == 0.0
    assert load_dataset(root).num_frames == 4


# --------------------------------------------------------------------------- as a user would: photos, SfM, partners


def _partner_share(dataset: Path, tmp_path: Path, step: float) -> tuple[float, dict, np.ndarray]:
    """cam0's images imported as a photo folder with the true K (the poses forgotten), SfM on
    them, and motion stereo's partners by the sparse points' depths: the share of frames with
    a partner on at least one side, the SfM report and the frames' sparse depths (n, 3)."""
    from recon.motion_stereo import MotionStereoConfig, select_partners
    from recon.pipeline import ReconConfig, estimate_poses
    from recon.sfm import SfmConfig

    K = load_dataset(dataset).rig.intrinsics[0]
    (tmp_path / "K.txt").write_text("\n".join(" ".join(repr(float(v)) for v in row) for row in K) + "\n")
    photos = tmp_path / "photos"
    assert main(["-q", "import", "photos", str(dataset / "images" / "cam0"), "--out", str(photos), "--intrinsics",
                 str(tmp_path / "K.txt"), "--step-length", repr(step)]) == 0
    world_from_rig, report, depths = estimate_poses(ReconConfig(poses="sfm", sfm=SfmConfig(num_threads=1)), photos,
                                                    tmp_path / "work")
    rig = load_dataset(photos).rig
    world_from_cam = world_from_rig @ np.linalg.inv(rig.cam_from_rig[0])
    partners = select_partners(world_from_cam, rig.intrinsics[0], rig.sizes[0], MotionStereoConfig(),
                               depth=depths[:, 1])
    return float((partners >= 0).any(axis=1).mean()), report, depths


@pytest.mark.slow
def test_an_orbit_found_by_sfm_gets_motion_stereo_partners(tmp_path):
    # 72 frames 5° (2.2 m) apart round the building at 25 m; the walls 13-20 m from the camera
    # (at 10° steps, or 15 m away, SfM breaks the loop at the building's corners)
    out = tmp_path / "orbit"
    assert main(["-q", "synth", "street", "--path", "orbit", "--orbit-radius", "25", "--frames", "72", "--length", "60",
                 "--cameras", "1", "--width", "320", "--height", "240", "--hfov", "75", "--pitch", "0", "--spp", "1",
                 "--no-gt-depth", "--workers", "2", "--out", str(out)]) == 0
    share, report, _ = _partner_share(out, tmp_path, step=2 * 25.0 * math.sin(math.pi / 72))
    assert report["registered_frames"] >= 0.9 * 72
    assert share >= 0.9


@pytest.mark.slow
def test_a_walk_along_the_facades_found_by_sfm_gets_motion_stereo_partners(tmp_path):
    # bbcity synth street --cameras 1 --frame-spacing 3 --no-return (the default portrait camera), 45 m
    from recon.motion_stereo import MotionStereoConfig

    out = tmp_path / "walk"
    assert main(["-q", "synth", "street", "--cameras", "1", "--frame-spacing", "3", "--no-return", "--length", "45",
                 "--spp", "1", "--no-gt-depth", "--workers", "2", "--out", str(out)]) == 0
    share, report, depths = _partner_share(out, tmp_path, step=3.0)
    assert report["registered_frames"] >= 0.9 * 16
    # the facades stand 5-9 m from the lane: 3 m is up to 0.55 of that, within max_baseline_ratio
    assert np.nanmax(3.0 / depths[:, 1]) <= MotionStereoConfig().max_baseline_ratio
    assert share >= 0.9
