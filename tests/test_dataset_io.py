"""Dataset writing (determinism, atomicity, resume) and reading (clear errors)."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest


from core import DataFormatError
from core.fileio import atomic_path, load_npy, read_png, save_npy, write_png
from capture import load_dataset
from data_synth import write_dataset

from .conftest import tiny_config


def digest_tree(root):
    """sha256 of every file but the run's timing report."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "synth_report.json"}


def test_same_seed_same_bytes_other_seed_differs(tmp_path, tiny_dataset):
    cfg = tiny_config(frames=2)
    a = digest_tree(write_dataset(cfg, tmp_path / "a", progress=False))
    b = digest_tree(write_dataset(cfg, tmp_path / "b", progress=False))
    assert a == b
    assert len(a) > 20
    c = digest_tree(write_dataset(tiny_config(seed=1, frames=2), tmp_path / "c", progress=False))
    assert c.keys() == a.keys()
    differing = [k for k in a if a[k] != c[k]]
    assert any(k.startswith("images/") for k in differing)
    assert "gt/mesh.ply" in differing


def test_dataset_layout(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    assert ds.num_frames == 6 and ds.rig.num_cameras == 3  # 3 frames per pass, return pass
    assert ds.image(0, 2).shape == (120, 160, 3)
    assert ds.world_from_rig.dtype == np.float64
    for name in ("cameras.txt", "images.txt", "rigs.txt", "frames.txt"):
        assert (tiny_dataset / "colmap" / name).is_file()
    manifest = json.loads((tiny_dataset / "dataset.json").read_text())
    assert manifest["frames"] == 6 and manifest["cameras"] == 3


def test_resume_renders_only_what_is_missing_and_refuses_other_settings(tmp_path):
    cfg = tiny_config(frames=2)
    out = write_dataset(cfg, tmp_path / "d", progress=False)
    before = digest_tree(out)
    missing = out / "images" / "cam1" / "000002.png"
    missing.unlink()
    stamp = (out / "images" / "cam0" / "000000.png").stat().st_mtime_ns
    write_dataset(cfg, out, progress=False)
    assert digest_tree(out) == before
    assert (out / "images" / "cam0" / "000000.png").stat().st_mtime_ns == stamp  # kept, not redone
    with pytest.raises(FileExistsError, match="other settings"):
        write_dataset(tiny_config(seed=5, frames=2), out, progress=False)


def test_interrupted_write_leaves_no_file(tmp_path):
    target = tmp_path / "x.npy"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            np.save(tmp, np.zeros(10))
            raise RuntimeError("killed mid-write")
    assert list(tmp_path.iterdir()) == []
    save_npy(target, np.arange(3))
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("killed mid-write")
    np.testing.assert_array_equal(np.load(target), np.arange(3))  # the old file survives


@pytest.fixture
def dataset_copy(tiny_dataset, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(tiny_dataset, dst)
    return dst


def test_missing_frame_names_the_file(dataset_copy):
    victim = dataset_copy / "images" / "cam2" / "000004.png"
    victim.unlink()
    with pytest.raises(DataFormatError, match=str(victim)):
        load_dataset(dataset_copy)


def test_truncated_png_names_the_file(dataset_copy):
    victim = dataset_copy / "images" / "cam0" / "000001.png"
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    ds = load_dataset(dataset_copy)
    with pytest.raises(DataFormatError, match=f"{victim}.*truncated"):
        ds.image(1, 0)
    with pytest.raises(DataFormatError, match=str(victim)):
        ds.verify()


def test_non_png_and_wrong_size_name_the_file(dataset_copy, tmp_path):
    victim = dataset_copy / "images" / "cam1" / "000000.png"
    victim.write_bytes(b"GIF89a not a png")
    with pytest.raises(DataFormatError, match=f"{victim}.*not a PNG"):
        load_dataset(dataset_copy).image(0, 1)
    write_png(victim, np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(DataFormatError, match=f"{victim}.*12x10, expected 160x120"):
        load_dataset(dataset_copy).image(0, 1)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: "{not json", "not valid JSON"),
    (lambda d: {**d, "format": "something"}, "not a rig file"),
    (lambda d: {**d, "cameras": []}, "non-empty list"),
    (lambda d: {**d, "cameras": [{**d["cameras"][0], "fx": None}]}, "intrinsics"),
    (lambda d: {**d, "cameras": [{k: v for k, v in d["cameras"][0].items() if k != "cy"}]}, "lacks cy"),
    (lambda d: {**d, "cameras": [{**d["cameras"][0], "width": -3}]}, "width/height"),
    (lambda d: {**d, "cameras": [{**d["cameras"][0], "cam_from_rig": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]},
     "not orthonormal"),
    (lambda d: {**d, "cameras": [{**d["cameras"][0], "cam_from_rig": [[1, 0, 0]]}]}, "shape"),
    (lambda d: {**d, "cameras": [{**d["cameras"][0], "distortion": [0.1, 0]}]}, "distortion"),
])
def test_malformed_rig_json_names_the_file(dataset_copy, mutate, message):
    path = dataset_copy / "rig.json"
    new = mutate(json.loads(path.read_text()))
    path.write_text(new if isinstance(new, str) else json.dumps(new))
    with pytest.raises(DataFormatError, match=f"{path}.*{message}"):
        load_dataset(dataset_copy)


def test_malformed_poses_json_names_the_file(dataset_copy):
    path = dataset_copy / "poses.json"
    data = json.loads(path.read_text())
    data["frames"][3]["world_from_rig"][0][3] = float("nan")
    path.write_text(json.dumps(data))  # Python writes NaN, which strict JSON forbids
    with pytest.raises(DataFormatError, match=f"{path}"):
        load_dataset(dataset_copy)
    data["frames"][3]["world_from_rig"][0][3] = 1.0
    data["frames"][3]["name"] = "../escape"
    path.write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match=f"{path}.*plain file stem"):
        load_dataset(dataset_copy)


def test_npy_reader_guards(tmp_path):
    p = tmp_path / "a.npy"
    np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DataFormatError, match="pickles"):
        load_npy(p)
    save_npy(p, np.zeros((4, 5), np.float64))
    with pytest.raises(DataFormatError, match="dtype float64, expected float32"):
        load_npy(p, dtype=np.float32)
    with pytest.raises(DataFormatError, match=r"shape \(4, 5\), expected \(\*, 6\)"):
        load_npy(p, shape=(None, 6))
    with pytest.raises(DataFormatError, match="exceeds the limit"):
        load_npy(p, max_bytes=100)
    save_npy(p, np.array([1.0, np.nan]))
    with pytest.raises(DataFormatError, match="NaN or inf"):
        load_npy(p, finite=True)
    p.write_bytes(b"\x93NUMPY\x01\x00garbage")
    with pytest.raises(DataFormatError, match=str(p)):
        load_npy(p)


def test_png_roundtrip(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    write_png(tmp_path / "x.png", rgb)
    np.testing.assert_array_equal(read_png(tmp_path / "x.png", (9, 7)), rgb)


def test_ground_truth_depth_behind_the_camera_names_the_file(dataset_copy):
    """Issue 35: negative ground-truth depths were scored against (stereo-sweep's bad-pixel rate
    0.033 became 0.156); a depth is NaN (no hit) or a positive distance."""
    ds = load_dataset(dataset_copy)
    path = dataset_copy / "gt" / "depth" / "cam0" / f"{ds.frame_names[0]}.npy"
    depth = np.load(path)
    depth[2, 3] = -depth[2, 3] if np.isfinite(depth[2, 3]) else -1.0
    save_npy(path, depth)
    with pytest.raises(DataFormatError, match=r"holds 1 depths that are neither NaN \(no hit\) nor a positive") as err:
        ds.gt_depth(0, 0)
    assert err.value.path == path
    assert np.isfinite(ds.gt_depth(1, 0)).any()  # the other frames still read


def test_lens_that_leaves_almost_nothing_of_the_image_names_the_file(dataset_copy):
    """Issue 35: a fisheye with k1 = 1e6 reconstructed to an empty cloud with exit 0."""
    rig = json.loads((dataset_copy / "rig.json").read_text())
    rig["cameras"][1]["distortion"] = {"model": "fisheye", "k1": 1e6, "k2": 0.0, "k3": 0.0, "k4": 0.0}
    (dataset_copy / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(DataFormatError, match=r"cameras\[1\]\.distortion leaves an undistorted image \d+× narrower"):
        load_dataset(dataset_copy)
