"""Synthetic street scenes with ground truth: geometry, procedural textures, the camera rig
(three cameras by default; lenses), a CPU ray-cast renderer, and the writer of datasets in
the capture format (:mod:`capture`, which reads them).

Public API:

- datasets: ``write_dataset(SynthConfig, out_dir, executor=None)`` writes a stored dataset, or a
  *lazy* one with ``SynthConfig(lazy=True)`` (no images: each frame is cast when read, the
  same bytes; importing this package registers the cast as the image source "lazy" of
  :mod:`capture.sources`); ``capture.load_dataset(dir)`` reads both kinds, and
  ``capture.read_image(path, size)`` a raw image by the path ``Dataset.image_path`` gives;
  ``frames_for_spacing(length, spacing, closed=False)`` → frames per pass (``closed``: an
  orbit's loop); ``SynthConfig(path="orbit")`` circles a street's free-standing building
  (``StreetConfig(square=...)``) instead of driving the street.
- scenes: ``load_scene(dataset_dir) -> Scene`` (the whole scene, regenerated and checked against
  the stored digest); ``stores_truth(dataset_dir)``: its stored images are ``truth_view``'s renders; ``scene_section(dataset_or_settings, lo, hi) -> Scene``: the objects whose
  bounds meet the world box [lo, hi] ((3,) or (2,) x, y; metres; ±inf allowed), generated
  without the rest, with the whole scene's object ids and object table — evaluation of a long
  street goes tile by tile with it; ``section_reference(scene, lo, hi)`` filters a whole scene
  the same way; ``scene_digest(name, config)`` digests a scene without holding it.
- rendering: ``Renderer(scene)``, ``truth_view(scene, K, world_from_cam, size)``.
"""


from .config import SynthConfig, build_scene, frames_for_spacing
from .dataset import load_scene, stores_truth, write_dataset
from .lazy import LazyImages
from .raycast import Renderer, RenderResult, truth_view
from .rig import RigConfig, make_rig
from .scene import Kind, Scene
from .section import scene_digest, scene_section, section_reference
from .street import StreetConfig, build_street
from .town import TownConfig, build_town

__all__ = [
    "Kind", "LazyImages", "Renderer", "RenderResult", "RigConfig", "Scene", "StreetConfig", "SynthConfig",
    "TownConfig", "build_scene", "build_street", "build_town", "frames_for_spacing", "load_scene", "make_rig",
    "scene_digest", "scene_section", "section_reference", "stores_truth", "truth_view", "write_dataset",
]
