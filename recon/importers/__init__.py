"""Importers: a user's own capture → a dataset directory (``rig.json``, ``poses.json``,
``images/cam{c}/``) that every stage reads like a synthetic one.

- :mod:`.kitti`: a KITTI odometry sequence (stereo, rectified, with poses).
"""
