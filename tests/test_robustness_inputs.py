"""Robustness against inputs that are well formed but wrong: a cloud file holding more
points than its header says, a cloud no camera sees, a rig whose focal length puts
the stereo search beyond the image, booleans given as image sizes, a screenshot name
whose suffix is not PNG, a dataset run that failed midway, and the mode of the
directories the model writer creates.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from core.fileio import DataFormatError
from data_synth import SynthConfig
from recon.cloud_io import read_cloud, read_cloud_arrays

from .test_robustness_readers import _cloud, ply_bytes

READERS = [read_cloud, read_cloud_arrays]


# ----------------------------------------------------------------------------------------------
# cloud files: the body is exactly what the header declares


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("reader", READERS)
def test_ply_header_claiming_fewer_points_than_the_file_holds(tmp_path, fmt, reader):
    points, colours, _ = _cloud(5)
    path = tmp_path / "c.ply"
    path.write_bytes(ply_bytes(fmt, points, colours, count=3))
    with pytest.raises(DataFormatError, match="promises 3 points") as info:
        reader(path)
    assert info.value.path == path and str(path) in str(info.value)
    found = "5 lines" if fmt == "ascii" else f"{5 * 27} bytes"  # 3 doubles + 3 uchars a point
    assert found in str(info.value)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("tail, ok", [(b"", True), (b"\n \n", None), (b"\x00", False), (b"7 7 7 1 2 3\n", False)])
def test_ply_bytes_after_the_points(tmp_path, fmt, tail, ok):
    """Blank lines may end an ASCII body; anything else after the points is refused."""
    points, colours, _ = _cloud(4)
    path = tmp_path / "c.ply"
    path.write_bytes(ply_bytes(fmt, points, colours) + tail)
    if ok is None:
        ok = fmt == "ascii"
    if ok:
        np.testing.assert_array_equal(read_cloud_arrays(path)[0], points)
    else:
        with pytest.raises(DataFormatError, match="promises 4 points"):
            read_cloud_arrays(path)


def test_ply_with_faces_after_the_vertices_still_reads(tmp_path):
    """A mesh: the faces after the vertices are not read, and not counted as vertices."""
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.eye(3)), o3d.utility.Vector3iVector([[0, 1, 2]]))
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.full((3, 3), 0.5))
    for ascii in (False, True):
        path = tmp_path / f"mesh{int(ascii)}.ply"
        o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=ascii)
        np.testing.assert_allclose(read_cloud_arrays(path)[0], np.eye(3))


@pytest.mark.parametrize("ascii, compressed", [(True, False), (False, False), (False, True)])
def test_pcd_header_claiming_fewer_points_than_the_file_holds(tmp_path, ascii, compressed):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.arange(15.0).reshape(5, 3)))
    pcd.colors = o3d.utility.Vector3dVector(np.full((5, 3), 0.5))
    path = tmp_path / "c.pcd"
    o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii, compressed=compressed)
    data = path.read_bytes()
    head, body = data.split(b"DATA", 1)
    if compressed:  # the body's own size fields say what it holds: bytes appended instead
        path.write_bytes(data + b"\x00" * 16)
    else:
        path.write_bytes(head.replace(b"WIDTH 5", b"WIDTH 3").replace(b"POINTS 5", b"POINTS 3") + b"DATA" + body)
    with pytest.raises(DataFormatError, match="promises") as info:
        read_cloud_arrays(path)
    assert info.value.path == path


# ----------------------------------------------------------------------------------------------
# rig: booleans are not image sizes


@pytest.mark.parametrize("field", ["width", "height"])
def test_rig_json_boolean_image_size_is_refused(tiny_dataset, tmp_path, field):
    from capture import Rig

    data = json.loads((Path(tiny_dataset) / "rig.json").read_text())
    data["cameras"][1][field] = True
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match=rf"cameras\[1\]\.{field} must be a positive integer") as info:
        Rig.load(path)
    assert info.value.path == path and str(path) in str(info.value)
    data["cameras"][1][field] = 160
    data["version"] = True  # == 1 to Python
    path.write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match="version"):
        Rig.load(path)


@pytest.mark.parametrize("field", ["width", "height"])
def test_rig_config_boolean_image_size_is_refused(field):
    from data_synth import RigConfig

    with pytest.raises(ValueError, match=f"{field} must be an integer"):
        RigConfig(**{field: True})
    assert RigConfig(**{field: np.int64(200)}).vfov_deg > 0


# ----------------------------------------------------------------------------------------------
# model directories: the mode of os.mkdir, not mkdtemp's 0o700


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o002])
def test_model_directory_has_the_mode_of_a_new_directory(tmp_path, umask):
    import stat

    from billboards import build as build_mod
    from billboards.model_reader import load
    from billboards.model_writer import save, temp_dir

    from .test_atlas_model import _write_streamed, make_model

    old = os.umask(umask)
    try:
        os.mkdir(tmp_path / "plain")
        expected = stat.S_IMODE((tmp_path / "plain").stat().st_mode)
        model, raw = make_model()
        saved = save(model, tmp_path / "saved")
        streamed = _write_streamed(tmp_path / "streamed", raw, "u8", "f32")
        replaced = save(load(saved), tmp_path / "streamed")  # over an existing model
        state = temp_dir(tmp_path, ".x.build-")  # the build's state directory
    finally:
        os.umask(old)
    assert expected == 0o777 & ~umask
    for path in (saved, streamed, replaced, state):
        assert stat.S_IMODE(path.stat().st_mode) == expected, path
    assert build_mod.temp_dir is temp_dir


# ----------------------------------------------------------------------------------------------
# build: a cloud that no camera sees


def _shifted_cloud(src, dst, shift=(0.0, 0.0, 0.0), keep=None):
    """The cloud at ``src`` moved by ``shift`` (m), optionally only the points where ``keep(points)``."""
    from recon.cloud_io import PlyStreamWriter

    points, colours = read_cloud_arrays(src)
    mask = np.ones(len(points), bool) if keep is None else keep(points)
    with PlyStreamWriter(dst, normals=False) as writer:
        writer.append(points[mask] + shift, colours[mask])
    return dst


@pytest.fixture(scope="module")
def gt_cloud(tiny_dataset, tmp_path_factory):
    from .conftest import write_ground_truth_cloud

    return write_ground_truth_cloud(tiny_dataset, tmp_path_factory.mktemp("cloud") / "cloud.ply")


def test_build_refuses_a_cloud_no_camera_sees(tiny_dataset, gt_cloud, tmp_path):
    from billboards.build import main as build_main

    from .test_build import small_config

    far = _shifted_cloud(gt_cloud, tmp_path / "far.ply", shift=(0.0, 0.0, 500.0))  # 500 m overhead
    with pytest.raises(ValueError, match=f"no camera of {tiny_dataset} sees any point of {far}: wrong dataset"):
        build_main(small_config(), far, tiny_dataset, tmp_path / "model")
    assert not (tmp_path / "model").exists() and list(tmp_path.iterdir()) == [far]
    # a cloud only the first frames see (the street's first 4 m) still builds
    start = float(read_cloud_arrays(gt_cloud)[0][:, 0].min())
    part = _shifted_cloud(gt_cloud, tmp_path / "part.ply", keep=lambda p: p[:, 0] < start + 4.0)
    result = build_main(small_config(), part, tiny_dataset, tmp_path / "model")
    assert result.report["voxels"] > 0


# ----------------------------------------------------------------------------------------------
# viewer: a screenshot holds the format its suffix names


def test_screenshot_is_written_in_the_format_of_its_suffix(tmp_path):
    from PIL import Image

    from render.viewer import save_image

    rgb = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    for name, fmt in (("a.png", "PNG"), ("b.jpg", "JPEG"), ("c.JPEG", "JPEG"), ("d.bmp", "BMP")):
        out = save_image(tmp_path / name, rgb)
        with Image.open(out) as image:
            assert image.format == fmt and image.size == (32, 24)
            if fmt != "JPEG":
                np.testing.assert_array_equal(np.asarray(image.convert("RGB")), rgb)
    for name in ("e.xyz", "f", "g.png.txt"):
        with pytest.raises(ValueError, match="cannot write an image as"):
            save_image(tmp_path / name, rgb)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.jpg", "c.JPEG", "d.bmp"]


def test_viewer_refuses_a_screenshot_suffix_before_opening_a_window(tmp_path, monkeypatch):
    pytest.importorskip("moderngl_window")
    from render import viewer

    def no_window(*args, **kwargs):
        raise AssertionError("a window was opened")

    monkeypatch.setattr(viewer, "_make_window", no_window)
    with pytest.raises(ValueError, match=r"shot\.jpx.*\.jpg"):
        viewer.run_viewer(None, script_frames=1, screenshot=tmp_path / "shot.jpx")


# ----------------------------------------------------------------------------------------------
# stereo: a focal length that puts the disparity range beyond the image


def test_disparity_search_is_bounded_by_the_image_width(caplog):
    from recon.stereo import DisparityRangeError, StereoConfig, _matcher_range, disparity, disparity_reference

    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (40, 64, 3), dtype=np.uint8)
    right = np.roll(left, -5, axis=1)
    with pytest.raises(DisparityRangeError, match=r"disparities of 66666\.7.*64-px wide image.*focal length"):
        disparity(left, right, StereoConfig(), focal_px=1e7, baseline_m=0.4)
    with pytest.raises(DisparityRangeError, match="64-px wide"):
        disparity_reference(left, right, StereoConfig(), focal_px=1e7, baseline_m=0.4)
    with pytest.raises(DisparityRangeError, match="min_disparity 96"):
        disparity(left, right, StereoConfig(min_disparity=96, num_disparities=16))
    # near depths beyond the image: searched up to its width, reported once
    for _ in range(2):
        d = disparity(left, right, StereoConfig(), focal_px=200.0, baseline_m=1.0)
    assert np.nanmedian(d[:, 20:]) == pytest.approx(5, abs=0.5)
    assert sum("searching up to 63 px" in r.message for r in caplog.records) == 1
    for extend in (True, False):
        lo, num = _matcher_range(1.0, 1e9, StereoConfig(extend_search=extend), 64)
        assert 0 <= lo and lo + num <= 64 + 16


def test_recon_of_a_rig_with_a_huge_focal_length_fails_clearly_and_cheaply(tiny_dataset, tmp_path):
    """fx = 1e7 once asked SGBM for 31 GB (rig.json now refuses such a lens for a 160-px image; 1e5 px is
    the longest it takes, and still asks for more disparities than the image has); run in a child whose
    address space is limited to 6 GB."""
    import resource
    import shutil
    import subprocess
    import sys

    dataset = tmp_path / "street"
    shutil.copytree(tiny_dataset, dataset)
    rig = json.loads((dataset / "rig.json").read_text())
    for cam in rig["cameras"]:
        cam["fx"] = cam["fy"] = 1e5
    (dataset / "rig.json").write_text(json.dumps(rig))
    code = ("import sys\nfrom recon.pipeline import ReconConfig, main\n"
            "main(ReconConfig(evaluate=False), sys.argv[1], sys.argv[2], progress=False)\n")

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))

    res = subprocess.run([sys.executable, "-c", code, str(dataset), str(tmp_path / "work")], capture_output=True,
                         text=True, timeout=120, preexec_fn=limit, cwd=Path(__file__).resolve().parents[1])
    assert res.returncode != 0
    assert "DisparityRangeError: stereo pair cam0–cam1" in res.stderr, res.stderr[-2000:]
    assert "rig.json fx, fy" in res.stderr and "Insufficient memory" not in res.stderr


# ----------------------------------------------------------------------------------------------
# synth: a run that failed midway is finished by the same command


@pytest.mark.parametrize("writer, nth", [("write_png", 4), ("save_npy", 2), ("street_coverage", 1)])
def test_failed_synth_resumes_and_other_settings_are_refused_clearly(tiny_dataset, tmp_path, monkeypatch,
                                                                      writer, nth):
    import data_synth.dataset as ds_mod
    from capture import load_dataset
    from data_synth import RigConfig, write_dataset

    from .conftest import tiny_config
    from .test_dataset_io import digest_tree

    original, calls = getattr(ds_mod, writer), []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == nth:
            raise OSError("No space left on device")
        return original(*args, **kwargs)

    out = tmp_path / "street"
    monkeypatch.setattr(ds_mod, writer, failing)
    with pytest.raises(OSError, match="No space"):
        write_dataset(tiny_config(), out, progress=False)
    monkeypatch.setattr(ds_mod, writer, original)
    assert not (out / "dataset.json").exists()
    with pytest.raises(FileExistsError, match=r"unfinished dataset .* other settings \(frames, street\.seed\): run "
                                              r"it again with those settings to finish it, or remove it"):
        write_dataset(tiny_config(seed=3, frames=2), out, progress=False)
    write_dataset(tiny_config(), out, progress=False)  # the same command again: finished
    assert digest_tree(out) == digest_tree(tiny_dataset)
    assert load_dataset(out).num_frames == 6
    with pytest.raises(FileExistsError, match=r"holds a dataset made with other settings \(rig\.width\); choose"):
        write_dataset(tiny_config(rig=RigConfig(width=200, height=120, hfov_deg=75.0, pitch_deg=10.0)),
                      out, progress=False)


@pytest.mark.parametrize("field, value", [("frames", 0), ("frames", True), ("spp", 0), ("spp", 1.5),
                                          ("town_path_length", float("nan")), ("town_path_length", -1.0),
                                          ("lane_offset", float("inf")), ("scene", "city")])
def test_synth_config_refuses_what_cannot_be_rendered(field, value):
    with pytest.raises(ValueError, match=field if field != "scene" else "unknown scene"):
        SynthConfig(**{field: value})


def test_colmap_model_whose_frame_names_a_missing_image(tiny_dataset, tmp_path):
    """images.txt cut short by a line: a frame of frames.txt names an image the model lacks."""
    import shutil

    from recon.importers.colmap import import_colmap

    model = tmp_path / "model"
    shutil.copytree(Path(tiny_dataset) / "colmap", model)
    images = model / "images.txt"
    images.write_text("\n".join(images.read_text().splitlines()[:-1]) + "\n")
    with pytest.raises(DataFormatError, match="which the model's images lack") as caught:
        import_colmap(model, Path(tiny_dataset) / "images", tmp_path / "out")
    assert caught.value.path == model and not (tmp_path / "out").exists()


@pytest.mark.parametrize("field, value, message", [
    ("fx", 1e7, "fx 1e+07 px is not a lens's"), ("fy", 1e-300, "fy 1e-300 px is not a lens's"),
    ("fx", True, "numbers only"), ("cx", "79.5", "numbers only")])
def test_rig_json_lens_values_that_are_no_lens(tiny_dataset, tmp_path, field, value, message):
    import shutil

    from capture import load_dataset

    dataset = tmp_path / "street"
    shutil.copytree(tiny_dataset, dataset)
    rig = json.loads((dataset / "rig.json").read_text())
    rig["cameras"][1][field] = value
    (dataset / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(DataFormatError, match=re.escape(message)) as caught:
        load_dataset(dataset)
    assert caught.value.path == dataset / "rig.json"
