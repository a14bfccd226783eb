"""The settings of ``bbcity import video`` (:mod:`.video`), apart from it so that the command
line takes its defaults from them without loading the importer (OpenCV, Open3D)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from core.errors import InputError

#: Frames per second of video kept when neither a rate nor a count is given.
DEFAULT_FPS = 2.0


@dataclass(frozen=True)
class VideoConfig:
    """Which frames of a video become the dataset's.

    The video's frames fall into slots: one per 1/``fps`` second (``fps`` None and ``frames``
    None: DEFAULT_FPS), or ``frames`` slots of equally many frames over the whole video. Of
    each slot the sharpest — the largest variance of the Laplacian of the grey image — of
    the ``sharpest_of`` consecutive frames at its middle is kept. Then the blur filter drops
    a kept frame whose sharpness is below ``min_relative_sharpness`` × the median of the kept
    frames' (its whole window was blurred: a fast pan), or below ``min_sharpness`` (a
    featureless frame: a lens cap, a blank wall).
    """

    intrinsics: Path | None = None  # K file (photos' format) of the upright frames; required (a video has no EXIF)
    fps: float | None = None  # frames kept per second of video (None: DEFAULT_FPS unless frames is given)
    frames: int | None = None  # instead of fps: this many frames spread evenly over the video
    sharpest_of: int = 5  # of each slot, the sharpest of this many consecutive frames at its middle (1: no choice)
    min_relative_sharpness: float = 0.3  # drop a kept frame below this share of the kept frames' median sharpness
    min_sharpness: float = 2.0  # drop a frame whose Laplacian variance (grey levels²) is below this: featureless
    step_length: float | None = None  # metres between consecutive kept frames, SfM's scale (None: arbitrary units)

    def __post_init__(self):
        if self.fps is not None and self.frames is not None:
            raise InputError("give --fps or --frames, not both")
        if self.fps is not None and (isinstance(self.fps, bool) or not (math.isfinite(self.fps) and self.fps > 0)):
            raise InputError(f"--fps must be a positive number of frames per second, got {self.fps!r}")
        if self.frames is not None and (isinstance(self.frames, bool) or not isinstance(self.frames, int)
                                        or self.frames < 1):
            raise InputError(f"--frames must be an integer ≥ 1, got {self.frames!r}")
        if isinstance(self.sharpest_of, bool) or not isinstance(self.sharpest_of, int) or self.sharpest_of < 1:
            raise InputError(f"sharpest_of must be an integer ≥ 1, got {self.sharpest_of!r}")
        if not (0.0 <= self.min_relative_sharpness < 1.0):
            raise InputError(f"min_relative_sharpness must lie in [0, 1), got {self.min_relative_sharpness!r}")
        if not (math.isfinite(self.min_sharpness) and self.min_sharpness >= 0.0):
            raise InputError(f"min_sharpness must be a finite number ≥ 0, got {self.min_sharpness!r}")
        if self.step_length is not None and not (math.isfinite(self.step_length) and self.step_length > 0):
            raise InputError(f"--step-length must be a positive number of metres, got {self.step_length!r}")

    @property
    def rate(self) -> float:
        """Frames kept per second of video, when the frames are chosen by rate."""
        return DEFAULT_FPS if self.fps is None else float(self.fps)
