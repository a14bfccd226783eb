"""The camera rig (by default three cameras in a row) and the capture trajectory.

Rig frame: x forward (driving direction), y left, z up, origin on the road
below the rig. The cameras sit in a row on the roof, optical axes parallel,
looking to the right of the car (−y), so that successive cameras are displaced
along their own x axis: a rectified horizontal stereo rig. Camera frames follow
OpenCV (x right, y down, z forward).

The default cameras are portrait (416×736, 9:16, about the pixels of 640×480)
with a 115° horizontal and 140° vertical field of view, pitched up 8°: they see
from 62° below the horizon (the road from about 1 m beside the path, the kerb,
the whole sidewalk) to 78° above it (the roofline of a 24 m facade standing
right at the back of the sidewalk). ``data_synth.coverage`` measures this.

Lens distortion (``data_synth.distortion``): a rig may hold raw, distorted
cameras. ``Rig.intrinsics`` are always the pinhole matrices of the undistorted
images that ``Dataset.image`` returns; the raw K and the lens are kept beside
them so that ``rig.json`` round-trips.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, as_matrix, check_rigid, read_json, write_json

from .distortion import PRESETS as DISTORTION_PRESETS
from .distortion import Distortion, UndistortTables, cached_tables, pinhole_for

RIG_FORMAT = "bbcity-rig"
POSES_FORMAT = "bbcity-poses"
FORMAT_VERSION = 1


#: A focal length lies within this factor of its image edge (pixels), either way.
FOCAL_RANGE = 1000.0
#: How much narrower than the raw image a lens's undistorted pinhole image may be (fisheye
#: k1 = 100 makes it 6×; k1 = 1e6, 126×: a reconstruction then sees nothing).
MAX_UNDISTORT_ZOOM = 20.0


def _is_int(value) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class RigConfig:
    width: int = 416  # image width, pixels (along the row: the stereo baseline)
    height: int = 736  # image height, pixels (portrait: road to roofline)
    hfov_deg: float = 115.0  # horizontal field of view, degrees (vertical: vfov_deg)
    baselines: tuple[float, ...] = (0.0, 0.4, 0.8)  # offset of each camera from cam0 along the row, metres
    mount_height: float = 2.0  # height of the optical centres above the road, metres
    pitch_deg: float = 8.0  # upward tilt of the (parallel) optical axes, degrees
    distortion: str = "none"  # lens of the raw images: "none" (pinhole), or the preset "radtan" or "fisheye"

    def __post_init__(self):
        for name in ("width", "height"):
            if not _is_int(getattr(self, name)):  # True is an int to Python, never an image size
                raise InputError(f"{name} must be an integer, got {getattr(self, name)!r}")
        if self.distortion != "none" and self.distortion not in DISTORTION_PRESETS:
            raise InputError(f"distortion must be \"none\" or one of {', '.join(DISTORTION_PRESETS)}, "
                             f"got {self.distortion!r}")
        if not (0 < self.hfov_deg < 170):
            raise InputError(f"hfov_deg must be in (0, 170), got {self.hfov_deg}")
        if isinstance(self.width, bool) or isinstance(self.height, bool):
            raise InputError(f"image size must be two integers, got {self.width!r}x{self.height!r}")
        if self.width < 8 or self.height < 8:
            raise InputError(f"image size {self.width}x{self.height} is too small")
        if not -90.0 <= self.pitch_deg <= 90.0:
            raise InputError(f"pitch_deg must be in [-90, 90], got {self.pitch_deg}")
        if not self.baselines or not all(np.isfinite(b) for b in self.baselines):
            raise InputError(f"baselines must be a non-empty tuple of finite offsets, got {self.baselines!r}")

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view, degrees (square pixels, centred principal point)."""
        return float(np.degrees(2 * np.arctan(self.height / self.width * np.tan(np.radians(self.hfov_deg) / 2))))


@dataclass(frozen=True)
class Rig:
    """Calibrated cameras of a rig.

    intrinsics: (c, 3, 3) float64 OpenCV pinhole matrices (pixel centres at integers) of the
        images downstream stages see (the undistorted ones where a camera has a lens distortion).
    sizes: c × (width, height) in pixels (raw and undistorted images alike).
    cam_from_rig: (c, 4, 4) float64 rigid transforms.
    raw_intrinsics: (c, 3, 3) float64 K of the raw, distorted images, or None when no camera
        is distorted (then the raw images are the pinhole images).
    distortions: c × (Distortion or None), or None when no camera is distorted.
    Build distorted rigs with :meth:`from_raw`.
    """

    intrinsics: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    cam_from_rig: np.ndarray
    raw_intrinsics: np.ndarray | None = None
    distortions: tuple[Distortion | None, ...] | None = None

    def __post_init__(self):
        if (self.raw_intrinsics is None) != (self.distortions is None):
            raise InputError("raw_intrinsics and distortions go together (use Rig.from_raw)")
        if self.distortions is not None and (len(self.distortions) != len(self.sizes)
                                             or len(self.raw_intrinsics) != len(self.sizes)):
            raise InputError(f"{len(self.sizes)} cameras but {len(self.distortions)} distortions "
                             f"and {len(self.raw_intrinsics)} raw intrinsics")

    @classmethod
    def from_raw(cls, raw_intrinsics: np.ndarray, sizes, cam_from_rig: np.ndarray,
                 distortions) -> "Rig":
        """A rig from its raw cameras: K (c, 3, 3) float64 and a Distortion or None each.

        The pinhole ``intrinsics`` of distorted cameras are those of their undistorted images
        (``data_synth.distortion.pinhole_for``). Without any distortion this is the plain rig.
        """
        raw = np.asarray(raw_intrinsics, dtype=np.float64)
        sizes = tuple((int(w), int(h)) for w, h in sizes)
        distortions = tuple(distortions)
        if all(d is None for d in distortions):
            return cls(raw, sizes, np.asarray(cam_from_rig, dtype=np.float64))
        Ks = np.array([K if d is None else pinhole_for(K, d, s) for K, d, s in zip(raw, distortions, sizes)])
        return cls(Ks, sizes, np.asarray(cam_from_rig, dtype=np.float64), raw, distortions)

    @property
    def num_cameras(self) -> int:
        return len(self.sizes)

    def distortion(self, cam: int) -> Distortion | None:
        """Lens distortion of camera ``cam``'s raw images (None: pinhole)."""
        return None if self.distortions is None else self.distortions[cam]

    def raw_K(self, cam: int) -> np.ndarray:
        """(3, 3) float64 K of camera ``cam``'s raw images (its pinhole K when undistorted)."""
        return self.intrinsics[cam] if self.raw_intrinsics is None else self.raw_intrinsics[cam]

    def undistort_tables(self, cam: int) -> UndistortTables | None:
        """Remap tables of camera ``cam`` (computed once per process and camera); None when pinhole."""
        d = self.distortion(cam)
        return None if d is None else cached_tables(self.raw_K(cam), d, self.sizes[cam])

    def undistort(self, raw: np.ndarray, cam: int, nearest: bool = False) -> np.ndarray:
        """Camera ``cam``'s raw image (h, w, 3) uint8 → the undistorted one (bilinear), or with
        ``nearest`` any per-pixel array (h, w) (depth, ids) by nearest raw pixel. A pinhole
        camera's array is returned as it is (no copy)."""
        tables = self.undistort_tables(cam)
        if tables is None:
            return raw
        return tables.nearest_values(raw) if nearest else tables.image(raw)

    def world_from_cam(self, world_from_rig: np.ndarray, cam: int) -> np.ndarray:
        """(4, 4) float64 pose of camera ``cam`` for a rig pose (4, 4) float64."""
        return world_from_rig @ np.linalg.inv(self.cam_from_rig[cam])

    def to_json(self) -> dict:
        cams = []
        for i, ((w, h), T) in enumerate(zip(self.sizes, self.cam_from_rig)):
            K, d = self.raw_K(i), self.distortion(i)  # rig.json holds the raw camera
            cams.append({
                "name": f"cam{i}", "model": "pinhole", "width": int(w), "height": int(h),
                "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                "distortion": "none" if d is None else d.to_json(), "cam_from_rig": T.tolist(),
            })
        return {"format": RIG_FORMAT, "version": FORMAT_VERSION, "pixel_centre": "integer (OpenCV)",
                "reference_camera": 0, "cameras": cams}

    def save(self, path: os.PathLike | str) -> Path:
        return write_json(path, self.to_json())

    @classmethod
    def load(cls, path: os.PathLike | str) -> "Rig":
        """Read and validate ``rig.json``; errors name the file and the field."""
        path = Path(path)
        data = read_json(path)
        if not isinstance(data, dict) or data.get("format") != RIG_FORMAT:
            raise DataFormatError(path, f"not a rig file (expected \"format\": \"{RIG_FORMAT}\")")
        if not _is_int(data.get("version")) or data["version"] != FORMAT_VERSION:  # true == 1 in Python
            raise DataFormatError(path, f"unsupported version {data.get('version')!r}")
        cams = data.get("cameras")
        if not isinstance(cams, list) or not cams:
            raise DataFormatError(path, "\"cameras\" must be a non-empty list")
        Ks, sizes, Ts, distortions = [], [], [], []
        for i, cam in enumerate(cams):
            where = f"cameras[{i}]"
            if not isinstance(cam, dict):
                raise DataFormatError(path, f"{where} is not an object")
            missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy", "cam_from_rig") if k not in cam]
            if missing:
                raise DataFormatError(path, f"{where} lacks {', '.join(missing)}")
            distortions.append(Distortion.from_json(cam.get("distortion", "none"), path, f"{where}.distortion"))
            for name in ("width", "height"):
                v = cam[name]
                if not (_is_int(v) and 0 < v <= 65536):  # JSON true would pass as 1
                    raise DataFormatError(path, f"{where}.{name} must be a positive integer ≤ 65536 "
                                                f"(image width/height in pixels), got {v!r}")
            w, h = cam["width"], cam["height"]
            f = as_matrix([cam["fx"], cam["fy"], cam["cx"], cam["cy"]], (4,), path, f"{where} intrinsics")
            if f[0] <= 0 or f[1] <= 0:
                raise DataFormatError(path, f"{where} focal lengths must be positive")
            for name, value, edge in (("fx", f[0], w), ("fy", f[1], h)):
                if not edge / FOCAL_RANGE <= value <= edge * FOCAL_RANGE:  # a 0.06° to 179.9° field of view
                    raise DataFormatError(path, f"{where}.{name} {value:g} px is not a lens's for a {edge}-px "
                                                f"image (expected {edge / FOCAL_RANGE:g} to {edge * FOCAL_RANGE:g})")
            Ks.append(np.array([[f[0], 0, f[2]], [0, f[1], f[3]], [0, 0, 1]]))
            sizes.append((w, h))
            Ts.append(check_rigid(as_matrix(cam["cam_from_rig"], (4, 4), path, f"{where}.cam_from_rig"),
                                  path, f"{where}.cam_from_rig"))
        try:
            rig = cls.from_raw(np.array(Ks), tuple(sizes), np.array(Ts), distortions)
        except ValueError as e:  # a lens that leaves no pinhole image inside the raw one
            raise DataFormatError(path, f"cannot undistort the cameras ({e})") from None
        for i, K in enumerate(Ks):
            zoom = rig.intrinsics[i][0, 0] / K[0, 0]
            if zoom > MAX_UNDISTORT_ZOOM:  # fisheye k1 = 1e6: the stages would see a few raw pixels
                raise DataFormatError(path, f"cameras[{i}].distortion leaves an undistorted image {zoom:.0f}× "
                                            f"narrower than the raw one (at most {MAX_UNDISTORT_ZOOM:g}×): "
                                            "coefficients no lens has")
        return rig


def pinhole(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) float64 K with square pixels and the principal point at the image centre."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


#: A synthetic fisheye's image corners stay this far off axis at most: a pinhole image (what the
#: undistorted images are) can show nothing at 90°, and little of what lies near it.
FISHEYE_MAX_CORNER_DEG = 85.0


def raw_camera(cfg: RigConfig) -> tuple[np.ndarray, Distortion | None]:
    """K (3, 3) float64 and lens of the synthetic rig's raw images.

    none: the pinhole of ``hfov_deg``. radtan: the same K with the preset's (barrel) lens.
    fisheye: an equidistant lens that spans ``hfov_deg`` across the width, unless that puts the
    image corners beyond FISHEYE_MAX_CORNER_DEG off axis (the default portrait camera's 115°
    would put its top and bottom edges 100° off axis); then the corners set the focal length.
    """
    K = pinhole(cfg.width, cfg.height, cfg.hfov_deg)
    if cfg.distortion == "none":
        return K, None
    d = Distortion.preset(cfg.distortion)
    if d.model == "fisheye":
        def theta_d(theta: float) -> float:
            t2 = theta * theta
            k1, k2, k3, k4 = d.coeffs
            return theta * (1 + k1 * t2 + k2 * t2 ** 2 + k3 * t2 ** 3 + k4 * t2 ** 4)
        f_width = 0.5 * cfg.width / theta_d(np.radians(cfg.hfov_deg) / 2)
        f_corner = np.hypot(K[0, 2], K[1, 2]) / theta_d(np.radians(FISHEYE_MAX_CORNER_DEG))
        K = K.copy()
        K[0, 0] = K[1, 1] = max(f_width, f_corner)
    return K, d


def make_rig(cfg: RigConfig) -> Rig:
    """Cameras in a row looking right (−y of the rig), pitched up by ``cfg.pitch_deg``;
    with ``cfg.distortion`` their raw images are distorted (see :func:`raw_camera`)."""
    if not (0 < cfg.hfov_deg < 170):
        raise InputError(f"hfov_deg must be in (0, 170), got {cfg.hfov_deg}")
    if cfg.width < 8 or cfg.height < 8:
        raise InputError(f"image size {cfg.width}x{cfg.height} is too small")
    a = np.radians(cfg.pitch_deg)
    z_axis = np.array([0.0, -np.cos(a), np.sin(a)])  # forward: right of the car, tilted up
    y_axis = np.array([0.0, -np.sin(a), -np.cos(a)])  # down in the image
    x_axis = np.cross(y_axis, z_axis)  # = −x of the rig: the row runs backwards
    rig_from_cam_rot = np.stack([x_axis, y_axis, z_axis], axis=1)
    K, distortion = raw_camera(cfg)
    Ts = []
    for b in cfg.baselines:
        T = np.eye(4)
        T[:3, :3] = rig_from_cam_rot
        T[:3, 3] = np.array([0.0, 0.0, cfg.mount_height]) + b * x_axis
        Ts.append(np.linalg.inv(T))
    n = len(cfg.baselines)
    if distortion is not None:
        return Rig.from_raw(np.repeat(K[None], n, axis=0), ((cfg.width, cfg.height),) * n, np.array(Ts),
                            (distortion,) * n)
    return Rig(np.repeat(K[None], n, axis=0), ((cfg.width, cfg.height),) * n, np.array(Ts))


def yaw_pose(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(n, 4, 4) float64 poses on the ground plane. x, y, yaw (radians): (n,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros((len(x), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, 0, 3], T[:, 1, 3] = x, y
    return T


def drive_path(x_start: float, x_end: float, y_centre: float, frames: int, lane_offset: float,
               return_pass: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Drive along +x in the right lane, then back along −x in the other lane.

    Frames are evenly spaced along each pass; the rig's cameras look right,
    so the outbound pass sees the y < y_centre side and the return pass the other.
    Returns world_from_rig (n, 4, 4) float64 and the pass of each frame (n,) int32.
    """
    if frames < 1:
        raise InputError(f"frames must be at least 1, got {frames}")
    x = np.linspace(x_start, x_end, frames) if frames > 1 else np.array([(x_start + x_end) / 2])
    out = yaw_pose(x, np.full(frames, y_centre - lane_offset), np.zeros(frames))
    passes = [out]
    if return_pass:
        passes.append(yaw_pose(x[::-1], np.full(frames, y_centre + lane_offset), np.full(frames, np.pi)))
    poses = np.concatenate(passes)
    which = np.repeat(np.arange(len(passes), dtype=np.int32), frames)
    return poses, which


def orbit_path(centre, radius: float, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Walk once round a circle of ``radius`` metres about ``centre`` (x, y), clockwise seen
    from above, so that the rig's right (where its cameras look) faces the centre.

    The first frame stands north of the centre (+y: the street's side of its free-standing
    building) heading along +x, as a drive starts; the frames are evenly spaced in angle,
    2π·radius / frames metres apart along the circle, and the loop is not closed by a repeat
    of the first frame. One pass. Returns world_from_rig (n, 4, 4) float64 and the pass of
    each frame (n,) int32 (all 0).
    """
    if frames < 1:
        raise InputError(f"frames must be at least 1, got {frames}")
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"radius must be a positive number of metres, got {radius}")
    cx, cy = (float(v) for v in centre)
    angle = np.pi / 2 - 2 * np.pi * np.arange(frames) / frames  # position angle about the centre
    x, y = cx + radius * np.cos(angle), cy + radius * np.sin(angle)
    return yaw_pose(x, y, angle - np.pi / 2), np.zeros(frames, dtype=np.int32)  # the rig's y (left) points out


def save_poses(path: os.PathLike | str, world_from_rig: np.ndarray, passes: np.ndarray,
               names: list[str] | None = None) -> Path:
    """Write ``poses.json``: one ``world_from_rig`` (4, 4) float64 per frame, named
    ``names`` (default: the frame index, six digits). A frame whose matrix has a NaN has
    no known pose (a photo folder's, before SfM): it is written as ``null``."""
    names = [f"{i:06d}" for i in range(len(world_from_rig))] if names is None else list(names)
    frames = [{"index": i, "name": name, "pass": int(p),
               "world_from_rig": T.tolist() if np.all(np.isfinite(T)) else None}
              for i, (T, p, name) in enumerate(zip(world_from_rig, passes, names))]
    return write_json(path, {"format": POSES_FORMAT, "version": FORMAT_VERSION, "frames": frames})


def load_poses(path: os.PathLike | str) -> tuple[np.ndarray, list[str]]:
    """Read and validate ``poses.json`` → world_from_rig (n, 4, 4) float64 and frame names.

    A frame's ``"world_from_rig": null`` means its pose is unknown: its matrix is all NaN
    (``bbcity recon --poses sfm`` computes it)."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != POSES_FORMAT:
        raise DataFormatError(path, f"not a poses file (expected \"format\": \"{POSES_FORMAT}\")")
    if not _is_int(data.get("version")) or data["version"] != FORMAT_VERSION:
        raise DataFormatError(path, f"unsupported version {data.get('version')!r}")
    frames = data.get("frames")
    if not isinstance(frames, list):
        raise DataFormatError(path, "\"frames\" must be a list")
    poses, names = [], []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "world_from_rig" not in fr or not isinstance(fr.get("name"), str):
            raise DataFormatError(path, f"frames[{i}] needs \"name\" and \"world_from_rig\"")
        if not fr["name"] or any(c in fr["name"] for c in "/\\\0") or fr["name"] in (".", ".."):
            raise DataFormatError(path, f"frames[{i}].name {fr['name']!r} is not a plain file stem")
        if fr["world_from_rig"] is None:
            poses.append(np.full((4, 4), np.nan))
        else:
            T = as_matrix(fr["world_from_rig"], (4, 4), path, f"frames[{i}].world_from_rig")
            poses.append(check_rigid(T, path, f"frames[{i}].world_from_rig"))
        names.append(fr["name"])
    if len(set(names)) != len(names):
        raise DataFormatError(path, "frame names are not unique")
    return np.array(poses).reshape(-1, 4, 4), names
