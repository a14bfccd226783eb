"""The web viewer's camera: a view as five numbers, ``x,y,z,yaw,pitch`` (and a field of view).

A link to a view of an exported site ends in ``#x,y,z,yaw,pitch[,fov]``: the eye in world
metres, the heading (yaw, degrees from +x toward +y, the world being z-up) and the elevation
of the line of sight (pitch, degrees, up positive), the vertical field of view in degrees. The
viewer (``share/viewer/camera.js``) turns them into an OpenCV camera exactly as
:func:`view_camera` does here, so a test can render the same view with
:func:`render.offscreen.render_view` and compare: no roll, square pixels, the principal point
at the image centre.
"""

from __future__ import annotations

import math

import numpy as np

from core.errors import InputError

DEFAULT_FOV_DEG = 60.0  # vertical field of view of a link that names none


def check_view(view) -> tuple[float, float, float, float, float, float]:
    """``view`` (5 or 6 numbers: x, y, z, yaw°, pitch°[, fov°]) as six floats, fov defaulted;
    ValueError naming what is wrong."""
    values = [float(v) for v in view]
    if len(values) not in (5, 6):
        raise InputError(f"a view is x,y,z,yaw,pitch[,fov]: 5 or 6 numbers, got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"a view's numbers must be finite, got {values}")
    if len(values) == 5:
        values.append(DEFAULT_FOV_DEG)
    if not -90.0 < values[4] < 90.0:
        raise InputError(f"pitch must lie strictly between -90 and 90 degrees, got {values[4]:g}")
    if not 1.0 <= values[5] <= 170.0:
        raise InputError(f"fov must lie within [1, 170] degrees, got {values[5]:g}")
    return tuple(values)


def view_camera(view, size) -> tuple[np.ndarray, np.ndarray]:
    """The OpenCV camera of ``view`` (x, y, z, yaw°, pitch°[, fov°]) for an image of ``size``
    (w, h): (K (3, 3) float64, world_from_cam (4, 4) float64). The focal length follows the
    vertical field of view: f = (h/2)/tan(fov/2); the principal point is ((w−1)/2, (h−1)/2)."""
    x, y, z, yaw, pitch, fov = check_view(view)
    w, h = (int(v) for v in size)
    f = 0.5 * h / math.tan(math.radians(fov) / 2)
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = view_rotation(yaw, pitch)
    T[:3, 3] = (x, y, z)
    return K, T


def view_rotation(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """(3, 3) float64 world_from_cam rotation of an OpenCV camera (x right, y down, z forward)
    looking along heading ``yaw_deg`` and elevation ``pitch_deg``, without roll."""
    a, b = math.radians(yaw_deg), math.radians(pitch_deg)
    forward = np.array([math.cos(b) * math.cos(a), math.cos(b) * math.sin(a), math.sin(b)])
    right = np.array([math.sin(a), -math.cos(a), 0.0])
    return np.stack([right, np.cross(forward, right), forward], axis=1)


def pose_view(world_from_cam: np.ndarray) -> tuple[float, float, float, float, float]:
    """(x, y, z, yaw°, pitch°) of a camera pose (its roll dropped): the inverse of
    :func:`view_camera` for a pose without roll."""
    T = np.asarray(world_from_cam, np.float64)
    forward = T[:3, 2]
    yaw = math.degrees(math.atan2(forward[1], forward[0]))
    pitch = math.degrees(math.atan2(forward[2], math.hypot(forward[0], forward[1])))
    return (*(float(v) for v in T[:3, 3]), yaw, pitch)
