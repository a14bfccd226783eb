"""Three-camera stereo → fused coloured point cloud.

Public API: :func:`recon.stereo.disparity` (any rectified RGB pair),
:func:`recon.rectify.rectify_rig`, :func:`recon.trinocular.frame_depth`,
:func:`recon.pipeline.main` (the stage's entry point) and the pose sources in
:mod:`recon.poses`.
"""
