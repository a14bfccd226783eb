"""A photo's EXIF GPS position, and GPS positions as local metres (east, north, up).

EXIF keeps the position in the GPS IFD (tag 0x8825): latitude and longitude as degrees,
minutes and seconds with a hemisphere reference ("N"/"S", "E"/"W"), the altitude in metres
with a reference (0: above sea level, 1: below). :func:`enu_from_geodetic` turns WGS84
positions into a local tangent plane about an origin (exact through Earth-centred
coordinates, float64: millimetres over a street's kilometres).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image as PILImage

from core.fileio import DataFormatError

GPS_IFD = 0x8825
TAG_LATITUDE_REF, TAG_LATITUDE = 1, 2
TAG_LONGITUDE_REF, TAG_LONGITUDE = 3, 4
TAG_ALTITUDE_REF, TAG_ALTITUDE = 5, 6

#: WGS84 ellipsoid: semi-major axis (m) and first eccentricity squared.
WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3


def _degrees(value, ref, negative: str) -> float | None:
    """EXIF (degrees, minutes, seconds) and its reference → signed decimal degrees, or None."""
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    if isinstance(ref, bytes):
        ref = ref.decode(errors="replace")
    out = d + m / 60.0 + s / 3600.0
    if not math.isfinite(out):
        return None
    return -out if str(ref).strip().upper() == negative else out


def exif_gps(path: Path) -> tuple[float, float, float | None] | None:
    """(latitude °, longitude °, altitude m or None) from a photo's EXIF GPS tags, or None
    when it has no (readable) position. Latitude north and longitude east are positive."""
    try:
        with PILImage.open(path) as im:
            gps = im.getexif().get_ifd(GPS_IFD)
    except Exception as e:  # Pillow raises many kinds for broken files
        raise DataFormatError(path, f"photo could not be read ({e})") from None
    if TAG_LATITUDE not in gps or TAG_LONGITUDE not in gps:
        return None
    lat = _degrees(gps[TAG_LATITUDE], gps.get(TAG_LATITUDE_REF, "N"), "S")
    lon = _degrees(gps[TAG_LONGITUDE], gps.get(TAG_LONGITUDE_REF, "E"), "W")
    if lat is None or lon is None or abs(lat) > 90.0 or abs(lon) > 180.0:
        return None
    alt = None
    if TAG_ALTITUDE in gps:
        try:
            alt = float(gps[TAG_ALTITUDE])
        except (TypeError, ValueError, ZeroDivisionError):
            alt = None
        ref = gps.get(TAG_ALTITUDE_REF, 0)
        below = ref[:1] == b"\x01" if isinstance(ref, bytes) else ref == 1
        if alt is not None:
            alt = -alt if below else alt
            alt = alt if math.isfinite(alt) else None
    return lat, lon, alt


def ecef_from_geodetic(lat_lon_alt: np.ndarray) -> np.ndarray:
    """(n, 3) float64 latitude °, longitude °, height m (WGS84) → (n, 3) Earth-centred,
    Earth-fixed metres."""
    p = np.asarray(lat_lon_alt, dtype=np.float64).reshape(-1, 3)
    lat, lon, h = np.radians(p[:, 0]), np.radians(p[:, 1]), p[:, 2]
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - WGS84_E2) + h) * np.sin(lat)], axis=1)


def enu_from_geodetic(lat_lon_alt: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(n, 3) float64 latitude °, longitude °, height m → (n, 3) float64 metres east, north
    and up in the plane tangent to the ellipsoid at ``origin`` (3,) (same units)."""
    origin = np.asarray(origin, dtype=np.float64)
    lat, lon = np.radians(origin[0]), np.radians(origin[1])
    R = np.array([[-np.sin(lon), np.cos(lon), 0.0],
                  [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
                  [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]])
    return (ecef_from_geodetic(lat_lon_alt) - ecef_from_geodetic(origin)) @ R.T
