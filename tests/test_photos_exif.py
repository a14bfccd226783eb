"""The photos importer's EXIF: orientation (stored upright) and GPS positions (local metres)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image as PILImage
from PIL.TiffImagePlugin import IFDRational

from core import DataFormatError
from capture import load_dataset
from recon.importers.gps import WGS84_A, WGS84_E2, enu_from_geodetic, exif_gps
from recon.importers.photos import PhotosConfig, import_photos, photo_size

#: A stored (landscape) photo whose EXIF says: turn it 90° clockwise to view it (a phone held upright).
STORED_W, STORED_H = 48, 32


def _pattern() -> np.ndarray:
    """(32, 48, 3) uint8: a left-to-right ramp with a bright top-left corner, so a turn shows."""
    image = np.zeros((STORED_H, STORED_W, 3), np.uint8)
    image[..., 0] = np.linspace(0, 250, STORED_W, dtype=np.uint8)[None, :]
    image[:8, :8] = 255
    return image


def _dms(value: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    d = int(value)
    m = int((value - d) * 60)
    s = (value - d - m / 60) * 3600
    return IFDRational(d, 1), IFDRational(m, 1), IFDRational(round(s * 1e6), 1_000_000)


def _photo(path: Path, orientation: int | None = None, gps: tuple[float, float, float | None] | None = None,
           quality: int = 100) -> Path:
    exif = PILImage.Exif()
    exif.get_ifd(0x8769)[0xA405] = 28  # FocalLengthIn35mmFilm: an EXIF focal length
    if orientation is not None:
        exif[0x0112] = orientation
    if gps is not None:
        lat, lon, alt = gps
        g = exif.get_ifd(0x8825)
        g[1], g[2] = ("N" if lat >= 0 else "S"), _dms(abs(lat))
        g[3], g[4] = ("E" if lon >= 0 else "W"), _dms(abs(lon))
        if alt is not None:
            g[5], g[6] = (b"\x00" if alt >= 0 else b"\x01"), IFDRational(round(abs(alt) * 1000), 1000)
    PILImage.fromarray(_pattern()).save(path, exif=exif, quality=quality, subsampling=0)
    return path


def test_a_turned_phone_photo_is_stored_upright(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(2):
        _photo(folder / f"IMG_{i}.jpg", orientation=6)
    assert photo_size(folder / "IMG_0.jpg") == (STORED_H, STORED_W)
    out = import_photos(folder, tmp_path / "ds", PhotosConfig())
    ds = load_dataset(out)
    assert ds.rig.sizes[0] == (STORED_H, STORED_W)  # upright: portrait
    image = ds.image(0, 0)
    assert image.shape == (STORED_W, STORED_H, 3)
    # orientation 6: the stored image turned 90° clockwise; the bright corner goes top-right
    upright = np.rot90(_pattern(), k=-1)
    assert np.abs(image.astype(int) - upright).mean() < 4
    assert image[:8, -8:].mean() > 200 and image[:8, :8].mean() < 100
    # the EXIF focal length is the same in pixels (the diagonal), the principal point the upright centre
    f = 28 * np.hypot(STORED_W, STORED_H) / np.hypot(36, 24)
    np.testing.assert_allclose(ds.rig.intrinsics[0], [[f, 0, (STORED_H - 1) / 2], [0, f, (STORED_W - 1) / 2],
                                                      [0, 0, 1]])
    source = json.loads((out / "dataset.json").read_text())["source"]
    assert source["exif_oriented"] == 2 and source["step_length"] is None and source["gps_enu_m"] is None


def test_upright_and_turned_photos_of_one_camera_agree(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    _photo(folder / "IMG_0.jpg", orientation=1)
    _photo(folder / "IMG_1.jpg", orientation=6)
    with pytest.raises(DataFormatError, match=r"IMG_1\.jpg: photo is 32x48 but IMG_0\.jpg is 48x32 \(upright\)"):
        import_photos(folder, tmp_path / "ds")


def test_gps_positions_become_local_metres(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    lat, lon = 48.137154, 11.576124
    # 10 m north along the meridian: its radius of curvature there
    meridian = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * np.sin(np.radians(lat)) ** 2) ** 1.5
    _photo(folder / "IMG_0.jpg", gps=(lat, lon, 520.0))
    _photo(folder / "IMG_1.jpg", gps=(lat + np.degrees(10.0 / meridian), lon, 520.0))
    assert exif_gps(folder / "IMG_0.jpg") == pytest.approx((lat, lon, 520.0), abs=1e-9)
    out = import_photos(folder, tmp_path / "ds", PhotosConfig(step_length=1.2))
    source = json.loads((out / "dataset.json").read_text())["source"]
    enu = np.array(source["gps_enu_m"])
    assert enu.shape == (2, 3) and source["gps_altitude"] is True and source["step_length"] == 1.2
    np.testing.assert_allclose(enu[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(enu[1], [0.0, 10.0, 0.0], atol=1e-3)


def test_gps_without_altitude_or_on_some_photos_only(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    _photo(folder / "IMG_0.jpg", gps=(-33.8688, 151.2093, None))
    _photo(folder / "IMG_1.jpg", gps=(-33.8688, 151.2094, None))  # 0.0001° east, southern hemisphere
    source = json.loads((import_photos(folder, tmp_path / "a") / "dataset.json").read_text())["source"]
    enu = np.array(source["gps_enu_m"])
    assert source["gps_altitude"] is False and enu[1, 2] == 0.0
    assert enu[1, 0] == pytest.approx(np.radians(1e-4) * 6378137.0 * np.cos(np.radians(33.8688)), rel=2e-3)
    _photo(folder / "IMG_2.jpg")  # no GPS: none is used
    source = json.loads((import_photos(folder, tmp_path / "b") / "dataset.json").read_text())["source"]
    assert source["gps_enu_m"] is None and source["gps_altitude"] is None


def test_enu_of_known_points():
    origin = np.array([45.0, 7.0, 100.0])
    np.testing.assert_allclose(enu_from_geodetic(origin[None], origin), [[0, 0, 0]], atol=1e-9)
    up = enu_from_geodetic(np.array([[45.0, 7.0, 150.0]]), origin)
    np.testing.assert_allclose(up, [[0, 0, 50.0]], atol=1e-6)
