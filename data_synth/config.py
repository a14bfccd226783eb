"""The generator's settings: :class:`SynthConfig`, their JSON form in ``dataset.json``, and
the scene and capture path they make.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from core.errors import InputError

from .rig import RigConfig, drive_path, orbit_path
from .scene import Scene
from .street import StreetConfig, build_street, free_building, street_settings
from .town import TownConfig, build_town, street_centres

SCENES = ("street", "town")
#: Capture paths: "drive" along the street (and back), or "orbit": one loop round a free-standing building.
PATHS = ("drive", "orbit")
#: An orbit keeps this far (metres) from the corners of its building and from anything else.
ORBIT_CLEARANCE_M = 2.0


MAX_SPP = 16  # supersampling per pixel axis at most (256 rays a pixel)


@dataclass(frozen=True)
class SynthConfig:
    scene: str = "street"  # "street" or "town"
    street: StreetConfig = field(default_factory=StreetConfig)  # used when scene == "street"
    town: TownConfig = field(default_factory=TownConfig)  # used when scene == "town"
    rig: RigConfig = field(default_factory=RigConfig)  # cameras and their mounting
    frames: int = 100  # frames per pass, evenly spaced along the path
    return_pass: bool = True  # a drive: back in the other lane so both sides are captured (an orbit is one loop)
    lane_offset: float = 1.75  # a drive's distance from the street's centre line, metres
    town_path_length: float = 300.0  # town: length of the drive along its middle street, metres
    spp: int = 2  # supersampling per pixel axis (spp² colour rays per pixel)
    ground_truth_depth: bool = True  # write gt/depth and gt/ids for every image
    lazy: bool = False  # write no images: cast each frame when it is read (data_synth.lazy)
    path: str = "drive"  # "drive" (along the street) or "orbit" (one loop round the street's free-standing building)
    orbit_radius: float = 25.0  # orbit: the circle's radius about the building's centre, metres

    def __post_init__(self):
        if self.scene not in SCENES:
            raise InputError(f"unknown scene {self.scene!r}; expected one of {SCENES}")
        if self.path not in PATHS:
            raise InputError(f"SynthConfig.path must be one of {PATHS}, got {self.path!r}")
        for name in ("frames", "spp"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InputError(f"SynthConfig.{name} must be an integer ≥ 1, got {value!r}")
        if self.spp > MAX_SPP:  # spp² rays a pixel: a lazy dataset's reader would cast for ever
            raise InputError(f"SynthConfig.spp must be at most {MAX_SPP} (spp² rays a pixel), got {self.spp}")
        for name in ("lane_offset", "town_path_length", "orbit_radius"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InputError(f"SynthConfig.{name} must be a finite number, got {value!r}")
        if self.town_path_length <= 0:
            raise InputError(f"SynthConfig.town_path_length must be positive, got {self.town_path_length}")
        if self.orbit_radius <= 0:
            raise InputError(f"SynthConfig.orbit_radius must be positive metres, got {self.orbit_radius}")
        if self.path == "orbit":
            self._check_orbit()
        for name in ("return_pass", "ground_truth_depth", "lazy"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"SynthConfig.{name} must be true or false, got {getattr(self, name)!r}")

    def _check_orbit(self) -> None:
        """An orbit circles the street's free-standing building (:func:`street.free_building`)
        clear of it and of everything else by ORBIT_CLEARANCE_M; ValueError otherwise."""
        r, gap = self.orbit_radius, ORBIT_CLEARANCE_M
        if self.scene != "street":
            raise InputError("path \"orbit\" needs the street scene: the town's houses stand in closed rows, "
                             "with no free path round one")
        if self.street.square < r + gap:
            raise InputError(f"path \"orbit\" of radius {r:g} m needs the street's open square (StreetConfig.square) "
                             f"to reach at least {r + gap:g} m from the building's centre, got {self.street.square:g}")
        lo, hi = free_building(self.street)
        corner = float(np.hypot(*(hi - lo))) / 2
        if r < corner + gap:
            raise InputError(f"SynthConfig.orbit_radius (--orbit-radius) {r:g} m passes within {gap:g} m of the "
                             f"free-standing building's corners (a {hi[0] - lo[0]:.1f} × {hi[1] - lo[1]:.1f} m "
                             f"footprint): at least {math.ceil((corner + gap) * 10) / 10:g} m")

    @property
    def passes(self) -> int:
        """Passes of the capture: an orbit's one loop, a drive's one or two (return_pass)."""
        return 2 if self.path == "drive" and self.return_pass else 1

    @property
    def path_length(self) -> float:
        """Metres the rig moves per pass: the street's length, the town drive's, or the
        orbit's circumference."""
        if self.path == "orbit":
            return 2 * math.pi * self.orbit_radius
        return float(self.street.length if self.scene == "street" else self.town_path_length)


def frames_for_spacing(path_length: float, spacing: float, closed: bool = False) -> int:
    """Frames per pass that put neighbouring frames at most ``spacing`` metres apart along a
    pass of ``path_length`` metres: ⌈length / spacing⌉ + 1 with both ends included, or
    ⌈length / spacing⌉ round a ``closed`` loop (an orbit: the last frame's neighbour is the first)."""
    if not (math.isfinite(path_length) and path_length > 0 and math.isfinite(spacing) and spacing > 0):
        raise InputError(f"path length and frame spacing must be positive metres, got {path_length}, {spacing}")
    return int(math.ceil(path_length / spacing - 1e-9)) + (0 if closed else 1)


def _from_dict(cls, data: dict):
    """Rebuild a flat config dataclass from JSON (lists back to tuples)."""
    fields = cls.__dataclass_fields__
    unknown = set(data) - set(fields)
    if unknown:
        raise InputError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


def build_scene(name: str, config: dict) -> Scene:
    """Generate the scene ``name`` ("street" or "town") from its configuration dict."""
    if name == "street":
        return build_street(_from_dict(StreetConfig, config))
    if name == "town":
        return build_town(_from_dict(TownConfig, config))
    raise InputError(f"unknown scene {name!r}; expected one of {SCENES}")


def capture_path(cfg: SynthConfig) -> tuple[np.ndarray, np.ndarray]:
    """The rig's trajectory: world_from_rig (n, 4, 4) float64 and pass index (n,) int32."""
    if cfg.path == "orbit":  # (a street: SynthConfig checks it)
        lo, hi = free_building(cfg.street)
        return orbit_path((lo + hi) / 2, cfg.orbit_radius, cfg.frames)
    if cfg.scene == "street":
        return drive_path(0.0, cfg.street.length, 0.0, cfg.frames, cfg.lane_offset, cfg.return_pass)
    centres = street_centres(cfg.town)
    y = centres[len(centres) // 2 if cfg.town.path_street < 0 else cfg.town.path_street]
    half = cfg.town_path_length / 2
    # narrow streets: drive near the middle, so that the facades are not at arm's length
    return drive_path(-half, half, y, cfg.frames, cfg.town.street_width / 8, cfg.return_pass)


def config_json(cfg: SynthConfig) -> dict:
    """The settings as ``dataset.json`` stores them (``"synth"``): what makes a dataset's bytes,
    the fields added since the first datasets left out at their old values."""
    data = json.loads(json.dumps(asdict(cfg)))
    data["street"] = json.loads(json.dumps(street_settings(cfg.street)))  # a street without a square keeps its bytes
    if data["path"] == "drive":  # drives keep the bytes they had before orbits
        del data["path"]
        if data["orbit_radius"] == SynthConfig.orbit_radius:
            del data["orbit_radius"]
    if data["rig"].get("distortion") == "none":  # pinhole datasets keep the bytes they had before lenses
        del data["rig"]["distortion"]
    if not data["lazy"]:  # stored datasets keep the bytes they had before lazy ones
        del data["lazy"]
    return data


def config_from_json(data: dict) -> SynthConfig:
    """Inverse of the configuration stored in ``dataset.json``."""
    data = dict(data)
    nested = {"street": StreetConfig, "town": TownConfig, "rig": RigConfig}
    for key, cls in nested.items():
        if key in data:
            data[key] = _from_dict(cls, data[key])
    return _from_dict(SynthConfig, data)
