"""Image sources: datasets whose images are made when they are read, not stored.

A dataset whose ``dataset.json`` names a kind of image source (``"images": "lazy"``: the
synthetic generator's lazy datasets, :mod:`data_synth.lazy`) has no ``images/`` files: each
raw image (and its ground truth) is made on demand by the source of that kind. The format
knows sources only through this registry, so that it needs none of the packages that make
images: a producer registers an opener for its kind (:func:`register_image_source`, on its
import), and one not imported yet is found through the package's entry points (group
:data:`ENTRY_POINTS`), so that a worker process that only got a dataset's path opens it too.

A source names its frames by their capture index (``NNNNNN``, six digits) and is small and
picklable (a worker process makes its own images).
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from importlib.metadata import entry_points
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from core.fileio import DataFormatError, read_json

#: The entry-point group of the openers of image sources: name = the kind (``dataset.json``
#: ``"images"``), value = the opener (``module:callable``).
ENTRY_POINTS = "bbcity.image_sources"


class ImageSource(Protocol):
    """What a dataset's images are made from when it stores none."""

    def image(self, frame: int, cam: int) -> np.ndarray:
        """(h, w, 3) uint8 raw RGB of frame ``frame`` (its index) of camera ``cam`` (a new array)."""

    def ground_truth(self, kind: str, frame: int, cam: int) -> np.ndarray:
        """Raw ``kind`` ("depth": (h, w) float32, NaN = sky; "ids": (h, w) int32, −1 = sky)."""

    @property
    def has_gt_depth(self) -> bool:
        """Whether :meth:`ground_truth` gives depth and ids (a source may make images alone)."""

    def check_rig(self, rig, path: Path) -> None:
        """DataFormatError naming ``path`` (the rig.json) unless ``rig`` (a :class:`capture.rig.Rig`)
        is the rig the source makes images with."""

    def check_frames(self, names, world_from_rig: np.ndarray, path: Path) -> None:
        """DataFormatError naming ``path`` (the poses.json) unless the frames ``names`` and their
        poses (n, 4, 4) float64 are those the source makes images of."""


#: Opens the source of a dataset directory from its parsed ``dataset.json``; errors are
#: DataFormatErrors naming the file that is malformed.
Opener = Callable[[Path, dict], ImageSource]

_LOCK = threading.RLock()
_OPENERS: dict[str, Opener] = {}
_SOURCES: OrderedDict = OrderedDict()  # (dataset.json, mtime, size) → ImageSource or None (stored)


def register_image_source(kind: str, opener: Opener) -> None:
    """Let datasets whose ``dataset.json`` says ``"images": kind`` be read through ``opener``."""
    with _LOCK:
        _OPENERS[kind] = opener


def _opener(kind: str, path: Path) -> Opener:
    """The opener of ``kind``: registered, or loaded from its entry point (whose import may
    register it); DataFormatError naming ``path`` (the dataset.json) when there is none."""
    with _LOCK:
        opener = _OPENERS.get(kind)
    if opener is None:
        for point in entry_points(group=ENTRY_POINTS, name=kind):
            opener = point.load()
            register_image_source(kind, opener)
            break
    if opener is None:
        raise DataFormatError(path, f"\"images\" is \"{kind}\": the dataset's images are made when read, by an "
                                    f"image source of that kind, and none is registered or installed (entry "
                                    f"points {ENTRY_POINTS})")
    return opener


def image_source(root: os.PathLike | str) -> ImageSource | None:
    """The :class:`ImageSource` of the dataset at ``root`` when its images are made when read,
    else None (read from its ``dataset.json`` once per process while that file is unchanged)."""
    path = Path(root) / "dataset.json"
    try:
        stat = path.stat()
        key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    except OSError:
        return None  # no manifest: a capture of images
    with _LOCK:
        if key in _SOURCES:
            return _SOURCES[key]
    source = None
    manifest = read_json(path)
    kind = manifest.get("images") if isinstance(manifest, dict) else None
    if isinstance(kind, str):
        source = _opener(kind, path)(Path(root), manifest)
    with _LOCK:
        _SOURCES[key] = source
        while len(_SOURCES) > 8:
            _SOURCES.popitem(last=False)
    return source
