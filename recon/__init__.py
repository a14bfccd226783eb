"""Three-camera stereo, fusion and poses (built by a later issue)."""
