"""Coloured cloud + captured images → the compact billboard model.

A facade layer of fixed blocks on the street's facades and ground (EPI facade depth,
:mod:`billboards.layer`), an octree whose voxel leaves become view-facing billboards
(:mod:`billboards.octree`), occlusion-aware angular sampling of their textures
(:mod:`billboards.sampling`), PCA eigen-textures (:mod:`billboards.pca`), quantised and
packed into atlas pages (:mod:`billboards.quantize`, :mod:`billboards.atlas`), and the
on-disk model (:mod:`billboards.model_format` the format, :mod:`billboards.model` in memory,
:mod:`billboards.model_reader` and :mod:`billboards.model_writer`) with its CPU decode
(:mod:`billboards.decode`). The stage's entry point is :func:`billboards.build.main`. No GPU
code: rendering is :mod:`render`'s.

Public API of the model: :class:`BillboardModel`, :func:`load`, :func:`save`,
:class:`ModelWriter`, :func:`decode`, :func:`decode_directions`, :func:`direction_index`.
"""

from .decode import decode, decode_directions, direction_index
from .model import BillboardModel
from .model_reader import load
from .model_writer import ModelWriter, save

__all__ = ["BillboardModel", "ModelWriter", "decode", "decode_directions", "direction_index", "load", "save"]
