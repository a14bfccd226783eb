"""The settings of a novel-view evaluation (``bbcity eval``, :func:`render.evaluate.evaluate_views`)
and the names of its kinds of viewpoint."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from core.errors import InputError

from .seen import SeenConfig

#: Viewpoints at held-out capture poses ("on path") and moved sideways and up ("off path").
WHERE = ("on path", "off path")
#: Viewpoints of frames the textures came from: the ceiling a model reaches where it was made.
TRAINING = "training"


@dataclass(frozen=True)
class EvalConfig:
    views: int | None = None                # viewpoints: held-out frames when the model has them (synthetic: each also
                                            # off path); None: 8 synthetic, every held-out frame of a real capture
    size: tuple[int, int] | None = None     # image size (w, h); None: the dataset camera's
    sideways: float = 2.0                   # off-path views: moved this far back horizontally (m) …
    up: float = 1.0                         # … and this far up (m)
    poisson_depth: int = 10                 # octree depth of the "Poisson mesh" baseline
    workprecision_depths: tuple[int, ...] = (8, 9, 10, 11)  # Poisson depths of the work-precision diagram
    trim_quantile: float = 0.05             # Poisson vertices below this density quantile are removed
    seen: SeenConfig = field(default_factory=SeenConfig)     # the seen-pixel test
    panel_width: int = 320                  # side-by-side images: width of each panel (0: none written)
    model_sky: bool = True                  # draw models over their sky (False: on black, like the baselines)
    training_views: int = 4                 # also this many viewpoints of frames the textures came from ("training",
                                            # the capture camera itself; none when no frame was held out)
    near: float = 5.0                       # the near field: seen pixels of a synthetic view nearer than this (m)

    def __post_init__(self):
        if self.views is not None and self.views < 1:
            raise InputError(f"views must be ≥ 1, got {self.views}")
        if isinstance(self.views, bool) or (self.size is not None and any(isinstance(s, bool) for s in self.size)):
            raise InputError(f"views and size must be integers, got {self.views!r}, {self.size!r}")
        if self.size is not None and (len(self.size) != 2 or min(int(s) for s in self.size) < 1):
            raise InputError(f"size must be two positive integers (w, h), got {self.size}")
        if not all(1 <= int(d) <= 16 for d in (self.poisson_depth, *self.workprecision_depths)):
            raise InputError("Poisson depths must lie in [1, 16]")
        if not 0 <= self.trim_quantile < 1 or self.panel_width < 0:
            raise InputError("trim_quantile must be in [0, 1) and panel_width ≥ 0")
        if isinstance(self.training_views, bool) or self.training_views < 0:
            raise InputError(f"training_views must be an integer ≥ 0, got {self.training_views!r}")
        if not (math.isfinite(self.sideways) and math.isfinite(self.up)):
            raise InputError("sideways and up must be finite")
        if not (math.isfinite(self.near) and self.near > 0):
            raise InputError(f"near must be a finite distance > 0 (m), got {self.near}")
