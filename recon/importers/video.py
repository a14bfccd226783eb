"""A video of one camera → a dataset with unknown poses (``bbcity import video``).

The video is decoded with ffmpeg (imageio-ffmpeg; any container and codec it reads, turned
upright by the stream's rotation tag as ffmpeg does). Its frames are split into **slots**:
``--fps N`` makes a slot of each 1/N second of video (default :data:`DEFAULT_FPS` per
second), ``--frames N`` N slots of equally many frames spread over the whole video. One frame
comes out of each slot, dropping blurred ones by the variance of the Laplacian of the grey
image (``cv2.Laplacian``, the sharpness measure of NeRF tools' frame filters: a blurred frame
has soft edges and a small variance). The rule (numbers: :class:`.video_config.VideoConfig`):

1. of the ``sharpest_of`` consecutive frames at the middle of the slot, the sharpest is kept
   (motion blur comes and goes from frame to frame with the hand's shake);
2. a kept frame whose sharpness is below ``min_relative_sharpness`` × the median of the kept
   frames' is dropped (the whole window was blurred: a fast pan);
3. so is one below ``min_sharpness`` (grey levels²): a featureless frame (a lens cap, a
   blank wall) that SfM could not place.

The frames become a one-camera dataset like a photo folder's (:mod:`.photos`): poses unknown
(``bbcity recon DATASET --poses sfm``), frames named ``frame_NNNNNN`` by their index in the
video (the first frame is 0). A video has no EXIF focal length: the intrinsics come from a
K file (``--intrinsics``, the format of :func:`.photos.read_intrinsics`, describing the
upright frames) and nothing else. ``--step-length`` gives the metres between consecutive
kept frames (a walk at 1.4 m/s at 2 frames per second: 0.7), SfM's scale; without it SfM's
units are arbitrary.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np

from core.fileio import DataFormatError, write_png

from .common import write_imported_dataset
from .photos import read_intrinsics, unposed_rig
from .video_config import DEFAULT_FPS, VideoConfig

__all__ = ["DEFAULT_FPS", "VideoConfig", "choose_frames", "import_video", "sharp_enough", "sharpness", "slot_window"]

logger = logging.getLogger(__name__)

#: Slack of the slot arithmetic (frame indices are integers, rates are not).
SLOT_EPS = 1e-9


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of an (h, w, 3) uint8 RGB image's grey levels: large for
    sharp edges, small for a blurred or featureless image."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def slot_window(k: int, frames_per_slot: float, sharpest_of: int) -> range:
    """The frame indices slot ``k`` chooses from: slot k holds the frames i with
    ⌊i / frames_per_slot⌋ = k (none when slots are shorter than a frame); its window is the
    ``sharpest_of`` of them at its middle (all of them when fewer)."""
    a = math.ceil(k * frames_per_slot - SLOT_EPS)
    b = math.ceil((k + 1) * frames_per_slot - SLOT_EPS)
    w = min(sharpest_of, max(b - a, 0))
    lo = a + (b - a - w) // 2
    return range(lo, lo + w)


def _ffmpeg_problem(error: BaseException) -> str:
    """The last line of ffmpeg's report in an imageio-ffmpeg error (what went wrong), or the error."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip() and not line.startswith("===")]
    return lines[-1] if lines else type(error).__name__


def _open(path: Path):
    """imageio-ffmpeg's frame generator and its metadata; DataFormatError naming ``path``
    when ffmpeg cannot read a video stream from it."""
    frames = imageio_ffmpeg.read_frames(str(path))
    try:
        meta = next(frames)
    except (OSError, RuntimeError, StopIteration, ValueError) as e:
        frames.close()
        raise DataFormatError(path, f"is not a video ffmpeg can decode ({_ffmpeg_problem(e)})") from None
    size = meta.get("size")
    if not size or min(size) <= 0:
        frames.close()
        raise DataFormatError(path, "has no video stream")
    return frames, meta


def _slots(path: Path, config: VideoConfig, meta: dict) -> tuple[float, int | None, str]:
    """Frames per slot, the number of slots (None: to the end of the video) and the rule in words."""
    if config.frames is not None:
        try:
            total, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
        except (OSError, RuntimeError, ValueError) as e:
            raise DataFormatError(path, f"is not a video ffmpeg can decode ({_ffmpeg_problem(e)})") from None
        if total < 1:
            raise DataFormatError(path, "holds no video frames")
        return total / config.frames, config.frames, f"{config.frames} frames spread over its {total}"
    fps = float(meta.get("fps") or 0.0)
    if not (math.isfinite(fps) and fps > 0):
        raise DataFormatError(path, "its frame rate is unknown: give --frames N instead of --fps")
    return fps / config.rate, None, f"{config.rate:g} per second of {fps:g} fps video"


def choose_frames(path: Path, config: VideoConfig, tmp: Path) -> tuple[list[int], list[Path], list[float], dict]:
    """Decode ``path`` once and keep the sharpest frame of each slot's window as a PNG in
    ``tmp``: (frame indices, PNG paths, sharpness of each, metadata with the "rule" in words).
    Blur rules 2 and 3 of the module doc are not applied yet."""
    frames, meta = _open(path)
    w, h = meta["size"]
    chosen: list[tuple[int, float, Path]] = []
    decoded = 0
    try:
        per_slot, slots, rule = _slots(path, config, meta)
        meta = {**meta, "rule": rule}
        k, window, best = 0, slot_window(0, per_slot, config.sharpest_of), None

        def keep_best():
            if best is not None:
                chosen.append((best[0], best[1], write_png(tmp / f"{best[0]:06d}.png", best[2])))

        for i, raw in enumerate(frames):
            decoded = i + 1
            while i >= window.stop and (slots is None or k < slots):  # past this slot's window: on to the next
                keep_best()
                k, best = k + 1, None
                window = slot_window(k, per_slot, config.sharpest_of)
            if slots is not None and k >= slots:
                break
            if i < window.start:
                continue
            image = np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3)
            score = sharpness(image)
            if best is None or score > best[1]:
                best = (i, score, image.copy())
        keep_best()  # the window the video ended in
    except RuntimeError as e:  # a frame ffmpeg could not decode (a truncated file)
        raise DataFormatError(path, f"could not be decoded to the end ({_ffmpeg_problem(e)})") from None
    finally:
        frames.close()
    if decoded == 0:
        raise DataFormatError(path, "holds no video frames")
    if not chosen:
        raise DataFormatError(path, f"its {decoded} frames are too few for {rule}: give --frames N")
    indices, scores, pngs = (list(v) for v in zip(*chosen))
    return indices, pngs, scores, meta


def sharp_enough(scores: list[float], config: VideoConfig) -> np.ndarray:
    """(n,) bool: the kept frames that pass blur rules 2 and 3 of the module doc."""
    s = np.asarray(scores, dtype=np.float64)
    if len(s) == 0:
        return np.zeros(0, dtype=bool)
    return (s >= config.min_relative_sharpness * np.median(s)) & (s >= config.min_sharpness)


def import_video(video: os.PathLike | str, out_dir: os.PathLike | str, config: VideoConfig = VideoConfig(),
                 progress=None) -> Path:
    """Import one camera's video into the dataset directory ``out_dir`` (new); its poses are
    unknown (``bbcity recon --poses sfm``)."""
    path, out = Path(video), Path(out_dir)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out")
    if not path.is_file():
        raise DataFormatError(path, "video file is missing")
    if config.intrinsics is None:
        raise DataFormatError(path, "a video carries no focal length: give --intrinsics K.txt (fx fy cx cy of its "
                                    "upright frames)")
    K, distortion = read_intrinsics(Path(config.intrinsics))
    with tempfile.TemporaryDirectory(prefix="bbcity-video-") as tmp:
        indices, pngs, scores, meta = choose_frames(path, config, Path(tmp))
        keep = sharp_enough(scores, config)
        if not keep.any():
            best = max(scores, default=0.0)
            raise DataFormatError(path, f"no frame is left after the blur filter (the sharpest has a Laplacian "
                                        f"variance of {best:.3g}, below {config.min_sharpness:g}: a blank or "
                                        "blurred video)")
        size = tuple(int(v) for v in meta["size"])
        rig = unposed_rig(K, distortion, size, Path(config.intrinsics))
        kept = np.flatnonzero(keep)
        source = {"kind": "video", "path": str(path.resolve()),
                  "intrinsics": f"file {Path(config.intrinsics).resolve()}", "poses": "unknown",
                  "step_length": None if config.step_length is None else float(config.step_length),
                  "gps_enu_m": None, "video_fps": float(meta.get("fps") or 0.0), "frames_from": meta["rule"],
                  "blur_filter": {"sharpest_of": config.sharpest_of,
                                  "min_relative_sharpness": config.min_relative_sharpness,
                                  "min_sharpness": config.min_sharpness,
                                  "dropped_frames": [int(indices[i]) for i in np.flatnonzero(~keep)]}}
        logger.info("%s: %d frames of %dx%d pixels kept (%s; %d dropped as blurred)", path, len(kept), size[0],
                    size[1], meta["rule"], int((~keep).sum()))
        return write_imported_dataset(out, rig, np.full((len(kept), 4, 4), np.nan), [[pngs[i]] for i in kept],
                                      source, names=[f"frame_{indices[i]:06d}" for i in kept], progress=progress)
