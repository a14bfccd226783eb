"""Stereo (a rig of three, two or one camera) → fused coloured point cloud.

Public API: :func:`recon.stereo.disparity` (any rectified RGB pair),
:func:`recon.rectify.rectify_rig`, :func:`recon.trinocular.frame_depth`,
:func:`recon.motion_stereo.motion_depth` (one camera, neighbouring frames),
:func:`recon.pipeline.main` (the stage's entry point), the pose sources in
:mod:`recon.poses` (given), :mod:`recon.colmap_poses` (a COLMAP model) and :mod:`recon.sfm`
(pycolmap SfM), their alignment and errors in :mod:`recon.trajectory`, and the importers of
real captures in :mod:`recon.importers`.
"""
