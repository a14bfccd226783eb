"""nerfstudio's transforms.json: export a dataset, import it back, and the importer's bad inputs."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image as PILImage

from bbcity.cli import main
from capture import load_dataset, load_poses, save_poses
from data_synth import RigConfig, write_dataset
from recon.importers.nerfstudio import NerfstudioImportConfig, import_nerfstudio
from recon.importers.nerfstudio_export import NerfstudioExportConfig, export_nerfstudio

from .conftest import tiny_config


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """4 frames × 3 cameras, 64×48, pitched up 10°: a z-up world."""
    cfg = tiny_config(frames=4, return_pass=False, spp=1, ground_truth_depth=False,
                      rig=RigConfig(width=64, height=48, hfov_deg=75.0, pitch_deg=10.0))
    return write_dataset(cfg, tmp_path_factory.mktemp("ns") / "street", progress=False)


@pytest.fixture(scope="module")
def exported(street, tmp_path_factory):
    return export_nerfstudio(street, tmp_path_factory.mktemp("ns_export") / "ns", NerfstudioExportConfig(holdout=2))


def _pairs(original) -> list[tuple[int, int]]:
    """(frame, camera) of each image in the exported file's sorted order (camera-major)."""
    return [(f, c) for c in range(original.rig.num_cameras) for f in range(original.num_frames)]


def test_export_writes_every_image_with_its_camera(street, exported):
    original = load_dataset(street)
    meta = json.loads((exported / "transforms.json").read_text())
    K = original.rig.intrinsics[0]
    assert meta["camera_model"] == "PINHOLE" and (meta["w"], meta["h"]) == (64, 48)
    assert (meta["fl_x"], meta["cx"], meta["cy"]) == (K[0, 0], K[0, 2] + 0.5, K[1, 2] + 0.5)  # pixel centres at .5
    assert len(meta["frames"]) == 12
    entry = next(fr for fr in meta["frames"] if fr["file_path"] == "images/cam1_000002.png")
    T = np.array(entry["transform_matrix"])
    np.testing.assert_array_equal(T[:3, 0], original.world_from_cam(2, 1)[:3, 0])
    np.testing.assert_array_equal(T[:3, 1:3], -original.world_from_cam(2, 1)[:3, 1:3])  # OpenGL: y up, z back
    # holdout 2: frames 1 and 3 held out; test is camera 0 of them, train every camera of frames 0 and 2
    assert meta["test_filenames"] == meta["val_filenames"] == ["images/cam0_000001.png", "images/cam0_000003.png"]
    assert sorted(meta["train_filenames"]) == sorted(f"images/cam{c}_{f:06d}.png" for c in range(3) for f in (0, 2))
    image = np.asarray(PILImage.open(exported / "images" / "cam2_000003.png"))
    assert np.array_equal(image, original.image(3, 2))


def test_round_trip_keeps_poses_intrinsics_and_pixels(street, exported, tmp_path):
    original = load_dataset(street)
    out = import_nerfstudio(exported / "transforms.json", tmp_path / "back")
    back = load_dataset(out)
    pairs = _pairs(original)
    assert back.rig.num_cameras == 1 and back.num_frames == len(pairs)
    assert back.frame_names == tuple(f"cam{c}_{f:06d}" for f, c in pairs)
    np.testing.assert_allclose(back.rig.intrinsics[0], original.rig.intrinsics[0], rtol=0, atol=1e-9)
    assert back.rig.distortion(0) is None and back.rig.sizes[0] == original.rig.sizes[0]
    for k, (f, c) in enumerate(pairs):
        # the exported world is z-up: the import keeps it, every pose exactly
        np.testing.assert_allclose(back.world_from_cam(k, 0), original.world_from_cam(f, c), rtol=0, atol=1e-9)
        assert np.array_equal(back.image(k, 0), original.image(f, c))
    # the rig frame is the camera made level: z up, x its view along the ground
    view = np.linalg.inv(back.rig.cam_from_rig[0])[:3, 2]
    np.testing.assert_allclose(view, [np.cos(np.radians(10.0)), 0, np.sin(np.radians(10.0))], atol=1e-9)  # 10° up
    assert np.allclose(back.world_from_rig[0][:3, 2], [0, 0, 1], atol=1e-9)
    source = json.loads((out / "dataset.json").read_text())["source"]
    assert source["world"] == "kept" and source["metric"] is False and source["poses"] == "given"


def test_a_world_that_is_not_z_up_is_turned(street, exported, tmp_path):
    original = load_dataset(street)
    meta = json.loads((exported / "transforms.json").read_text())
    turn = np.eye(4)
    turn[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # z-up → y-up (Blender's export of a scene, say)
    turn[:3, 3] = [5.0, -2.0, 1.0]
    for fr in meta["frames"]:
        fr["transform_matrix"] = (turn @ np.array(fr["transform_matrix"])).tolist()
    shutil.copytree(exported / "images", tmp_path / "ns" / "images")
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    back = load_dataset(import_nerfstudio(tmp_path / "ns", tmp_path / "back", NerfstudioImportConfig(metric=True)))
    source = json.loads((tmp_path / "back" / "dataset.json").read_text())["source"]
    assert source["world"] == "turned z-up" and source["metric"] is True and source["units"] == "metres"
    a = np.array([original.world_from_cam(f, c) for f, c in _pairs(original)])
    b = np.array([back.world_from_cam(k, 0) for k in range(back.num_frames)])
    change = b[0] @ np.linalg.inv(a[0])  # one rigid change of world maps every pose …
    np.testing.assert_allclose(change[None] @ a, b, atol=1e-9)
    # … and keeps up up, to the cameras' pitch (10°): the estimate's error
    assert np.degrees(np.arccos(change[2, 2])) < 10.5
    # "keep" leaves it turned
    kept = load_dataset(import_nerfstudio(tmp_path / "ns", tmp_path / "kept", NerfstudioImportConfig(world="keep")))
    np.testing.assert_allclose(kept.world_from_cam(0, 0), turn @ a[0], atol=1e-9)


def _write_transforms(folder: Path, meta: dict, frames: int = 2, size=(32, 24)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    entries = []
    for i in range(frames):
        PILImage.new("RGB", size, (40 * i, 90, 200)).save(folder / "images" / f"frame_{i:05d}.jpg")
        T = np.eye(4)  # a level camera looking along +x (OpenGL axes: x right, y up, z back), 1 m apart
        T[:3, :3] = np.array([[0, -1, 0], [0, 0, 1], [-1, 0, 0]]).T
        T[0, 3] = i
        entries.append({"file_path": f"images/frame_{i:05d}.jpg", "transform_matrix": T.tolist()})
    (folder / "transforms.json").write_text(json.dumps({**meta, "frames": entries}))
    return folder / "transforms.json"


BASE = {"fl_x": 30.0, "fl_y": 31.0, "cx": 16.0, "cy": 12.0, "w": 32, "h": 24}


@pytest.mark.parametrize("model, coeffs, lens", [
    ("OPENCV", {"k1": -0.05, "k2": 0.01, "p1": 0.001, "p2": -0.002}, ("radtan", (-0.05, 0.01, 0.001, -0.002, 0.0))),
    ("OPENCV_FISHEYE", {"k1": 0.02, "k2": -0.006, "k3": 0.001, "k4": -1e-4},
     ("fisheye", (0.02, -0.006, 0.001, -1e-4))),
    ("PINHOLE", {}, None),
])
def test_lenses_map_to_the_rig_lenses(tmp_path, model, coeffs, lens):
    path = _write_transforms(tmp_path / "ns", {**BASE, "camera_model": model, **coeffs})
    ds = load_dataset(import_nerfstudio(path, tmp_path / "ds"))
    np.testing.assert_allclose(ds.rig.raw_K(0), [[30, 0, 15.5], [0, 31, 11.5], [0, 0, 1]])
    d = ds.rig.distortion(0)
    assert (d is None and lens is None) or (d.model, d.coeffs) == lens
    # the camera's pose: frame 1 is 1 m along x, looking along it (the z-up world kept)
    np.testing.assert_allclose(ds.world_from_cam(1, 0)[:3, 3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ds.world_from_cam(1, 0)[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    assert ds.image(0, 0).shape == (24, 32, 3)


def _break(meta_path: Path, edit) -> None:
    meta = json.loads(meta_path.read_text())
    edit(meta)
    meta_path.write_text(json.dumps(meta))


@pytest.mark.parametrize("case, message", [
    ("missing image", r"images/frame_00001\.jpg: image named in transforms\.json is missing"),
    ("no fl_x", r"transforms\.json: frames\[0\] has no 'fl_x'"),
    ("infinite", r"transforms\.json: frames\[1\]\.transform_matrix has non-finite values"),
    ("scaled", r"transforms\.json: frames\[0\]\.transform_matrix is not a rotation and translation"),
    ("two cameras", r"transforms\.json: the frame of images/frame_00001\.jpg has another camera"),
    ("equirectangular", r"transforms\.json: camera_model 'EQUIRECTANGULAR' cannot be imported"),
    ("wrong size", r"frame_00000\.jpg: image is 32x24 but transforms\.json gives w×h 40x24"),
])
def test_bad_transforms_are_one_clear_line(tmp_path, caplog, case, message):
    path = _write_transforms(tmp_path / "ns", {"camera_model": "OPENCV"})
    for fr in (edits := json.loads(path.read_text()))["frames"]:
        fr.update(BASE)  # per-frame intrinsics
    path.write_text(json.dumps(edits))
    if case == "missing image":
        (tmp_path / "ns" / "images" / "frame_00001.jpg").unlink()
    elif case == "no fl_x":
        _break(path, lambda m: m["frames"][0].pop("fl_x"))
    elif case == "infinite":
        _break(path, lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, "INF"))
        path.write_text(path.read_text().replace('"INF"', "1e999"))
    elif case == "scaled":
        _break(path, lambda m: m["frames"][0].update(transform_matrix=np.diag([2.0, 2.0, 2.0, 1.0]).tolist()))
    elif case == "two cameras":
        _break(path, lambda m: m["frames"][1].update(fl_x=40.0))
    elif case == "equirectangular":
        _break(path, lambda m: m.update(camera_model="EQUIRECTANGULAR"))
    elif case == "wrong size":
        _break(path, lambda m: [fr.update(w=40) for fr in m["frames"]])
    assert main(["import", "nerfstudio", str(path), "--out", str(tmp_path / "ds")]) == 2
    lines = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(lines) == 1 and "Traceback" not in caplog.text, caplog.text
    assert re.search(message, lines[0]), lines[0]
    assert not (tmp_path / "ds").exists()


def test_export_through_the_cli_leaves_out_frames_without_a_pose(street, tmp_path, caplog):
    ds = tmp_path / "street"
    shutil.copytree(street, ds, ignore=shutil.ignore_patterns("gt", "colmap"))
    poses, names = load_poses(ds / "poses.json")
    poses[1] = np.nan
    (ds / "poses.json").unlink()
    save_poses(ds / "poses.json", poses, np.zeros(len(poses), dtype=np.int32), names=names)
    caplog.set_level("INFO")
    assert main(["export", "nerfstudio", str(ds), "--out", str(tmp_path / "ns")]) == 0
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    assert len(meta["frames"]) == 9 and "test_filenames" not in meta
    assert not any("_000001" in fr["file_path"] for fr in meta["frames"])
    assert "1 frames without a pose left out" in caplog.text
    assert main(["export", "nerfstudio", str(ds), "--out", str(tmp_path / "ns")]) == 2  # never over an output


def test_configs_are_checked():
    with pytest.raises(ValueError):
        NerfstudioExportConfig(holdout=1)
    with pytest.raises(ValueError):
        NerfstudioImportConfig(world="up")
