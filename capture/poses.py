"""``poses.json``: the rig's pose (``world_from_rig``) at every frame, and poses that are unknown.

A frame whose pose is not known (a photo folder's, before SfM) has an all-NaN matrix here
and ``null`` in the file: :func:`posed` tells the known ones apart.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from core.fileio import DataFormatError, as_matrix, check_rigid, read_json, write_json

from .rig import FORMAT_VERSION, is_int

POSES_FORMAT = "bbcity-poses"


def unknown_poses(n: int) -> np.ndarray:
    """(n, 4, 4) float64 all NaN: ``n`` frames without a pose."""
    return np.full((n, 4, 4), np.nan)


def posed(T: np.ndarray) -> np.ndarray:
    """(n,) bool: which poses of T (n, 4, 4) are known (fully finite)."""
    return np.isfinite(T).all(axis=(1, 2))


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
    if not is_int(data.get("version")) or data["version"] != FORMAT_VERSION:
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
