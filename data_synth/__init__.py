"""Synthetic street scenes with ground truth: geometry, procedural textures,
the camera rig (three cameras by default; lenses), a CPU ray-cast renderer and the dataset format."""

from .dataset import Dataset, SynthConfig, build_scene, load_dataset, load_scene, write_dataset
from .raycast import Renderer, RenderResult, truth_view
from .rig import Rig, RigConfig, make_rig
from .scene import Kind, Scene
from .street import StreetConfig, build_street
from .town import TownConfig, build_town

__all__ = [
    "Dataset", "Kind", "Renderer", "RenderResult", "Rig", "RigConfig", "Scene",
    "StreetConfig", "SynthConfig", "TownConfig", "build_scene", "build_street", "build_town",
    "load_dataset", "load_scene", "make_rig", "truth_view", "write_dataset",
]
