"""Poisson meshes of a cloud kept on disk, keyed by the cloud's content, so that a mesh is made once.

Meshing a street's fused cloud takes tens of seconds (:func:`render.baselines.poisson_arrays`);
``bbcity mesh`` makes it while the build runs and ``bbcity eval`` takes it from here. An entry
lives beside the cloud, ``cache/poisson/STEM-DIGEST-dDEPTH-qTRIM.npz``: DIGEST is the start of
the SHA-256 of the cloud file's bytes (the whole digest is stored inside and checked), so a
cloud made again, changed or replaced never reads another's mesh. A cloud without normals is
meshed with normals turned toward viewpoints: its entry also records a digest of those, and
serves only the same viewpoints. Storing an entry removes the entries of the same depth and
trim made from another version of the cloud. A cache that cannot be read or written (a
read-only directory, a damaged file) only costs a mesh: it is logged, never raised.
"""

from __future__ import annotations

import glob
import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from core.fileio import atomic_path

from .baselines import poisson_arrays

logger = logging.getLogger(__name__)

#: Where a cloud's meshes are kept, relative to the cloud's directory.
CACHE_DIR = Path("cache") / "poisson"
#: The arrays an entry keeps (those of :func:`render.baselines.poisson_arrays`' result).
ARRAYS = ("origin", "vertices", "vertex_colours", "triangles")


def file_digest(path: os.PathLike | str) -> str:
    """Hex SHA-256 of the file's bytes (read in chunks: a cloud may be gigabytes)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def viewpoints_digest(viewpoints: np.ndarray | None) -> str:
    """Hex SHA-256 of viewpoints (v, 3) as float64 ("none" for None)."""
    if viewpoints is None:
        return "none"
    vp = np.ascontiguousarray(viewpoints, dtype=np.float64).reshape(-1, 3)
    return hashlib.sha256(vp.tobytes()).hexdigest()


@dataclass(frozen=True)
class PoissonCache:
    """The meshes of the cloud at ``cloud`` whose bytes hash to ``digest`` (:meth:`of`)."""

    cloud: Path
    digest: str

    @classmethod
    def of(cls, cloud: os.PathLike | str) -> "PoissonCache":
        """The cache of the cloud file as it is now (OSError when it cannot be read)."""
        return cls(Path(cloud), file_digest(cloud))

    def path(self, depth: int, trim_quantile: float) -> Path:
        """The entry of a mesh of this octree depth and density trim."""
        return self.cloud.parent / CACHE_DIR / self._name(self.digest[:16], depth, trim_quantile)

    def _name(self, digest: str, depth: int, trim_quantile: float, stem: str | None = None) -> str:
        return f"{self.cloud.stem if stem is None else stem}-{digest}-d{int(depth)}-q{float(trim_quantile)!r}.npz"

    def load(self, depth: int, trim_quantile: float, viewpoints: np.ndarray | None) -> dict | None:
        """The mesh (a :func:`~render.baselines.poisson_arrays` result, with "cached": True) made
        from this cloud with these settings, or None when there is none (or it cannot be read)."""
        path = self.path(depth, trim_quantile)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                entry = {k: z[k] for k in (*ARRAYS, "digest", "viewpoints", "seconds")}
        except (OSError, ValueError, KeyError, EOFError) as e:
            logger.warning("%s: not a readable cached mesh (%s); meshing again", path, e)
            return None
        vp = str(entry["viewpoints"])
        if str(entry["digest"]) != self.digest or vp not in ("any", viewpoints_digest(viewpoints)):
            return None
        vertices, triangles = entry["vertices"], entry["triangles"]
        if not (entry["origin"].shape == (3,) and vertices.ndim == 2 and vertices.shape[1] == 3
                and entry["vertex_colours"].shape == vertices.shape and triangles.ndim == 2
                and triangles.shape[1] == 3 and (not triangles.size or 0 <= triangles.min()
                                                 and triangles.max() < len(vertices))):
            logger.warning("%s: a cached mesh of malformed arrays; meshing again", path)
            return None
        return {"depth": int(depth), "origin": entry["origin"].astype(np.float64),
                "vertices": vertices.astype(np.float32), "vertex_colours": entry["vertex_colours"].astype(np.uint8),
                "triangles": triangles.astype(np.int32), "seconds": float(entry["seconds"]), "cached": True}

    def store(self, mesh: dict, trim_quantile: float, viewpoints: np.ndarray | None, oriented: bool) -> Path | None:
        """Keep ``mesh`` (a :func:`~render.baselines.poisson_arrays` result) for this cloud;
        ``oriented``: the cloud had its own normals (the viewpoints did not matter). Removes the
        entries of the same settings from other versions of the cloud. Returns the entry's path,
        or None when it could not be written."""
        path = self.path(mesh["depth"], trim_quantile)
        try:
            with atomic_path(path) as tmp, open(tmp, "wb") as f:
                np.savez(f, **{k: mesh[k] for k in ARRAYS}, digest=np.str_(self.digest),
                         viewpoints=np.str_("any" if oriented else viewpoints_digest(viewpoints)),
                         seconds=np.float64(mesh["seconds"]))
            for old in path.parent.glob(self._name("*", mesh["depth"], trim_quantile, glob.escape(self.cloud.stem))):
                if old != path:
                    old.unlink(missing_ok=True)
        except OSError as e:
            logger.warning("%s: could not keep the mesh (%s)", path, e)
            return None
        return path


def cached_poisson(cache: PoissonCache | None, cloud: Callable[[], dict], depth: int, trim_quantile: float,
                   viewpoints: np.ndarray | None) -> dict:
    """The :func:`~render.baselines.poisson_arrays` result of a cloud: the one ``cache`` keeps
    for these settings ("cached": True), else made from ``cloud()`` (its points, colours and
    normals, as :func:`render.evaluate.read_cloud_for_baselines` gives them; called only then)
    and kept in ``cache`` (None: no cache)."""
    mesh = None if cache is None else cache.load(depth, trim_quantile, viewpoints)
    if mesh is None:
        arrays = cloud()
        mesh = poisson_arrays(arrays["points"], arrays["colours"], arrays["normals"], depth=depth,
                              trim_quantile=trim_quantile, viewpoints=viewpoints)
        if cache is not None:
            cache.store(mesh, trim_quantile, viewpoints, oriented=arrays["normals"] is not None)
    return mesh
