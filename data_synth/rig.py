"""The synthetic camera rig (by default three cameras in a row) and the capture trajectory.

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

Lens distortion (:mod:`capture.distortion`): the synthetic rig may hold raw, distorted
cameras (``RigConfig.distortion``, a named lens); :class:`capture.rig.Rig` keeps the raw K
and the lens beside the pinhole intrinsics of the undistorted images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capture.distortion import PRESETS as DISTORTION_PRESETS
from capture.distortion import Distortion
from capture.rig import Rig, is_int, pinhole
from core.errors import InputError


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
            if not is_int(getattr(self, name)):  # True is an int to Python, never an image size
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
