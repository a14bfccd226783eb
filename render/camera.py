"""OpenCV pinhole cameras as OpenGL projection and view matrices.

Conventions. A camera is an OpenCV intrinsic matrix ``K`` (3, 3) and a pose
``world_from_cam`` (4, 4) float64 whose camera frame is OpenCV's (x right, y down,
z forward). OpenGL's eye frame has x right, y up, z backward, so
``gl_from_cv = diag(1, −1, −1)``. Pixel (u, v) in OpenCV has its centre at integer
coordinates and covers [u − ½, u + ½]; the image spans [−½, w − ½] × [−½, h − ½]
and maps to NDC x ∈ [−1, 1] left to right and y ∈ [1, −1] top to bottom. The
renderer reads the framebuffer back bottom-up and flips it, so image row 0 is the
top as in OpenCV.

Precision. World coordinates may be city-scale (UTM eastings of 10⁶ m); the GPU
gets float32 positions relative to the model origin. The view matrix is therefore
built in float64 from the camera centre *minus the origin* and only then cast to
float32: it maps model coordinates (world − origin) to the GL eye frame.

Matrices are returned row-major float32 for ``M @ p``; write them to GLSL
``mat4`` uniforms transposed (:func:`gl_bytes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class ClipPlanes:
    near: float = 0.1  # near plane distance (m) in front of the camera
    far: float = 2000.0  # far plane distance (m)

    def __post_init__(self):
        if not (np.isfinite(self.near) and np.isfinite(self.far) and 0 < self.near < self.far):
            raise InputError(f"need 0 < near < far, got near={self.near}, far={self.far}")


@dataclass(frozen=True)
class GLCamera:
    """Everything the shaders need about one camera, relative to a model origin."""

    projection: np.ndarray  # (4, 4) float32 GL clip from GL eye
    view: np.ndarray  # (4, 4) float32 GL eye from model (= world − origin)
    eye: np.ndarray  # (3,) float64 camera centre in model coordinates (world − origin)
    size: tuple[int, int]  # (width, height) pixels


def _size(size) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise InputError(f"size must be (width, height), got {size!r}") from None
    if w < 1 or h < 1 or (w, h) != tuple(size):
        raise InputError(f"size must be two positive integers (width, height), got {size!r}")
    return w, h


def check_intrinsics(K) -> np.ndarray:
    """K as (3, 3) float64 after checking it is a finite upper-triangular pinhole matrix with fx, fy > 0."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"K must be a finite (3, 3) matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] or K[2, 0] or K[2, 1] or K[2, 2] != 1:
        raise InputError(f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}")
    return K


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_I3 = np.eye(3)
_LAST_ROW.flags.writeable = _I3.flags.writeable = False


def check_pose(world_from_cam) -> np.ndarray:
    """world_from_cam as (4, 4) float64 after checking it is a finite rigid transform."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"world_from_cam must be a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    # np.allclose (rtol 1e-5; atol 1e-8, and 1e-6 for RᵀR) written out: this runs for every tile
    # of every frame, and allclose's own checks cost more than the test
    if np.any(np.abs(T[3] - _LAST_ROW) > 1e-8 + 1e-5 * _LAST_ROW) \
            or np.any(np.abs(R.T @ R - _I3) > 1e-6 + 1e-5 * _I3) or np.linalg.det(R) <= 0:
        raise InputError("world_from_cam must be a rigid transform (rotation + translation)")
    return T


def projection_from_K(K, size, near: float = 0.1, far: float = 2000.0) -> np.ndarray:
    """OpenGL projection (4, 4) float32 reproducing the pinhole ``K`` for an image of ``size`` = (w, h).

    Maps the GL eye frame to clip space so that a point projecting to OpenCV pixel
    (u, v) lands at the centre of framebuffer pixel (u, h − 1 − v); depth maps
    [near, far] to NDC [−1, 1] (standard GL perspective). Skew K[0, 1] is honoured.
    """
    K = check_intrinsics(K)
    w, h = _size(size)
    ClipPlanes(near, far)
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    P = np.zeros((4, 4))
    # x_clip = (2fx/w)·x_c + (2s/w)·y_c + (2(cx+½)/w − 1)·z_c with x_c = x_g, y_c = −y_g, z_c = −z_g
    P[0, 0] = 2 * fx / w
    P[0, 1] = -2 * s / w
    P[0, 2] = 1 - 2 * (cx + 0.5) / w
    # y_ndc = 1 − 2(v+½)/h  →  y_clip = (2fy/h)·y_g + (2(cy+½)/h − 1)·z_g
    P[1, 1] = 2 * fy / h
    P[1, 2] = 2 * (cy + 0.5) / h - 1
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2 * far * near / (far - near)
    P[3, 2] = -1
    return P.astype(np.float32)


def eye_position(world_from_cam, origin) -> np.ndarray:
    """Camera centre relative to ``origin``: (3,) float64 (computed in float64)."""
    T = check_pose(world_from_cam)
    return T[:3, 3] - np.asarray(origin, dtype=np.float64).reshape(3)


def view_from_pose(world_from_cam, origin) -> np.ndarray:
    """GL view matrix (4, 4) float32: GL eye frame from model coordinates (world − origin).

    Built in float64 from the camera centre minus the origin, then cast, so it stays
    exact to float32 rounding of *relative* positions whatever the origin's magnitude.
    """
    T = check_pose(world_from_cam)
    return _view(T, T[:3, 3] - np.asarray(origin, dtype=np.float64).reshape(3))


def _view(T: np.ndarray, eye: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    cam_from_model = np.eye(4)
    cam_from_model[:3, :3] = R.T
    cam_from_model[:3, 3] = -R.T @ eye
    return (GL_FROM_CV @ cam_from_model).astype(np.float32)


def gl_camera(K, world_from_cam, size, origin, clip: ClipPlanes = ClipPlanes()) -> GLCamera:
    """:class:`GLCamera` for an OpenCV camera and a model ``origin`` (3,) float64."""
    size = _size(size)
    T = check_pose(world_from_cam)  # once: a frame's budget is milliseconds
    eye = T[:3, 3] - np.asarray(origin, dtype=np.float64).reshape(3)
    return GLCamera(projection=projection_from_K(K, size, clip.near, clip.far), view=_view(T, eye), eye=eye,
                    size=size)


def camera_at_origin(camera: GLCamera, world_from_cam, origin) -> GLCamera:
    """``camera`` (made by :func:`gl_camera` from ``world_from_cam``, the pose checked then) for a
    model at ``origin`` (3,) float64: the same projection, the view built in float64 from the
    camera centre minus ``origin`` as :func:`gl_camera` builds it. A tiled model draws each tile
    with one."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    eye = T[:3, 3] - np.asarray(origin, dtype=np.float64).reshape(3)
    return GLCamera(projection=camera.projection, view=_view(T, eye), eye=eye, size=camera.size)


def gl_bytes(matrix: np.ndarray) -> bytes:
    """A row-major (4, 4) matrix as the column-major float32 bytes a GLSL ``mat4`` uniform expects."""
    return np.ascontiguousarray(np.asarray(matrix, dtype=np.float32).T).tobytes()


def project_cv(points_world, K, world_from_cam) -> tuple[np.ndarray, np.ndarray]:
    """Reference OpenCV projection in float64: points (n, 3) world → pixels (n, 2) (u, v), depth (n,)."""
    K = check_intrinsics(K)
    T = check_pose(world_from_cam)
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    cam = (p - T[:3, 3]) @ T[:3, :3]
    uvw = cam @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[:, :2] / uvw[:, 2:], cam[:, 2]


def project_gl(points_model, camera: GLCamera) -> tuple[np.ndarray, np.ndarray]:
    """What the GPU computes, in float32: model points (n, 3) → pixels (n, 2) in OpenCV (u, v), NDC depth (n,).

    ``u = (x_ndc + 1)·w/2 − ½``, ``v = (1 − y_ndc)·h/2 − ½`` (the inverse of the
    framebuffer mapping plus the vertical flip of the read-back image).
    """
    p = np.asarray(points_model, dtype=np.float32).reshape(-1, 3)
    ph = np.concatenate([p, np.ones((len(p), 1), np.float32)], axis=1)
    clip = (ph @ camera.view.T) @ camera.projection.T  # as the vertex shader: proj · (view · p)
    with np.errstate(divide="ignore", invalid="ignore"):
        ndc = clip[:, :3] / clip[:, 3:]
    w, h = camera.size
    u = (ndc[:, 0].astype(np.float64) + 1) * w / 2 - 0.5
    v = (1 - ndc[:, 1].astype(np.float64)) * h / 2 - 0.5
    return np.stack([u, v], axis=1), ndc[:, 2]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """world_from_cam (4, 4) float64 of an OpenCV camera at ``eye`` (3,) looking at ``target`` (3,).

    The image's up direction is ``up`` (world z by default) projected onto the image
    plane; raises ValueError when the viewing direction is parallel to ``up``.
    """
    eye, target = np.asarray(eye, np.float64).reshape(3), np.asarray(target, np.float64).reshape(3)
    z = target - eye
    x = np.cross(z, np.asarray(up, np.float64))
    if np.linalg.norm(z) == 0 or np.linalg.norm(x) < 1e-12 * np.linalg.norm(z):
        raise InputError("look_at needs target ≠ eye and a viewing direction not parallel to up")
    z /= np.linalg.norm(z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def default_intrinsics(width: int, height: int, hfov_deg: float = 75.0) -> np.ndarray:
    """Pinhole K (3, 3) float64 with the given horizontal field of view and a centred principal point."""
    f = width / 2 / np.tan(np.deg2rad(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
