"""A folder of photos of one camera → a dataset with unknown poses (``bbcity import photos``).

The photos (JPEG or PNG, all the same size, taken in file-name order) become the frames
of a one-camera rig. Their poses are unknown: ``poses.json`` gives ``"world_from_rig":
null`` for every frame and ``bbcity recon DATASET --poses sfm`` computes them.

Intrinsics, first found of:

1. ``--intrinsics K.txt``: a 3×3 matrix as three lines of three numbers, or one line
   ``fx fy cx cy``; optionally followed (on its own line, or at the end of the
   ``fx fy cx cy`` line) by radtan coefficients ``k1 k2 p1 p2 [k3]``. OpenCV's pixel
   convention: the centre of the top-left pixel is (0, 0).
2. EXIF: ``FocalLengthIn35mmFilm`` (f_px = f35 · image diagonal / 43.27 mm, the 35 mm
   frame's diagonal), else ``FocalLength`` (mm) with ``--sensor-width`` (mm), else
   ``FocalLength`` with ``FocalPlaneXResolution`` (pixels per unit of
   ``FocalPlaneResolutionUnit`` at ``PixelXDimension``). The principal point is the image
   centre, pixels are square, there is no distortion. Every photo's EXIF must agree
   (a zoom lens that moved is refused, naming the photo).

Orientation: a photo's EXIF orientation tag (a phone held upright writes its pixels
sideways and tag 6) is applied: the dataset holds the upright image, re-encoded as PNG.
Sizes are compared, and the principal point of an EXIF focal length put at the centre, of
the upright images; the focal length in pixels does not change with a quarter turn (it
comes from the image diagonal or the sensor's pixel pitch, and pixels are square). A K file
describes the upright images (its cx is along their width).

Scale: one moving camera has none. ``--step-length`` gives the metres between consecutive
photos (``dataset.json`` "source" "step_length"; null when not given). When every photo
carries an EXIF GPS position, "source" "gps_enu_m" holds them as [east, north, up] metres
about the first photo (:mod:`.gps`; up is 0 for all when any photo lacks an altitude, then
"gps_altitude" is false); else it is null. SfM takes its scale from the step length when
given, else from the GPS positions, else it stays in arbitrary units: stereo depth ranges
are in metres, so give the real spacing when it is known (a walk: about 1 m between photos;
a car: its speed ÷ the frame rate). The rig frame has its origin at the camera, x along
the viewing direction, z up (the camera is taken to be level; SfM estimates the world's up
from all the photos).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image as PILImage

from capture.distortion import Distortion
from capture.rig import Rig
from core.errors import InputError
from core.fileio import DataFormatError

from .common import ZUP_FROM_CAMERA, exif_orientation, write_imported_dataset
from .gps import enu_from_geodetic, exif_gps

logger = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))  # the 35 mm film frame, for FocalLengthIn35mmFilm

# EXIF tags (the Exif sub-IFD, 0x8769, holds them; some writers put them in IFD0)
EXIF_IFD = 0x8769
TAG_FOCAL_LENGTH = 0x920A
TAG_FOCAL_35MM = 0xA405
TAG_FOCAL_PLANE_X_RES = 0xA20E
TAG_FOCAL_PLANE_UNIT = 0xA210
TAG_PIXEL_X_DIMENSION = 0xA002
#: EXIF orientations (:func:`.common.exif_orientation`) whose upright image is the stored one
#: turned a quarter (width ↔ height).
QUARTER_TURNS = (5, 6, 7, 8)
#: FocalPlaneResolutionUnit → millimetres per unit (EXIF: 2 inch, the default; 3 cm; 4 mm; 5 µm).
FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
#: Photos whose EXIF focal lengths differ by more than this (relative) are refused.
FOCAL_AGREEMENT = 1e-3


@dataclass(frozen=True)
class PhotosConfig:
    intrinsics: Path | None = None  # K file (see the module doc); None: from EXIF
    sensor_width_mm: float | None = None  # sensor width, with EXIF FocalLength when there is no 35 mm equivalent
    step_length: float | None = None  # metres between consecutive photos, SfM's scale; None: GPS or none (module doc)

    def __post_init__(self):
        if self.step_length is not None and not (np.isfinite(self.step_length) and self.step_length > 0):
            raise InputError(f"step_length must be a positive number of metres, got {self.step_length}")
        if self.sensor_width_mm is not None and not (np.isfinite(self.sensor_width_mm) and self.sensor_width_mm > 0):
            raise InputError(f"sensor_width_mm must be a positive width, got {self.sensor_width_mm}")


def read_intrinsics(path: Path) -> tuple[np.ndarray, Distortion | None]:
    """A K file (see the module doc) → K (3, 3) float64 and a radtan lens or None."""
    if not path.is_file():
        raise DataFormatError(path, "intrinsics file is missing")
    rows = []
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise DataFormatError(path, f"line {i} is not a row of numbers") from None
        if not all(np.isfinite(values)):
            raise DataFormatError(path, f"line {i} has non-finite numbers")
        rows.append(values)
    lengths = [len(r) for r in rows]
    coeffs: list[float] = []
    if lengths[:3] == [3, 3, 3]:
        K = np.array(rows[:3])
        rest = rows[3:]
    elif lengths[:1] and lengths[0] in (4, 8, 9):
        fx, fy, cx, cy = rows[0][:4]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        coeffs = rows[0][4:]
        rest = rows[1:]
    else:
        raise DataFormatError(path, "expected a 3×3 matrix (three lines of three numbers) or a line "
                                    "\"fx fy cx cy\"")
    if rest and not coeffs and len(rest) == 1 and len(rest[0]) in (4, 5):
        coeffs = rest[0]
    elif rest:
        raise DataFormatError(path, "after the intrinsics only one line of radtan coefficients "
                                    "\"k1 k2 p1 p2 [k3]\" may follow")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or K[1, 0] != 0 or K[0, 1] != 0:
        raise DataFormatError(path, "K must have positive focal lengths, no skew and last row 0 0 1")
    if not coeffs or not any(coeffs):
        return K, None
    try:
        return K, Distortion("radtan", tuple(coeffs) + (0.0,) * (5 - len(coeffs)))
    except ValueError as e:
        raise DataFormatError(path, str(e)) from None


def _exif_value(exif, tag: int):
    value = exif.get_ifd(EXIF_IFD).get(tag)
    if value is None:
        value = exif.get(tag)
    try:
        number = None if value is None else float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if number is not None and np.isfinite(number) else None  # a rational 0/0 reads as NaN


def exif_focal_px(path: Path, size: tuple[int, int], sensor_width_mm: float | None = None
                  ) -> tuple[float, str] | None:
    """The focal length in pixels from a photo's EXIF and how it was found, or None.

    size: (width, height) of the image as stored (before its EXIF orientation is applied:
    FocalPlaneXResolution and PixelXDimension count along the stored width). The focal
    length is that of the upright image too (square pixels).
    """
    try:
        with PILImage.open(path) as im:
            exif = im.getexif()
    except Exception as e:  # Pillow raises many kinds for broken files
        raise DataFormatError(path, f"photo could not be read ({e})") from None
    w, h = size
    f35 = _exif_value(exif, TAG_FOCAL_35MM)
    if f35 and f35 > 0:
        return f35 * float(np.hypot(w, h)) / FULL_FRAME_DIAGONAL_MM, "exif FocalLengthIn35mmFilm"
    f_mm = _exif_value(exif, TAG_FOCAL_LENGTH)
    if not f_mm or f_mm <= 0:
        return None
    if sensor_width_mm:
        return f_mm * max(w, h) / sensor_width_mm, "exif FocalLength and --sensor-width"
    res = _exif_value(exif, TAG_FOCAL_PLANE_X_RES)
    unit = FOCAL_PLANE_UNIT_MM.get(int(_exif_value(exif, TAG_FOCAL_PLANE_UNIT) or 2))
    if res and res > 0 and unit:
        # the resolution is that of the sensor's full image: rescale to a downsized photo
        full_width = _exif_value(exif, TAG_PIXEL_X_DIMENSION)
        ratio = w / full_width if full_width and full_width > 0 else 1.0
        return f_mm * res / unit * ratio, "exif FocalLength and FocalPlaneXResolution"
    return None


def list_photos(folder: Path) -> list[Path]:
    """The photos of ``folder`` (JPEG, PNG) in file-name order; errors name the folder."""
    if not folder.is_dir():
        raise DataFormatError(folder, "photo folder does not exist")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if not photos:
        raise DataFormatError(folder, "holds no photos (.jpg, .jpeg, .png)")
    stems = [p.stem for p in photos]
    if len(set(stems)) != len(stems):
        twice = next(s for s in stems if stems.count(s) > 1)
        raise DataFormatError(folder, f"two photos are named {twice!r} (with different extensions)")
    return photos


def photo_header(path: Path) -> tuple[tuple[int, int], int]:
    """(width, height) of a photo as stored and its EXIF orientation (1: as stored)."""
    try:
        with PILImage.open(path) as im:
            size = im.size
    except Exception as e:  # Pillow raises many kinds for broken files
        raise DataFormatError(path, f"photo could not be read ({e})") from None
    return size, exif_orientation(path)


def photo_size(path: Path) -> tuple[int, int]:
    """(width, height) of the upright photo (its EXIF orientation applied)."""
    (w, h), orientation = photo_header(path)
    return (h, w) if orientation in QUARTER_TURNS else (w, h)


def gps_positions(photos: list[Path]) -> tuple[np.ndarray, bool] | None:
    """(n, 3) float64 [east, north, up] metres of each photo's EXIF GPS position about the
    first photo's, and whether the altitudes were known (else up is 0); None unless every
    photo has a position."""
    found = [exif_gps(p) for p in photos]
    if any(g is None for g in found):
        have = sum(g is not None for g in found)
        if have:
            logger.warning("%d of %d photos have an EXIF GPS position: none is used", have, len(photos))
        return None
    with_altitude = all(g[2] is not None for g in found)
    lla = np.array([[lat, lon, alt if with_altitude else 0.0] for lat, lon, alt in found], dtype=np.float64)
    enu = enu_from_geodetic(lla, lla[0])
    if not with_altitude:
        enu[:, 2] = 0.0
    return enu, with_altitude


def unposed_rig(K: np.ndarray, distortion: Distortion | None, size: tuple[int, int], where: Path) -> Rig:
    """The one-camera rig of a capture whose poses are unknown: the camera K (3, 3) float64
    with its lens at ``size``, the rig frame its own turned to the project's axes (x along
    the view, z up: see the module doc). ``where`` is named when the lens cannot be undistorted."""
    try:
        return Rig.from_raw(K[None], [size], np.linalg.inv(ZUP_FROM_CAMERA)[None], [distortion])
    except ValueError as e:  # a lens that leaves no pinhole image inside the raw one
        raise DataFormatError(where, f"cannot undistort the camera ({e})") from None


def import_photos(folder: os.PathLike | str, out_dir: os.PathLike | str, config: PhotosConfig = PhotosConfig(),
                  progress=None) -> Path:
    """Import a folder of one camera's photos into the dataset directory ``out_dir`` (new);
    its poses are unknown (``bbcity recon --poses sfm``)."""
    root, out = Path(folder), Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    photos = list_photos(root)
    headers = [photo_header(p) for p in photos]
    sizes = [(h, w) if o in QUARTER_TURNS else (w, h) for (w, h), o in headers]
    size = sizes[0]
    for p, got in zip(photos[1:], sizes[1:]):
        if got != size:
            raise DataFormatError(p, f"photo is {got[0]}x{got[1]} but {photos[0].name} is {size[0]}x{size[1]} "
                                     "(upright); all photos must come from one camera at one size")
    if config.intrinsics is not None:
        K, distortion = read_intrinsics(Path(config.intrinsics))
        how = f"file {Path(config.intrinsics).resolve()}"
    else:
        found = [exif_focal_px(p, stored, config.sensor_width_mm) for p, (stored, _) in zip(photos, headers)]
        if found[0] is None:
            raise DataFormatError(root, "no focal length: give --intrinsics (no EXIF FocalLengthIn35mmFilm, or "
                                        "FocalLength with --sensor-width or FocalPlaneXResolution, in "
                                        f"{photos[0].name})")
        f, how = found[0]
        for p, other in zip(photos[1:], found[1:]):
            if other is None or abs(other[0] - f) > FOCAL_AGREEMENT * f:
                what = "no EXIF focal length" if other is None else f"focal length {other[0]:.1f} px"
                raise DataFormatError(p, f"has {what} but {photos[0].name} has {f:.1f} px; the photos must "
                                         "share one camera (or give --intrinsics)")
        w, h = size
        K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
        distortion = None
    rig = unposed_rig(K, distortion, size, Path(config.intrinsics or root))
    gps = gps_positions(photos)
    poses = np.full((len(photos), 4, 4), np.nan)  # unknown: poses.json says null, SfM finds them
    turned = [p for p, (_, o) in zip(photos, headers) if o != 1]
    source = {"kind": "photos", "path": str(root.resolve()), "intrinsics": how, "poses": "unknown",
              "step_length": None if config.step_length is None else float(config.step_length),
              "gps_enu_m": None if gps is None else gps[0].tolist(),
              "gps_altitude": None if gps is None else gps[1],
              "exif_oriented": len(turned)}
    logger.info("%d photos of %dx%d pixels, focal %.1f px (%s)%s%s", len(photos), size[0], size[1], K[0, 0], how,
                f", {len(turned)} turned upright by their EXIF orientation" if turned else "",
                ", with GPS positions" if gps is not None else "")
    return write_imported_dataset(out, rig, poses, [[p] for p in photos], source, names=[p.stem for p in photos],
                                  progress=progress, upright=True)
