"""Octree, angular sampling, PCA eigen-textures and atlases (built by a later issue)."""
