"""The settings of ``bbcity bench`` (:class:`BenchConfig`) and the benchmark street's frame spacing."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from core.errors import InputError

if TYPE_CHECKING:
    from data_synth import RigConfig


SCENES = ("all", "street", "town", "executor", "city", "demo")

#: Metres between neighbouring frames of a pass along the benchmark streets.
FRAME_SPACING = 3.0


@dataclass(frozen=True)
class BenchConfig:
    """What one ``bbcity bench`` run measures, and on what."""

    quick: bool = False  # small inputs for a smoke run (under 3 minutes; "all" leaves the executors out)
    scene: str = "all"  # "street" (the pipeline and everything on its model), "town" (culling), "executor", "all",
    # or (not in "all") "city" or "demo" (make demo's steps and the layer's comparison, profiled)
    repeats: int = 3  # each timing is the median of this many runs
    workers: int = 2  # process pool size
    work: str | None = None  # a recon work directory (e.g. the default street's): the billboard sections use it
    street_length: float = 30.0  # metres: the 1× street of the pipeline runs
    scales: tuple[int, ...] = (1, 2, 4)  # street lengths of the scaling runs, in multiples of street_length
    city_scales: tuple[int, ...] = (1, 4, 16)  # the city-scale runs (scene "city", tile by tile), likewise
    city_gpu_budget_mb: int = 256  # the city runs' viewer: its GPU budget (the 1× street should fill it)
    city_lazy: bool = False  # the city runs' datasets cast on demand (no images stored, no ground-truth depth)

    def __post_init__(self):
        if self.scene not in SCENES:
            raise InputError(f"scene must be one of {SCENES}, got {self.scene!r}")
        if not (0 < self.street_length < float("inf") and self.scales and all(int(s) >= 1 for s in self.scales)
                and self.repeats >= 1 and self.workers >= 1 and self.city_gpu_budget_mb >= 1):
            raise InputError(f"invalid BenchConfig: {self}")

    @classmethod
    def quick_config(cls, **overrides) -> "BenchConfig":
        """The smoke run's settings: a 6 m street at 1× and 2×, one repeat."""
        return cls(**{"quick": True, "repeats": 1, "street_length": 6.0, "scales": (1, 2), **overrides})

    def rig(self) -> "RigConfig":
        """The capture rig of the street runs: the default rig (:class:`data_synth.RigConfig`,
        what ``make demo`` builds), at half its width and height for quick runs (the same
        aspect ratio, field of view and pitch)."""
        from dataclasses import replace

        from data_synth import RigConfig

        rig = RigConfig()
        return replace(rig, width=rig.width // 2, height=rig.height // 2) if self.quick else rig
