"""Scene sections: the part of a scene inside a world box, generated without the rest.

A generator (:func:`street.generate_street`, :func:`town.generate_town`) walks its random
sequence in a fixed order and hands every object to a :class:`scene.MeshBuilder`. A section
walks it twice: a bounds pass keeps the object table (kind, seed, bounding box of every
object; about 54 bytes per object, some 30 bytes per metre of street), a second pass keeps
the triangles of the objects whose bounds meet the box. So a section holds exactly the
whole scene's triangles of those objects (same vertices, same order, same object ids: the
object table stays the whole scene's), and its triangles and ray-casting structure do not
grow with the street: the street's ground, road and sidewalks are one long box or quad each
and are in every section whole; a building, pillar, pole or beam is in when its box meets
the section's. Walking the sequence takes time in proportion to the street (about 15 ms
per kilometre) but keeps no geometry outside the box.

The same walk feeds the mesh's arrays to SHA-256 one primitive at a time, giving
:meth:`scene.Scene.digest` of a scene that is never held whole (:func:`scene_digest`).

:func:`section_reference` filters a whole scene by the same rule: the reference the tests
compare sections with.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import OrderedDict
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, read_json

from .scene import BoundsBuilder, DigestBuilder, MeshBuilder, Scene, SectionBuilder
from .street import StreetConfig, generate_street, street_settings
from .town import TownConfig, generate_town

#: scene name → (configuration class, generator filling a MeshBuilder)
GENERATORS = {"street": (StreetConfig, generate_street), "town": (TownConfig, generate_town)}

SCENE_FORMAT = "bbcity-scene"

#: object tables kept per process: (name, config JSON) → (kind, seed, bounds, triangles)
_TABLES: OrderedDict = OrderedDict()
_TABLES_KEPT = 4
#: (name, config JSON, digest) triples whose streamed digest this process has checked
_VERIFIED: set = set()


def _config_object(name: str, config: dict):
    """The generator's configuration dataclass from its JSON dict (lists back to tuples)."""
    if name not in GENERATORS:
        raise InputError(f"unknown scene {name!r}; expected one of {tuple(GENERATORS)}")
    cls = GENERATORS[name][0]
    if not isinstance(config, dict):
        raise InputError(f"a {name} configuration must be a JSON object, got {type(config).__name__}")
    unknown = set(config) - set(cls.__dataclass_fields__)
    if unknown:
        raise InputError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()})


def scene_settings(source) -> tuple[str, dict, str | None]:
    """(scene name, generator configuration dict, stored digest or None) of ``source``: a
    dataset directory or :class:`capture.dataset.Dataset` (its ``gt/scene.json``), a
    :class:`data_synth.SynthConfig`, a :class:`StreetConfig` or :class:`TownConfig`, or a
    ``(name, config dict)`` pair. A dataset without a readable ``gt/scene.json`` raises
    DataFormatError naming it."""
    if isinstance(source, StreetConfig):
        return "street", street_settings(source), None
    if isinstance(source, TownConfig):
        return "town", asdict(source), None
    if isinstance(source, tuple) and len(source) == 2 and isinstance(source[0], str):
        return source[0], dict(source[1]), None
    if hasattr(source, "street") and hasattr(source, "town") and hasattr(source, "scene"):  # a SynthConfig
        street = source.scene == "street"
        return source.scene, street_settings(source.street) if street else asdict(source.town), None
    if not isinstance(source, (str, os.PathLike)):  # (a Dataset is path-like: its directory)
        raise TypeError(f"expected a dataset, its directory or scene settings, got {type(source).__name__}")
    path = Path(os.fspath(source)) / "gt" / "scene.json"
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != SCENE_FORMAT:
        raise DataFormatError(path, f"not a scene file (expected \"format\": \"{SCENE_FORMAT}\")")
    name, config, digest = data.get("scene"), data.get("config"), data.get("digest")
    if name not in GENERATORS or not isinstance(config, dict) or not isinstance(digest, str):
        raise DataFormatError(path, "needs \"scene\" (street or town), \"config\" (an object) and \"digest\"")
    return name, config, digest


def _key(name: str, config: dict) -> tuple[str, str]:
    return name, json.dumps(config, sort_keys=True)


def object_table(name: str, config: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The whole scene's object table without its geometry: object_kind (k,) int16,
    object_seed (k,) uint32, object_bounds (k, 2, 3) float64 (equal to :class:`Scene`'s) and
    the number of triangles. Kept per process for the few most recent scenes."""
    key = _key(name, config)
    if key in _TABLES:
        _TABLES.move_to_end(key)
        return _TABLES[key]
    cfg = _config_object(name, config)
    builder = GENERATORS[name][1](cfg, BoundsBuilder())
    table = (*builder.tables(), builder.num_triangles)
    _TABLES[key] = table
    while len(_TABLES) > _TABLES_KEPT:
        _TABLES.popitem(last=False)
    return table


def scene_digest(name: str, config: dict) -> str:
    """:meth:`Scene.digest` of the scene ``name`` with ``config``, computed by walking the
    generator four times (object table, vertices, triangles, triangle objects) without ever
    holding the mesh."""
    cfg = _config_object(name, config)
    generate = GENERATORS[name][1]
    kind, seed, bounds, _ = object_table(name, config)
    h = hashlib.sha256()
    for part in DigestBuilder.PARTS:  # the order of Scene.digest
        generate(cfg, DigestBuilder(part, h))
    for a in (kind, seed, bounds):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def verify_digest(name: str, config: dict, digest: str, path: os.PathLike | str) -> None:
    """DataFormatError naming ``path`` unless the generator still makes the scene whose digest
    is ``digest`` (checked once per process for each scene)."""
    key = (*_key(name, config), digest)
    if key in _VERIFIED:
        return
    if scene_digest(name, config) != digest:
        raise DataFormatError(path, "the re-created scene differs from the one the dataset was made with "
                                    "(generator changed since)")
    _VERIFIED.add(key)


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """(3,) float64 lo and hi from 2 (x, y; z unbounded) or 3 numbers each; ValueError when malformed."""
    lo = np.asarray(lo, dtype=np.float64).reshape(-1)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1)
    if lo.shape != hi.shape or len(lo) not in (2, 3):
        raise InputError(f"a section box needs lo and hi of 2 (x, y) or 3 (x, y, z) numbers each, got "
                         f"{lo.shape} and {hi.shape}")
    if np.isnan(lo).any() or np.isnan(hi).any() or np.any(lo > hi):
        raise InputError(f"a section box needs lo ≤ hi (±inf allowed), got {lo.tolist()} and {hi.tolist()}")
    if len(lo) == 2:
        lo, hi = np.append(lo, -np.inf), np.append(hi, np.inf)
    return lo, hi


def objects_in_box(bounds: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(k,) bool: the objects whose bounds (k, 2, 3) meet the closed box [lo, hi] (3,)."""
    return np.all(bounds[:, 0] <= hi, axis=1) & np.all(bounds[:, 1] >= lo, axis=1)


def scene_section(source, lo, hi) -> Scene:
    """The part of a scene in the world box [lo, hi], generated without the rest.

    source: what :func:`scene_settings` takes (a dataset or its directory: the scene its
    ``gt/scene.json`` describes, whose digest is checked once per process; or settings).
    lo, hi: (3,) float64 box corners in world metres, or (2,) x, y (z unbounded); ±inf allowed.
    Returns a :class:`Scene` whose ``section`` is the box: the triangles of every object whose
    bounds meet the box, exactly as the whole scene holds them (same vertices in the same
    order, same object ids), and the whole scene's object table. Its triangles do not grow
    with the street; a box holding everything gives the whole scene's arrays.
    """
    name, config, digest = scene_settings(source)
    lo, hi = _box(lo, hi)
    if digest is not None:
        verify_digest(name, config, digest, Path(os.fspath(source)) / "gt" / "scene.json")
    box = (tuple(float(v) for v in lo), tuple(float(v) for v in hi))
    generate = GENERATORS[name][1]
    if np.all(lo == -np.inf) and np.all(hi == np.inf):  # everything: one walk
        return replace(generate(_config_object(name, config), MeshBuilder()).build(name, config), section=box)
    kind, seed, bounds, _ = object_table(name, config)
    keep = objects_in_box(bounds, lo, hi)
    builder = generate(_config_object(name, config), SectionBuilder(keep))
    return builder.build_section(name, config, bounds, box)


def section_reference(scene: Scene, lo, hi) -> Scene:
    """Slow reference of :func:`scene_section`: filter a whole ``scene`` (the same rule: the
    triangles of objects whose bounds meet the box, vertices renumbered in order)."""
    lo, hi = _box(lo, hi)
    keep = objects_in_box(scene.object_bounds, lo, hi)
    tri_keep = keep[scene.triangle_object]
    used = np.zeros(len(scene.vertices), dtype=bool)
    used[scene.triangles[tri_keep].reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    return Scene(scene.name, scene.config, scene.vertices[used],
                 new_index[scene.triangles[tri_keep]].astype(np.int32), scene.triangle_object[tri_keep],
                 scene.object_kind, scene.object_seed, scene.object_bounds,
                 section=(tuple(float(v) for v in lo), tuple(float(v) for v in hi)))
