"""Coloured cloud + captured images → the compact billboard model.

A facade layer of fixed blocks on the street's facades and ground (EPI facade depth,
:mod:`billboards.layer`), an octree whose voxel leaves become view-facing billboards
(:mod:`billboards.octree`), occlusion-aware angular sampling of their textures
(:mod:`billboards.sampling`), PCA eigen-textures (:mod:`billboards.pca`), quantised and
packed into atlas pages (:mod:`billboards.quantize`, :mod:`billboards.atlas`), and the
on-disk model with its CPU decode (:mod:`billboards.model`). The stage's entry point is
:func:`billboards.build.main`. No GPU code: rendering is :mod:`render`'s.
"""
