"""Importers: COLMAP models, photo folders and KITTI sequences → datasets, and their bad inputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image as PILImage
from PIL.TiffImagePlugin import IFDRational


from core import DataFormatError
from capture import load_dataset, load_poses, save_poses
from capture.colmap import write_colmap_text
from capture.native import pycolmap
from data_synth import RigConfig, StreetConfig, write_dataset
from recon.importers.colmap import camera_from_colmap, import_colmap, colmap_pinhole_maps
from recon.importers.kitti import KittiConfig, import_kitti
from recon.importers.photos import PhotosConfig, exif_focal_px, import_photos, read_intrinsics
from recon.trajectory import align_trajectory, level_from_world, up_direction

from .conftest import SMALL_RIG, tiny_config

KITTI06 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti06"


# --------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """A tiny street: 2 passes × 3 frames × 3 cameras, 160×120, its COLMAP model in colmap/."""
    cfg = tiny_config(ground_truth_depth=False, spp=1)
    return write_dataset(cfg, tmp_path_factory.mktemp("synth") / "street", progress=False)


def _camera_poses(ds) -> np.ndarray:
    """(n·c, 4, 4) float64 world_from_cam of every image of a dataset."""
    return np.array([ds.world_from_cam(f, c) for f in range(ds.num_frames) for c in range(ds.rig.num_cameras)])


def _world_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(4, 4) rigid b_world_from_a_world from camera poses (m, 4, 4) of the same cameras, checked
    to map every pose of ``a`` onto ``b``."""
    T = b[0] @ np.linalg.inv(a[0])
    assert np.abs(T[None] @ a - b).max() < 1e-6
    return T


def _check_same_capture(original, imported, check_up: bool = True) -> None:
    """Same intrinsics, lenses, images and camera poses up to one rigid change of world whose
    rotation keeps z (when ``check_up``)."""
    assert imported.frame_names == original.frame_names
    np.testing.assert_allclose(imported.rig.intrinsics, original.rig.intrinsics, atol=1e-9)
    for c in range(original.rig.num_cameras):
        assert imported.rig.distortion(c) == original.rig.distortion(c)
        np.testing.assert_allclose(imported.rig.raw_K(c), original.rig.raw_K(c), atol=1e-9)
    T = _world_change(_camera_poses(original), _camera_poses(imported))
    if check_up:
        np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-9)  # z stays up
    for f in (0, original.num_frames - 1):
        for c in range(original.rig.num_cameras):
            assert imported.image_path(f, c).read_bytes() == original.image_path(f, c).read_bytes()


def _copy_model(src: Path, dst: Path, drop=(), replace: dict | None = None) -> Path:
    """Copy a text model, leaving out the files ``drop`` and replacing text in every file."""
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.name in drop:
            continue
        text = p.read_text()
        for old, new in (replace or {}).items():
            text = text.replace(old, new)
        (dst / p.name).write_text(text)
    return dst


# --------------------------------------------------------------------------- COLMAP


def test_colmap_text_model_gives_the_same_rig_and_poses(synth, tmp_path):
    out = import_colmap(synth / "colmap", synth / "images", tmp_path / "ds")
    original, imported = load_dataset(synth), load_dataset(out)
    _check_same_capture(original, imported)
    # the rig frame is level (its z is the world's up) with x along cam0's view
    np.testing.assert_allclose(imported.world_from_rig[:, 2, 2], 1.0, atol=1e-9)
    np.testing.assert_allclose(imported.world_from_rig[0], np.eye(4), atol=1e-9)
    source = json.loads((out / "dataset.json").read_text())["source"]
    assert source["kind"] == "colmap" and source["frames_from"] == "rig 1" and "metric" in source["units"]


@pytest.mark.parametrize("name", ["frames.txt", "images.txt"])
@pytest.mark.parametrize("value, message", [("q", r"quaternion \[0\.0, 0\.0, 0\.0, 0\.0\].*norm 0"),
                                            ("t", r"translation \[1e\+300.*not within")])
def test_colmap_pose_that_is_no_rigid_transform_is_one_clear_error(synth, tmp_path, name, value, message):
    """pycolmap reads the quaternion 0 0 0 0 as the identity, and 1e300 m as a place: in a rig's
    frame (frames.txt) or, in a model without rigs, an image (images.txt)."""
    drop = () if name == "frames.txt" else ("rigs.txt", "frames.txt")
    model = _copy_model(synth / "colmap", tmp_path / "model", drop=drop)
    lines = (model / name).read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    parts = lines[first].split()
    q = 2 if name == "frames.txt" else 1  # FRAME_ID RIG_ID QW … / IMAGE_ID QW …
    if value == "q":
        parts[q:q + 4] = ["0"] * 4
    else:
        parts[q + 4:q + 7] = ["1e300", "0", "0"]
    lines[first] = " ".join(parts)
    (model / name).write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=message) as caught:
        import_colmap(model, synth / "images", tmp_path / "ds")
    assert caught.value.path == model and not (tmp_path / "ds").exists()


def test_colmap_camera_of_negative_width_is_shown_as_written(synth, tmp_path):
    """Issue 35: a width of −160 was reported as 18446744073709551456 (pycolmap's unsigned read)."""
    model = _copy_model(synth / "colmap", tmp_path / "model", replace={"PINHOLE 160 120": "PINHOLE -160 120"})
    with pytest.raises(DataFormatError, match=r"has width -160: not an image width"):
        import_colmap(model, synth / "images", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_colmap_binary_model_and_model_without_rig_match_the_text_model(synth, tmp_path):
    text = load_dataset(import_colmap(synth / "colmap", synth / "images", tmp_path / "text"))
    binary_dir = tmp_path / "bin"
    binary_dir.mkdir()
    pycolmap.Reconstruction(synth / "colmap").write_binary(binary_dir)
    binary = load_dataset(import_colmap(binary_dir, synth / "images", tmp_path / "binary"))
    np.testing.assert_allclose(binary.world_from_rig, text.world_from_rig, atol=1e-9)
    np.testing.assert_allclose(binary.rig.cam_from_rig, text.rig.cam_from_rig, atol=1e-9)
    # COLMAP before 3.12: no rigs.txt or frames.txt; cam{c}/NAME images grouped into frames
    old = _copy_model(synth / "colmap", tmp_path / "old", drop=("rigs.txt", "frames.txt"))
    grouped_dir = import_colmap(old, synth / "images", tmp_path / "grouped")
    grouped = load_dataset(grouped_dir)
    np.testing.assert_allclose(grouped.world_from_rig, text.world_from_rig, atol=1e-6)
    np.testing.assert_allclose(grouped.rig.cam_from_rig, text.rig.cam_from_rig, atol=1e-6)
    assert json.loads((grouped_dir / "dataset.json").read_text())["source"]["frames_from"] == "cam{c}/NAME images"


@pytest.mark.parametrize("with_rig_files", [True, False])
def test_colmap_one_camera_model(synth, tmp_path, with_rig_files):
    original = load_dataset(synth)
    photos = tmp_path / "photos"
    names = [[f"shot_{n}.png"] for n in original.frame_names]
    for n, row in zip(original.frame_names, names):
        (photos / row[0]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(synth / "images" / "cam1" / f"{n}.png", photos / row[0])
    model = write_colmap_text(tmp_path / "model", original.rig.intrinsics[1:2], original.rig.sizes[1:2],
                              np.eye(4)[None], np.array([original.world_from_cam(f, 1)
                                                         for f in range(original.num_frames)]), names)
    if not with_rig_files:
        (model / "rigs.txt").unlink()
        (model / "frames.txt").unlink()
    imported = load_dataset(import_colmap(model, photos, tmp_path / "ds"))
    assert imported.rig.num_cameras == 1 and imported.frame_names == tuple(f"shot_{n}" for n in original.frame_names)
    np.testing.assert_allclose(imported.rig.intrinsics[0], original.rig.intrinsics[1], atol=1e-9)
    T = _world_change(np.array([original.world_from_cam(f, 1) for f in range(original.num_frames)]),
                      _camera_poses(imported))
    np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-9)


@pytest.mark.parametrize("model, params, lens, coeffs", [
    ("SIMPLE_PINHOLE", [100, 50, 40], None, None),
    ("PINHOLE", [100, 110, 50, 40], None, None),
    ("SIMPLE_RADIAL", [100, 50, 40, 0.1], "radtan", (0.1, 0, 0, 0, 0)),
    ("RADIAL", [100, 50, 40, 0.1, 0.01], "radtan", (0.1, 0.01, 0, 0, 0)),
    ("OPENCV", [100, 110, 50, 40, 0.1, 0.01, 1e-3, 2e-3], "radtan", (0.1, 0.01, 1e-3, 2e-3, 0)),
    ("FULL_OPENCV", [100, 110, 50, 40, 0.1, 0.01, 1e-3, 2e-3, 1e-4, 0, 0, 0], "radtan", (0.1, 0.01, 1e-3, 2e-3, 1e-4)),
    ("SIMPLE_RADIAL_FISHEYE", [100, 50, 40, 0.02], "fisheye", (0.02, 0, 0, 0)),
    ("RADIAL_FISHEYE", [100, 50, 40, 0.02, -0.006], "fisheye", (0.02, -0.006, 0, 0)),
    ("OPENCV_FISHEYE", [100, 110, 50, 40, 0.02, -0.006, 0.001, -1e-4], "fisheye", (0.02, -0.006, 0.001, -1e-4)),
])
def test_colmap_camera_models_map_to_rig_lenses(model, params, lens, coeffs):
    cam = camera_from_colmap(pycolmap.Camera(camera_id=7, model=model, width=100, height=80, params=params),
                             Path("cameras.txt"))
    assert cam.raw is None and cam.size == (100, 80)
    fx = params[0]
    fy = params[1] if model in ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE") else fx
    np.testing.assert_allclose(cam.K, [[fx, 0, 49.5], [0, fy, 39.5], [0, 0, 1]])  # OpenCV pixel centres
    if lens is None:
        assert cam.distortion is None
    else:
        assert cam.distortion.model == lens
        np.testing.assert_allclose(cam.distortion.coeffs, coeffs)


@pytest.mark.parametrize("model, params", [
    ("FULL_OPENCV", [100, 100, 50, 40, -0.05, 0.01, 0, 0, 0, 0.02, 0, 0]),  # a rational term
    ("FOV", [100, 100, 50, 40, 0.3]),
    ("THIN_PRISM_FISHEYE", [100, 100, 50, 40, 0.02, 0, 0, 0, 0, 0, 1e-3, 0]),
])
def test_colmap_lenses_beyond_ours_are_undistorted_to_pinhole(model, params):
    raw = pycolmap.Camera(camera_id=3, model=model, width=100, height=80, params=params)
    cam = camera_from_colmap(raw, Path("cameras.txt"))
    assert cam.distortion is None and cam.pinhole.model.name == "PINHOLE" and cam.raw is raw
    map_x, map_y = colmap_pinhole_maps(cam.raw, cam.pinhole)
    assert map_x.shape == (cam.size[1], cam.size[0]) and map_x.dtype == np.float32
    # each pinhole pixel samples the raw pixel that sees the same ray
    v, u = 17, 23
    ray = np.append(cam.pinhole.cam_from_img(np.array([[u + 0.5, v + 0.5]]))[0], 1.0)
    np.testing.assert_allclose([map_x[v, u] + 0.5, map_y[v, u] + 0.5], raw.img_from_cam(ray[None])[0], atol=1e-3)


def test_undistort_maps_agree_with_opencv():
    K = np.array([[90.0, 0, 49.5], [0, 95.0, 39.5], [0, 0, 1]])
    d = np.array([-0.1, 0.02, 1e-3, -2e-3, 0.0])
    raw = pycolmap.Camera(model="OPENCV", width=100, height=80, params=[90, 95, 50, 40, *d[:4]])
    pinhole = pycolmap.Camera(model="PINHOLE", width=100, height=80, params=[90, 95, 50, 40])
    map_x, map_y = colmap_pinhole_maps(raw, pinhole)
    cv_x, cv_y = cv2.initUndistortRectifyMap(K, d, None, K, (100, 80), cv2.CV_32FC1)
    assert np.abs(map_x - cv_x).max() < 1e-3 and np.abs(map_y - cv_y).max() < 1e-3


@pytest.mark.parametrize("lens", ["radtan", "fisheye"])
def test_colmap_import_of_a_distorted_capture_keeps_its_lens(tmp_path, lens):
    cfg = tiny_config(frames=2, ground_truth_depth=False, spp=1, rig=RigConfig(**SMALL_RIG, distortion=lens))
    synth = write_dataset(cfg, tmp_path / "street", progress=False)
    imported = load_dataset(import_colmap(synth / "colmap", synth / "images", tmp_path / "ds"))
    _check_same_capture(load_dataset(synth), imported)
    assert imported.rig.distortion(0).model == lens


def test_colmap_full_opencv_with_rational_terms_imports_undistorted_images(synth, tmp_path):
    line = "1 PINHOLE 160 120 104.25802982729645 104.25802982729645 80 60"
    assert line in (synth / "colmap" / "cameras.txt").read_text()
    model = _copy_model(synth / "colmap", tmp_path / "model", replace={
        line: "1 FULL_OPENCV 160 120 104.25802982729645 104.25802982729645 80 60 0 0 0 0 0 0.01 0 0"})
    out = import_colmap(model, synth / "images", tmp_path / "ds")
    ds = load_dataset(out)
    raw = pycolmap.Reconstruction(model).cameras[1]
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), raw)
    assert ds.rig.distortion(0) is None and ds.rig.sizes[0] == (pinhole.width, pinhole.height)
    np.testing.assert_allclose(ds.rig.intrinsics[0, :2, 2], np.asarray(pinhole.params[2:]) - 0.5)
    assert ds.image(0, 0).shape == (ds.rig.sizes[0][1], ds.rig.sizes[0][0], 3)
    assert json.loads((out / "dataset.json").read_text())["source"]["undistorted_here"] == ["cam0"]
    assert ds.image_path(0, 1).read_bytes() == (synth / "images" / "cam1" / "000000.png").read_bytes()


def test_colmap_unknown_camera_model_is_one_clear_error(synth, tmp_path):
    model = _copy_model(synth / "colmap", tmp_path / "model", replace={"\n2 PINHOLE ": "\n2 PINHOLE_PLUS "})
    with pytest.raises(DataFormatError, match=r"cameras\.txt.*camera 2 has unknown camera model 'PINHOLE_PLUS'"):
        import_colmap(model, synth / "images", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_colmap_several_cameras_without_rig_is_refused(synth, tmp_path):
    model = _copy_model(synth / "colmap", tmp_path / "model", drop=("rigs.txt", "frames.txt"),
                        replace={f" cam{c}/": f" shots{c}_" for c in range(3)})
    with pytest.raises(DataFormatError, match="3 cameras but no rig: give the model a rig"):
        import_colmap(model, synth / "images", tmp_path / "ds")


def test_colmap_missing_or_wrongly_sized_image_names_the_file(synth, tmp_path):
    images = tmp_path / "images"
    shutil.copytree(synth / "images", images)
    (images / "cam2" / "000004.png").unlink()
    with pytest.raises(DataFormatError, match=r"cam2/000004\.png.*missing"):
        import_colmap(synth / "colmap", images, tmp_path / "ds")
    cv2.imwrite(str(images / "cam2" / "000004.png"), np.zeros((60, 80, 3), np.uint8))
    with pytest.raises(DataFormatError, match=r"cam2/000004\.png.*80x60 but COLMAP camera 3 is 160x120"):
        import_colmap(synth / "colmap", images, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


# --------------------------------------------------------------------------- levelling


def test_up_direction_of_level_and_pitched_cameras():
    from recon.importers.common import ZUP_FROM_CAMERA
    yaw = np.radians([0.0, 30.0, 120.0, 250.0])
    poses = []
    for y in yaw:  # cameras looking around the horizon, level
        T = np.eye(4)
        T[:3, :3] = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
        poses.append(T @ ZUP_FROM_CAMERA)
    np.testing.assert_allclose(up_direction(np.array(poses)), [0, 0, 1], atol=1e-12)
    # forward-looking cameras pitched 5° up along a drive: the drive's direction levels them
    pitch = np.eye(4)
    pitch[:3, :3] = cv2.Rodrigues(np.array([np.radians(5.0), 0, 0]))[0]
    forward = np.array([ZUP_FROM_CAMERA @ np.linalg.inv(pitch)] * 3)
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [2.1, 0, 0]])
    assert np.degrees(np.arccos(up_direction(forward) @ [0, 0, 1])) == pytest.approx(5.0)
    np.testing.assert_allclose(up_direction(forward, positions), [0, 0, 1], atol=1e-12)
    L = level_from_world([0, 0, 2.0], [0, 3.0, 1.0], [1, 2, 3])
    np.testing.assert_allclose(L[:3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(L @ [1, 2, 3, 1], [0, 0, 0, 1], atol=1e-12)


# --------------------------------------------------------------------------- photos


def _write_photos(folder: Path, source: Path, count: int, suffix: str = ".jpg", exif=None) -> list[Path]:
    folder.mkdir(parents=True)
    out = []
    for i, p in enumerate(sorted(source.glob("*.png"))[:count]):
        target = folder / f"IMG_{i:04d}{suffix}"
        im = PILImage.open(p)
        im.save(target, **({"exif": exif} if exif is not None else {}), **({"quality": 95} if suffix == ".jpg" else {}))
        out.append(target)
    return out


def test_photos_with_a_k_file_import_with_unknown_poses(synth, tmp_path):
    original = load_dataset(synth)
    _write_photos(tmp_path / "photos", synth / "images" / "cam0", 4)
    K = original.rig.intrinsics[0]
    (tmp_path / "K.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    out = import_photos(tmp_path / "photos", tmp_path / "ds", PhotosConfig(intrinsics=tmp_path / "K.txt",
                                                                          step_length=1.5))
    ds = load_dataset(out)
    assert ds.num_frames == 4 and ds.rig.num_cameras == 1 and ds.frame_names[0] == "IMG_0000"
    np.testing.assert_allclose(ds.rig.intrinsics[0], K)
    assert np.isnan(ds.world_from_rig).all()
    assert all(fr["world_from_rig"] is None for fr in json.loads((out / "poses.json").read_text())["frames"])
    source = json.loads((out / "dataset.json").read_text())["source"]
    assert source["poses"] == "unknown" and source["step_length"] == 1.5
    assert ds.image(0, 0).shape == (120, 160, 3)
    # the rig is the camera, level: x along its view, z up (y down in the image)
    np.testing.assert_allclose(np.linalg.inv(ds.rig.cam_from_rig[0])[:3, 2], [1, 0, 0], atol=1e-12)
    from recon.pipeline import ReconConfig, estimate_poses
    with pytest.raises(DataFormatError, match="poses unknown: use --poses sfm"):
        estimate_poses(ReconConfig(poses="given"), out, tmp_path / "work")


def test_k_file_forms(tmp_path):
    path = tmp_path / "K.txt"
    path.write_text("500 0 319.5\n0 510 239.5\n0 0 1\n-0.1 0.01 0.001 0.002\n")
    K, d = read_intrinsics(path)
    np.testing.assert_allclose(K, [[500, 0, 319.5], [0, 510, 239.5], [0, 0, 1]])
    assert d.model == "radtan" and d.coeffs == (-0.1, 0.01, 0.001, 0.002, 0.0)
    path.write_text("500 510 319.5 239.5 -0.1 0.01 0 0 0.003  # fx fy cx cy k1 k2 p1 p2 k3\n")
    K, d = read_intrinsics(path)
    assert K[1, 1] == 510 and d.coeffs == (-0.1, 0.01, 0.0, 0.0, 0.003)
    path.write_text("500 510 319.5\n")
    with pytest.raises(DataFormatError, match=r"K\.txt.*3×3 matrix"):
        read_intrinsics(path)


def test_photos_with_exif_focal_length(synth, tmp_path):
    exif = PILImage.Exif()
    exif.get_ifd(0x8769)[0xA405] = 28  # FocalLengthIn35mmFilm, mm
    _write_photos(tmp_path / "photos", synth / "images" / "cam0", 3, exif=exif)
    ds = load_dataset(import_photos(tmp_path / "photos", tmp_path / "ds"))
    f = 28 * np.hypot(160, 120) / np.hypot(36, 24)
    np.testing.assert_allclose(ds.rig.intrinsics[0], [[f, 0, 79.5], [0, f, 59.5], [0, 0, 1]])
    # FocalLength with the focal plane's resolution, or with a sensor width
    exif = PILImage.Exif()
    ifd = exif.get_ifd(0x8769)
    ifd[0x920A] = IFDRational(43, 10)  # 4.3 mm
    ifd[0xA20E] = IFDRational(8000, 1)  # pixels per cm of the sensor at its full 640 px width
    ifd[0xA210] = 3
    ifd[0xA002] = 640
    photo = _write_photos(tmp_path / "more", synth / "images" / "cam0", 1, exif=exif)[0]
    assert exif_focal_px(photo, (160, 120))[0] == pytest.approx(4.3 * 800 / 4)
    assert exif_focal_px(photo, (160, 120), sensor_width_mm=6.4)[0] == pytest.approx(4.3 * 160 / 6.4)


def test_photo_folder_with_no_focal_length_is_one_clear_error(synth, tmp_path):
    _write_photos(tmp_path / "photos", synth / "images" / "cam0", 2, suffix=".png")
    with pytest.raises(DataFormatError, match=r"photos.*no focal length: give --intrinsics"):
        import_photos(tmp_path / "photos", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_photo_exif_focal_of_zero_over_zero_is_no_focal_length(synth, tmp_path):
    """Issue 35: EXIF FocalLength 0/0 (a rational Pillow reads as NaN) ended in "Out of range
    float values are not JSON compliant: nan"; it is no focal length."""
    exif = PILImage.Exif()
    exif.get_ifd(0x8769)[0x920A] = IFDRational(0, 0)
    exif.get_ifd(0x8769)[0xA405] = IFDRational(0, 0)
    photo = _write_photos(tmp_path / "photos", synth / "images" / "cam0", 2, exif=exif)[0]
    assert exif_focal_px(photo, (160, 120), sensor_width_mm=6.4) is None
    with pytest.raises(DataFormatError, match=r"no focal length: give --intrinsics"):
        import_photos(tmp_path / "photos", tmp_path / "ds", PhotosConfig(sensor_width_mm=6.4))
    assert not (tmp_path / "ds").exists()


def test_photos_of_another_size_name_the_odd_file(synth, tmp_path):
    _write_photos(tmp_path / "photos", synth / "images" / "cam0", 3)
    PILImage.new("RGB", (120, 160)).save(tmp_path / "photos" / "IMG_0001.jpg")
    (tmp_path / "K.txt").write_text("100 100 79.5 59.5\n")
    with pytest.raises(DataFormatError, match=r"IMG_0001\.jpg.*120x160 but IMG_0000\.jpg is 160x120"):
        import_photos(tmp_path / "photos", tmp_path / "ds", PhotosConfig(intrinsics=tmp_path / "K.txt"))


def test_poses_json_holds_unknown_poses_as_null(tmp_path):
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1] = np.nan
    save_poses(tmp_path / "poses.json", poses, np.zeros(3, dtype=np.int32), names=["a", "b", "c"])
    assert json.loads((tmp_path / "poses.json").read_text())["frames"][1]["world_from_rig"] is None
    back, names = load_poses(tmp_path / "poses.json")
    assert names == ["a", "b", "c"] and np.isnan(back[1]).all() and np.array_equal(back[[0, 2]], poses[[0, 2]])


# --------------------------------------------------------------------------- KITTI


def _fake_kitti(root: Path, frames: int = 4, baseline: float = 0.537, width: int = 48, height: int = 16) -> Path:
    """A tiny KITTI odometry sequence: grey image_0/1, calib.txt (P0..P3), poses.txt driving
    1 m per frame along cam0's z (forward)."""
    rng = np.random.default_rng(0)
    f, cx, cy = 40.0, (width - 1) / 2, (height - 1) / 2
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]])
    P = [K @ np.hstack([np.eye(3), [[-b], [0], [0]]]) for b in (0.0, baseline, 0.06, baseline + 0.06)]
    root.mkdir(parents=True)
    (root / "calib.txt").write_text("".join(f"P{i}: " + " ".join(f"{v:.12e}" for v in p.ravel()) + "\n"
                                            for i, p in enumerate(P)))
    poses = [np.hstack([np.eye(3), [[0.0], [0.0], [float(i)]]]) for i in range(frames)]
    (root / "poses.txt").write_text("".join(" ".join(f"{v:.6e}" for v in T.ravel()) + "\n" for T in poses))
    for folder in ("image_0", "image_1"):
        (root / folder).mkdir()
        for i in range(frames):
            cv2.imwrite(str(root / folder / f"{i:06d}.png"), rng.integers(0, 255, (height, width), dtype=np.uint8))
    return root


def test_kitti_import_of_a_fake_sequence(tmp_path):
    seq = _fake_kitti(tmp_path / "seq")
    ds = load_dataset(import_kitti(seq, tmp_path / "ds"))
    assert ds.num_frames == 4 and ds.rig.num_cameras == 2
    centres = np.array([np.linalg.inv(T)[:3, 3] for T in ds.rig.cam_from_rig])
    assert np.linalg.norm(centres[1] - centres[0]) == pytest.approx(0.537, abs=1e-9)
    # world z is up: the car drives level along +x, the camera's image-down axis points down
    np.testing.assert_allclose(ds.world_from_rig[:, :3, 3], [[i, 0, 0] for i in range(4)], atol=1e-6)
    np.testing.assert_allclose(ds.world_from_cam(2, 0)[:3, 1], [0, 0, -1], atol=1e-9)
    assert ds.world_from_cam(0, 0)[2, 3] == pytest.approx(1.65)  # cam0 above the road
    assert ds.image(0, 0).shape == (16, 48, 3)


def test_kitti_colour_pair_on_a_turning_drive_keeps_cam0s_poses(tmp_path):
    """poses.txt holds cam0's poses whichever pair is imported: the colour cameras (P2, P3,
    offset from cam0) must sit where cam0's pose and P2's translation put them, also in a turn."""
    seq = _fake_kitti(tmp_path / "seq")
    yaw = np.radians([0.0, 30.0, 60.0, 90.0])  # turning about cam0's y (down) axis while driving
    poses = []
    for i, a in enumerate(yaw):
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        poses.append(np.hstack([R, [[2.0 * i], [0.0], [3.0 * i]]]))
    (seq / "poses.txt").write_text("".join(" ".join(f"{v:.9e}" for v in T.ravel()) + "\n" for T in poses))
    for left, right in (("image_0", "image_2"), ("image_1", "image_3")):
        (seq / left).rename(seq / right)
    ds = load_dataset(import_kitti(seq, tmp_path / "ds"))  # auto: the colour pair
    assert ds.rig.num_cameras == 2
    # cam2 sits 0.06 m to the right of cam0 (P2 = K [I | (−0.06, 0, 0)]); cam0 of frame 0 is the world's reference
    from recon.importers.kitti import rig_from_cam0

    to_rig = rig_from_cam0(1.65)
    for f, T in enumerate(poses):
        world_from_cam0 = to_rig @ np.vstack([T, [0, 0, 0, 1]])
        expected = world_from_cam0 @ np.array([0.06, 0.0, 0.0, 1.0])
        np.testing.assert_allclose(ds.world_from_cam(f, 0)[:3, 3], expected[:3], atol=1e-6)
        np.testing.assert_allclose(ds.world_from_cam(f, 0)[:3, :3], world_from_cam0[:3, :3], atol=1e-6)


def test_kitti_calib_with_the_wrong_line_count_is_one_clear_error(tmp_path):
    seq = _fake_kitti(tmp_path / "seq")
    lines = (seq / "calib.txt").read_text().splitlines()
    (seq / "calib.txt").write_text("\n".join(line.split(": ", 1)[1] for line in lines[:3]) + "\n")
    with pytest.raises(DataFormatError, match=r"calib\.txt.*has 3 lines; expected 2 \(P0, P1\) or 4"):
        import_kitti(seq, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_kitti_poses_and_images_of_different_lengths_is_one_clear_error(tmp_path):
    seq = _fake_kitti(tmp_path / "seq")
    (seq / "image_1" / "000003.png").unlink()
    (seq / "image_0" / "000003.png").unlink()
    with pytest.raises(DataFormatError, match=r"poses\.txt.*has 4 poses but image_0/ has 3 images"):
        import_kitti(seq, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_kitti_calib_that_is_no_lens_is_refused_before_writing(tmp_path):
    """fx 5e6 px on a 48-px image (a field of view of 0.0006°): the import used to write a dataset
    that check and every stage refuse."""
    seq = _fake_kitti(tmp_path / "seq")
    lines = (seq / "calib.txt").read_text().splitlines()
    for i in (0, 1):
        head, values = lines[i].split(": ")
        v = [float(x) for x in values.split()]
        v[0] *= 5e6 / 40.0
        v[3] *= 5e6 / 40.0  # P[0, 3] = −fx·b: the baseline stays
        lines[i] = f"{head}: " + " ".join(f"{x:.12e}" for x in v)
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"refused by the dataset format.*fx 5e\+06 px is not a lens's"):
        import_kitti(seq, tmp_path / "ds")
    assert not (tmp_path / "ds").exists() and not list(tmp_path.glob(".ds*"))


def test_kitti_gap_in_the_numbering_is_one_clear_error(tmp_path):
    """000002 missing, 000004 present (as many images as poses): 000003 would silently take pose
    line 3; line i of poses.txt is frame i, so the names must run 0, 1, 2 …"""
    seq = _fake_kitti(tmp_path / "seq", frames=4)
    for folder in ("image_0", "image_1"):
        (seq / folder / "000002.png").rename(seq / folder / "000004.png")
    with pytest.raises(DataFormatError, match=r"000003\.png: is image 2 of image_0/.*frame 2 000002"):
        import_kitti(seq, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


@pytest.mark.skipif(not KITTI06.is_dir(), reason="../shared/data/kitti06 is not here")
def test_kitti06_imports(tmp_path):
    ds = load_dataset(import_kitti(KITTI06, tmp_path / "ds", KittiConfig(count=6)))
    assert ds.num_frames == 6 and ds.rig.sizes[0] == (1226, 370)
    centres = np.array([np.linalg.inv(T)[:3, 3] for T in ds.rig.cam_from_rig])
    assert np.linalg.norm(centres[1] - centres[0]) == pytest.approx(0.537, abs=1e-3)
    drive = ds.world_from_rig[-1, :3, 3] - ds.world_from_rig[0, :3, 3]
    assert np.linalg.norm(drive) > 3.0 and abs(drive[2]) < 0.05 * np.linalg.norm(drive)  # a level street
    assert ds.world_from_cam(0, 0)[:3, 1] @ [0, 0, -1] > 0.99  # image down is world down


# --------------------------------------------------------------------------- SfM without poses


@pytest.fixture(scope="module")
def one_camera_street(tmp_path_factory):
    """One level camera looking at the facades: a 21 m pass, 16 frames 1.4 m apart (motion stereo's
    baselines), 480×360 (at 320×240 one camera's SfM registers few points and drifts by degrees)."""
    cfg = tiny_config(frames=16, return_pass=False, street=StreetConfig(length=21.0, seed=0), ground_truth_depth=False,
                      spp=1, rig=RigConfig(width=480, height=360, hfov_deg=75.0, pitch_deg=0.0, baselines=(0.0,)))
    return write_dataset(cfg, tmp_path_factory.mktemp("one") / "street", progress=False)


def _import_as_photos(street: Path, tmp_path: Path, step: float) -> Path:
    original = load_dataset(street)
    K = original.rig.intrinsics[0]
    (tmp_path / "K.txt").write_text("\n".join(" ".join(repr(float(v)) for v in row) for row in K) + "\n")
    return import_photos(street / "images" / "cam0", tmp_path / "photos_ds",
                         PhotosConfig(intrinsics=tmp_path / "K.txt", step_length=step))


@pytest.mark.slow
def test_sfm_of_photos_with_unknown_poses_is_level_and_step_scaled(one_camera_street, tmp_path):
    from recon.sfm import SfmConfig, poses_sfm
    original = load_dataset(one_camera_street)
    ds = load_dataset(_import_as_photos(one_camera_street, tmp_path, step=1.4))
    res = poses_sfm(ds, tmp_path / "sfm", SfmConfig(num_threads=1), progress=False)
    assert res.num_registered == ds.num_frames
    cams = np.array([ds.rig.world_from_cam(T, 0) for T in res.world_from_rig])
    truth = _camera_poses(original)
    steps = np.linalg.norm(np.diff(res.world_from_rig[:, :3, 3], axis=0), axis=1)
    assert np.median(steps) == pytest.approx(1.4, rel=1e-6)  # the step length sets the scale
    # origin and heading (+x) from frame 0's rig
    np.testing.assert_allclose(res.world_from_rig[0, :3, 3], 0.0, atol=1e-9)
    assert abs(res.world_from_rig[0, 1, 0]) < 1e-9 and res.world_from_rig[0, 0, 0] > 0.99
    aligned, T, s = align_trajectory(cams, truth, with_scale=True)
    assert s == pytest.approx(1.0, abs=0.01)  # frames really are 1.4 m apart
    assert np.abs(aligned[:, :3, 3] - truth[:, :3, 3]).max() < 0.05
    assert np.degrees(np.arccos(np.clip(T[:3, 2] @ [0, 0, 1] / s, -1, 1))) < 1.0  # the world's z is up
    assert res.scale_from == ["step_length"]
    # the depths of the sparse points each frame sees: near < median < far, the facades' metres
    from recon.colmap_poses import frame_depths, read_reconstruction
    rec = read_reconstruction(res.model_dirs[0])
    d = frame_depths(rec, ds)
    assert np.isfinite(d).all() and (d[:, 0] < d[:, 1]).all() and (d[:, 1] < d[:, 2]).all()
    assert 4.0 < np.median(d[:, 1]) < 15.0
    # against a plain loop over each image's observations
    for image in rec.images.values():
        X = np.array([rec.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()])
        z = X @ image.cam_from_world().matrix()[2, :3] + image.cam_from_world().matrix()[2, 3]
        f = list(ds.frame_names).index(Path(image.name).stem)
        np.testing.assert_allclose(d[f], np.quantile(z[z > 0], (0.02, 0.5, 0.98)), rtol=1e-12)


@pytest.mark.slow
def test_cli_import_photos_then_recon_with_sfm(one_camera_street, tmp_path):
    from bbcity.cli import main
    original = load_dataset(one_camera_street)
    K = original.rig.intrinsics[0]
    (tmp_path / "K.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    assert main(["-q", "import", "photos", str(one_camera_street / "images" / "cam0"), "--out",
                 str(tmp_path / "ds"), "--intrinsics", str(tmp_path / "K.txt"), "--step-length", "1.4"]) == 0
    assert main(["-q", "recon", str(tmp_path / "ds"), "--out", str(tmp_path / "work"), "--poses", "given"]) == 2
    assert main(["-q", "recon", str(tmp_path / "ds"), "--out", str(tmp_path / "work"), "--poses", "sfm",
                 "--preset", "fast", "--workers", "1"]) == 0
    report = json.loads((tmp_path / "work" / "recon_report.json").read_text())
    assert report["poses"]["source"] == "sfm" and report["poses"]["registered_frames"] == 16
    assert report["points"] > 1000
    assert report["poses"]["scale_from"] == ["step_length"]
    # photos larger than the working size: stereo and SIFT at 240 px, the cloud still there
    assert main(["-q", "recon", str(tmp_path / "ds"), "--out", str(tmp_path / "small"), "--poses", "sfm",
                 "--preset", "fast", "--workers", "1", "--max-image-size", "240"]) == 0
    small = json.loads((tmp_path / "small" / "recon_report.json").read_text())
    assert small["config"]["max_image_size"] == 240 and 0.1 * report["points"] < small["points"] < report["points"]


@pytest.mark.slow
def test_stereo_that_cannot_fit_in_memory_is_one_clear_error_from_a_worker(one_camera_street, tmp_path):
    from dataclasses import replace

    from bbcity.executor import executor_scope
    from recon.pipeline import ReconConfig, main as recon_main
    from recon.stereo import StereoMemoryError

    conf = ReconConfig(evaluate=False)
    conf = replace(conf, trinocular=replace(conf.trinocular, stereo=replace(conf.trinocular.stereo,
                                                                            memory_budget=1000.0)))
    with pytest.raises(StereoMemoryError, match=r"^not enough memory for stereo: a 480x360 pair searching \d+ "
                                                r"disparities at \d+x\d+ needs [\d.]+ GB, its budget is 0.0 GB"):
        with executor_scope(1) as executor:
            recon_main(conf, one_camera_street, tmp_path / "work", executor=executor, progress=False)
    assert not (tmp_path / "work" / "cloud.ply").exists() and not (tmp_path / "work" / "recon_report.json").exists()


@pytest.mark.parametrize("baseline", [-0.537, 1e6, 0.0])
def test_kitti_calib_whose_pair_is_no_car_rig_is_one_clear_error(tmp_path, baseline):
    """A right camera to the left of the left one (a sign slip), or absurdly far or near."""
    seq = _fake_kitti(tmp_path / "seq", baseline=baseline)
    with pytest.raises(DataFormatError, match=r"calib\.txt: P1 is not 0\.01–10 m to the right of P0"):
        import_kitti(seq, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_kitti_pose_at_an_absurd_position_is_one_clear_error(tmp_path):
    seq = _fake_kitti(tmp_path / "seq")
    lines = (seq / "poses.txt").read_text().splitlines()
    values = lines[2].split()
    values[3] = "1e308"
    lines[2] = " ".join(values)
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=r"poses\.txt: line 3: a position beyond 1e\+07 m"):
        import_kitti(seq, tmp_path / "ds")


def test_sfm_scale_from_step_length_gps_or_nothing():
    from recon.capture_scale import CaptureScale, scale_factor
    rng = np.random.default_rng(4)
    truth = np.cumsum(rng.uniform([2.0, -0.5, -0.1], [4.0, 0.5, 0.1], (12, 3)), axis=0)  # a walk, 2–4 m a step
    sfm = truth / 7.3  # SfM's arbitrary units
    ok = np.arange(12)
    # the step length: consecutive frames' median distance becomes it
    f, kind = scale_factor(CaptureScale("step_length", step=3.0), sfm, ok)
    steps = np.linalg.norm(np.diff(sfm * f, axis=0), axis=1)
    assert kind == "step_length" and np.median(steps) == pytest.approx(3.0)
    # GPS with 3 m of noise: frames ≥ 20 m apart give the scale within a few percent
    gps = truth + rng.normal(0, 3.0, truth.shape)
    f, kind = scale_factor(CaptureScale("gps", gps=gps), sfm, ok)
    assert kind == "gps" and f == pytest.approx(7.3, rel=0.05)
    # frames left out of the model (not registered) are left out of the GPS fit too
    f2, _ = scale_factor(CaptureScale("gps", gps=gps), sfm[::2], ok[::2])
    assert f2 == pytest.approx(7.3, rel=0.08)
    # GPS spanning less than 20 m says nothing: arbitrary units, 1 between consecutive frames
    f, kind = scale_factor(CaptureScale("gps", gps=gps[:4] * 0.1), sfm[:4], ok[:4])
    assert kind == "arbitrary" and np.median(np.linalg.norm(np.diff(sfm[:4] * f, axis=0), axis=1)) == pytest.approx(1)
    # a long video's frames: the scale from 500 of them, evenly spread
    long_truth = np.cumsum(rng.uniform([0.5, -0.2, -0.05], [1.5, 0.2, 0.05], (1500, 3)), axis=0)
    f, kind = scale_factor(CaptureScale("gps", gps=long_truth + rng.normal(0, 3.0, long_truth.shape)),
                           long_truth / 2.0, np.arange(1500))
    assert kind == "gps" and f == pytest.approx(2.0, rel=0.02)
    f, kind = scale_factor(CaptureScale("arbitrary"), sfm, ok)
    assert kind == "arbitrary" and np.median(np.linalg.norm(np.diff(sfm * f, axis=0), axis=1)) == pytest.approx(1)
