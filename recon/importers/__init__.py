"""Importers: a user's own capture → a dataset directory (``rig.json``, ``poses.json``,
``images/cam{c}/``) that every stage reads like a synthetic one.

- :mod:`.kitti`: a KITTI odometry sequence (stereo, rectified, with poses).
- :mod:`.colmap`: a COLMAP sparse model (a rig or one camera, any lens) and its images.
- :mod:`.photos`: a folder of one camera's photos, poses unknown (``recon --poses sfm``); EXIF
  orientation applied, EXIF GPS positions kept as local metres (:mod:`.gps`).
- :mod:`.video`: one camera's video, frames sampled and blurred ones dropped, poses unknown.
- :mod:`.nerfstudio`: a nerfstudio ``transforms.json`` (one camera, given poses) and its images;
  :mod:`.nerfstudio_export` writes a dataset back out in that format.
"""
