"""Baselines the billboard model is measured against in ``bbcity eval``: the fused cloud
rendered two ways, on the CPU with Open3D.

- :class:`PointProjector`: every point projected to one pixel, nearest wins
  (``PointCloud.project_to_rgbd_image``). Bytes: float32 xyz + uint8 RGB per point.
- :class:`PoissonMesh`: the cloud meshed by screened Poisson reconstruction
  (``TriangleMesh.create_from_point_cloud_poisson``, octree ``depth``), vertices whose
  Poisson density is below the ``trim_quantile`` quantile removed (the surface Poisson
  invents far from any point), vertex colours. Rendered by ray casting
  (``RaycastingScene``): one ray through each pixel centre (OpenCV: centres at integer
  coordinates), the first triangle hit, its vertex colours interpolated with the hit's
  barycentric coordinates (``primitive_uvs``: the hit is (1 − u − v)·v₀ + u·v₁ + v·v₂)
  and rounded to 8 bits; black where no triangle is hit. Bytes: float32 xyz + uint8
  RGB per vertex + 3 int32 per triangle.

Both keep float32 coordinates relative to an origin (the cloud's mean), so city
coordinates keep their centimetres.
"""

from __future__ import annotations

import errno
import logging
import os
import time
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import atomic_path

logger = logging.getLogger(__name__)


class PointProjector:
    """The cloud projected to images with Open3D. points (N, 3) float64 world, colours (N, 3) uint8."""

    def __init__(self, points: np.ndarray, colours: np.ndarray):
        import open3d as o3d

        self._o3d = o3d
        self.origin = points.mean(axis=0) if len(points) else np.zeros(3)
        self.cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor((points - self.origin).astype(np.float32)))
        self.cloud.point.colors = o3d.core.Tensor(colours.astype(np.float32) / 255.0)
        self.nbytes = len(points) * (3 * 4 + 3)

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, size) -> np.ndarray:
        """(h, w, 3) uint8: nearest point per pixel, background black."""
        o3d = self._o3d
        local = np.array(world_from_cam, dtype=np.float64)
        local[:3, 3] -= self.origin
        image = self.cloud.project_to_rgbd_image(int(size[0]), int(size[1]), o3d.core.Tensor(np.asarray(K, np.float64)),
                                                 o3d.core.Tensor(np.linalg.inv(local)), depth_scale=1.0,
                                                 depth_max=1000.0)
        colour = image.color.as_tensor().numpy()
        return np.clip(np.rint(colour * 255), 0, 255).astype(np.uint8)

    __call__ = render


def orient_normals(points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """(N, 3) ``normals`` flipped where they point away from the nearest of ``viewpoints``
    (v, 3) (camera centres); points (N, 3) in the same frame."""
    out = np.array(normals, dtype=np.float64)
    vp = np.asarray(viewpoints, np.float64).reshape(-1, 3)
    if len(vp) == 0:
        return out
    for b in range(0, len(points), chunk):
        p = points[b:b + chunk]
        d2 = ((p[:, None, :] - vp[None, :, :]) ** 2).sum(-1)
        to_eye = vp[np.argmin(d2, axis=1)] - p
        flip = np.einsum("ij,ij->i", out[b:b + chunk], to_eye) < 0
        out[b:b + chunk][flip] *= -1
    return out


def poisson_arrays(points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None, *,
                   depth: int = 10, trim_quantile: float = 0.05, viewpoints: np.ndarray | None = None) -> dict:
    """The cloud as a screened Poisson mesh with vertex colours (Open3D), as arrays.

    points (N, 3) float64 world; colours (N, 3) uint8; normals (N, 3) or None (then
    estimated from 30 neighbours and turned toward the nearest of ``viewpoints`` (v, 3),
    e.g. the capture camera centres); depth: Poisson octree depth (cells of the
    bounding cube's edge / 2^depth); trim_quantile: vertices of lower density removed.
    Returns {"depth", "origin" (3,) float64, "vertices" (V, 3) float32 relative to it,
    "vertex_colours" (V, 3) uint8, "triangles" (T, 3) int32, "seconds"}: small enough to
    come back from a worker process (Open3D's Poisson holds the GIL while it meshes).
    """
    import open3d as o3d

    if not 1 <= int(depth) <= 16:
        raise InputError(f"Poisson depth must be in [1, 16], got {depth}")
    if not 0 <= trim_quantile < 1:
        raise InputError(f"trim_quantile must be in [0, 1), got {trim_quantile}")
    t0 = time.perf_counter()
    points = np.asarray(points, np.float64)
    extent = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    if not extent > 0:  # Open3D's Poisson crashes (SIGSEGV) on a cloud of one point repeated
        raise InputError(f"a Poisson mesh needs points spread in space: the cloud's {len(points)} points "
                         f"span {extent:g} m")
    origin = points.mean(axis=0)
    local = points - origin
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(local))
    pcd.colors = o3d.utility.Vector3dVector(np.asarray(colours, np.float64) / 255.0)
    if normals is None:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
        vp = np.zeros((0, 3)) if viewpoints is None else np.asarray(viewpoints, np.float64) - origin
        pcd.normals = o3d.utility.Vector3dVector(orient_normals(local, np.asarray(pcd.normals), vp))
    else:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    del local
    # one thread: Open3D's Poisson with several races (a random SIGSEGV, Open3D issue 6828, and meshes
    # that differ from run to run); with one it is the same mesh every time
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=int(depth), n_threads=1)
    del pcd
    density = np.asarray(density)
    if trim_quantile > 0 and len(density):
        mesh.remove_vertices_by_mask(density < np.quantile(density, trim_quantile))
    vertices = np.asarray(mesh.vertices).astype(np.float32)
    vertex_colours = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255), 0, 255).astype(np.uint8)
    if len(vertex_colours) != len(vertices):  # Open3D gives no colours for a colourless cloud
        vertex_colours = np.zeros((len(vertices), 3), np.uint8)
    return {"depth": int(depth), "origin": origin, "vertices": vertices, "vertex_colours": vertex_colours,
            "triangles": np.asarray(mesh.triangles).astype(np.int32), "seconds": time.perf_counter() - t0}


def write_poisson_ply(path: os.PathLike | str, mesh: dict) -> Path:
    """Write a :func:`poisson_arrays` result atomically as a binary PLY mesh (float64 world
    vertices, vertex colours); OSError naming ``path`` when Open3D cannot write it."""
    import open3d as o3d

    out = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh["vertices"].astype(np.float64) + mesh["origin"]),
        o3d.utility.Vector3iVector(mesh["triangles"].astype(np.int32)))
    out.vertex_colors = o3d.utility.Vector3dVector(mesh["vertex_colours"].astype(np.float64) / 255.0)
    path = Path(path)
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), out, write_ascii=False, compressed=False,
                                          write_vertex_normals=False, write_vertex_colors=True):
            raise OSError(errno.EIO, "Open3D could not write the mesh", str(path))
    return path


class PoissonMesh:
    """The cloud as a screened Poisson mesh with vertex colours, ray cast to images.

    The arguments are :func:`poisson_arrays`'s (:meth:`from_arrays`: its result, made
    elsewhere). ``vertices`` (V, 3) float32 relative to ``origin``, ``vertex_colours``
    (V, 3) uint8, ``triangles`` (T, 3) int32; ``seconds``: time to mesh.
    """

    def __init__(self, points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None, *,
                 depth: int = 10, trim_quantile: float = 0.05, viewpoints: np.ndarray | None = None):
        self._adopt(poisson_arrays(points, colours, normals, depth=depth, trim_quantile=trim_quantile,
                                   viewpoints=viewpoints))

    @classmethod
    def from_arrays(cls, arrays: dict) -> "PoissonMesh":
        """The mesh of :func:`poisson_arrays`' result."""
        mesh = cls.__new__(cls)
        mesh._adopt(arrays)
        return mesh

    def _adopt(self, arrays: dict) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.depth, self.origin, self.seconds = arrays["depth"], arrays["origin"], arrays["seconds"]
        self.vertices, self.vertex_colours = arrays["vertices"], arrays["vertex_colours"]
        self.triangles = arrays["triangles"]
        self.nbytes = len(self.vertices) * (3 * 4 + 3) + len(self.triangles) * 3 * 4
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(self.triangles):
            self.scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles.astype(np.uint32)))
        logger.info("Poisson mesh, depth %d: %d vertices, %d triangles, %.1f MB, %.1f s%s", self.depth,
                    len(self.vertices), len(self.triangles), self.nbytes / 1e6, self.seconds,
                    " (made earlier, from the cloud's cache)" if arrays.get("cached") else "")

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, size) -> np.ndarray:
        """(h, w, 3) uint8: the first triangle hit through each pixel centre, its vertex
        colours interpolated by the hit's barycentric coordinates; black where none is hit."""
        o3d = self._o3d
        w, h = (int(s) for s in size)
        T = np.asarray(world_from_cam, np.float64)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        rays_cam = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(np.asarray(K, np.float64)).T
        rays = np.empty((h * w, 6), np.float32)
        rays[:, :3] = T[:3, 3] - self.origin
        rays[:, 3:] = rays_cam @ T[:3, :3].T
        image = np.zeros((h * w, 3), np.uint8)
        if len(self.triangles) == 0:
            return image.reshape(h, w, 3)
        hits = self.scene.cast_rays(o3d.core.Tensor(rays))
        prim = hits["primitive_ids"].numpy()
        hit = prim != o3d.t.geometry.RaycastingScene.INVALID_ID
        tri = self.triangles[prim[hit].astype(np.int64)]
        uv = hits["primitive_uvs"].numpy()[hit].astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
        colour = np.einsum("nk,nkc->nc", bary, self.vertex_colours[tri].astype(np.float64))
        image[hit] = np.clip(np.rint(colour), 0, 255).astype(np.uint8)
        return image.reshape(h, w, 3)

    __call__ = render
