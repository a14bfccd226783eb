"""Synthetic street scenes with ground truth: geometry, procedural textures,
the camera rig (three cameras by default; lenses), a CPU ray-cast renderer and the dataset format.

Public API:

- datasets: ``write_dataset(SynthConfig, out_dir, executor=None)`` writes a stored dataset, or a
  *lazy* one with ``SynthConfig(lazy=True)`` (no images: each frame is cast when read, the
  same bytes); ``load_dataset(dir) -> Dataset``; ``Dataset.image(f, c)``, ``gt_depth``,
  ``gt_ids`` read both kinds; ``read_image(path, size)`` reads a raw image by the path
  ``Dataset.image_path`` gives (a PNG, or a lazy dataset's frame cast on demand);
  ``frames_for_spacing(length, spacing, closed=False)`` → frames per pass (``closed``: an
  orbit's loop); ``SynthConfig(path="orbit")`` circles a street's free-standing building
  (``StreetConfig(square=...)``) instead of driving the street.
- scenes: ``load_scene(dataset_dir) -> Scene`` (the whole scene, regenerated and checked against
  the stored digest); ``scene_section(dataset_or_settings, lo, hi) -> Scene``: the objects whose
  bounds meet the world box [lo, hi] ((3,) or (2,) x, y; metres; ±inf allowed), generated
  without the rest, with the whole scene's object ids and object table — evaluation of a long
  street goes tile by tile with it; ``section_reference(scene, lo, hi)`` filters a whole scene
  the same way; ``scene_digest(name, config)`` digests a scene without holding it.
- rendering: ``Renderer(scene)``, ``truth_view(scene, K, world_from_cam, size)``.
"""

from .dataset import (Dataset, SynthConfig, build_scene, frames_for_spacing, load_dataset, load_scene,
                      write_dataset)
from .lazy import LazyImages, read_image
from .raycast import Renderer, RenderResult, truth_view
from .rig import Rig, RigConfig, make_rig
from .scene import Kind, Scene
from .section import scene_digest, scene_section, section_reference
from .street import StreetConfig, build_street
from .town import TownConfig, build_town

__all__ = [
    "Dataset", "Kind", "LazyImages", "Renderer", "RenderResult", "Rig", "RigConfig", "Scene",
    "StreetConfig", "SynthConfig", "TownConfig", "build_scene", "build_street", "build_town",
    "frames_for_spacing", "load_dataset", "load_scene", "make_rig", "read_image", "scene_digest",
    "scene_section", "section_reference", "truth_view", "write_dataset",
]
