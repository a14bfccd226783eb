"""Scene sections and lazy datasets (data_synth.section, data_synth.lazy)."""

from __future__ import annotations

import hashlib
import json
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from core import DataFormatError
from capture import load_dataset, read_image
from capture import sources as sources_module
from data_synth import (RigConfig, StreetConfig, SynthConfig, TownConfig, build_street, build_town,
                        frames_for_spacing, load_scene, scene_digest, scene_section, section_reference, write_dataset)
from data_synth import lazy as lazy_module
from data_synth.config import capture_path
from data_synth.raycast import Renderer

from .conftest import tiny_config

SCENE_FIELDS = ("vertices", "triangles", "triangle_object", "object_kind", "object_seed", "object_bounds")


def _same_scene(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in SCENE_FIELDS)


def _forget_casts():
    """Empty this process's lazy caches (as a fresh process starts)."""
    for cache in (lazy_module._STATES, lazy_module._RENDERERS, lazy_module._RESULTS, sources_module._SOURCES,
                  lazy_module._CACHES):
        cache.clear()


# ---------------------------------------------------------------------------- sections


@pytest.mark.parametrize("lo, hi", [
    ((100.0, -np.inf), (250.0, np.inf)),        # an x window, as lazy frames use
    ((0.0, 0.0, 0.0), (50.0, 10.0, 3.0)),       # a 3-D box: one side, below 3 m
    ((-1e9, -1e9), (1e9, 1e9)),                 # everything
    ((390.0, -5.0), (1000.0, 5.0)),             # past the street's end
    ((5000.0, 0.0), (6000.0, 1.0)),             # nothing
])
def test_street_section_is_the_whole_street_filtered(lo, hi):
    cfg = StreetConfig(length=400.0, seed=2)
    section = scene_section(cfg, lo, hi)
    assert _same_scene(section, section_reference(build_street(cfg), lo, hi))
    assert section.section == (tuple(float(v) for v in (*lo, *(() if len(lo) == 3 else (-np.inf,)))),
                               tuple(float(v) for v in (*hi, *(() if len(hi) == 3 else (np.inf,)))))


def test_a_box_around_everything_gives_the_whole_scene_and_its_digest():
    cfg = StreetConfig(length=120.0, seed=5)
    whole = build_street(cfg)
    section = scene_section(cfg, (-np.inf, -np.inf, -np.inf), (np.inf, np.inf, np.inf))
    assert _same_scene(section, whole) and section.digest() == whole.digest()


def test_town_section_keeps_houses_whole():
    cfg = TownConfig(size=160.0, seed=1)
    whole = build_town(cfg)
    lo, hi = (-30.0, -20.0, 4.0), (10.0, 25.0, np.inf)  # cuts through walls: roofs and walls stay together
    section = scene_section(cfg, lo, hi)
    assert _same_scene(section, section_reference(whole, lo, hi))
    kept = np.unique(section.triangle_object)
    assert len(kept) and all(np.sum(section.triangle_object == k) == np.sum(whole.triangle_object == k) for k in kept)


def test_streamed_digest_equals_the_scene_digest():
    for name, cfg, build in (("street", StreetConfig(length=700.0, seed=4), build_street),
                             ("town", TownConfig(size=160.0, seed=2), build_town)):
        from dataclasses import asdict
        assert scene_digest(name, asdict(cfg)) == build(cfg).digest()


def test_a_section_does_not_grow_with_the_street():
    window = ((100.0, -np.inf), (220.0, np.inf))
    counts = [len(scene_section(StreetConfig(length=length), *window).triangles) for length in (240.0, 2000.0, 20000.0)]
    whole = len(build_street(StreetConfig(length=2000.0)).triangles)
    assert max(counts) < 1.5 * min(counts) and max(counts) < whole / 5


def test_section_boxes_are_checked():
    for lo, hi in (((0.0,), (1.0,)), ((0.0, 1.0), (1.0, 0.0)), ((np.nan, 0.0), (1.0, 1.0)), ((0, 0), (1, 1, 1))):
        with pytest.raises(ValueError, match="section box"):
            scene_section(StreetConfig(length=50.0), lo, hi)


# ---------------------------------------------------------------------------- the reach


@pytest.mark.parametrize("distortion", ["none", "fisheye"])
def test_frames_cast_from_sections_show_the_whole_street(distortion, tmp_path):
    """Each ray of a section-cast frame meets what it meets in the whole street: the same depth
    everywhere; ids and colour may differ only where two objects are hit at one distance exactly
    (the shared edge of flush neighbouring facades)."""
    cfg = SynthConfig(street=StreetConfig(length=400.0, seed=1), frames=9, spp=1, lazy=True,
                      rig=RigConfig(width=52, height=92, distortion=distortion))  # the default 115° portrait rig
    ds = load_dataset(write_dataset(cfg, tmp_path / "d", progress=False))
    assert 20.0 < ds.lazy.reach < 80.0
    whole = Renderer(build_street(cfg.street))
    poses, _ = capture_path(cfg)
    rig = ds.rig
    _forget_casts()
    ties = 0
    for f in range(len(poses)):
        _, lo, hi = ds.lazy.section_box(f)
        assert hi[0] - lo[0] < 250.0  # a strict part of the 450 m the street's objects span
        for c in range(rig.num_cameras):
            a = whole.render(rig.raw_K(c), rig.world_from_cam(poses[f], c), rig.sizes[c], spp=1,
                             distortion=rig.distortion(c))
            b = ds.lazy.render(f, c, keep=False)
            np.testing.assert_array_equal(a.depth, b.depth)  # the same distance on every ray
            ties += int(((a.ids != b.ids) | (a.rgb != b.rgb).any(axis=-1)).sum())
    assert ties <= 5


# ---------------------------------------------------------------------------- lazy datasets


@pytest.fixture(scope="module")
def stored_and_lazy(tmp_path_factory):
    """A 150 m street (sections are strict parts of it) written stored and lazy."""
    root = tmp_path_factory.mktemp("lazy")
    cfg = tiny_config(street=StreetConfig(length=150.0, seed=3), frames=3)
    stored = write_dataset(cfg, root / "stored", progress=False)
    lazy = write_dataset(replace(cfg, lazy=True), root / "lazy", progress=False)
    return load_dataset(stored), load_dataset(lazy)


def test_lazy_dataset_holds_settings_not_pixels(stored_and_lazy):
    stored, lazy = stored_and_lazy
    assert lazy.lazy is not None and stored.lazy is None
    assert not (lazy.root / "images").exists()
    assert sorted(p.relative_to(lazy.root).as_posix() for p in (lazy.root / "gt").rglob("*")) == ["gt/scene.json"]
    for name in ("rig.json", "poses.json", "colmap/cameras.txt", "colmap/images.txt", "colmap/frames.txt"):
        assert (lazy.root / name).read_bytes() == (stored.root / name).read_bytes(), name
    a, b = (json.loads((d.root / "gt" / "scene.json").read_text()) for d in (stored, lazy))
    assert a["digest"] == b["digest"] and a["config"] == b["config"]
    manifest = json.loads((lazy.root / "dataset.json").read_text())
    assert manifest["images"] == "lazy" and manifest["lazy"]["reach_m"] > 0 and manifest["frames"] == 6
    assert "lazy" not in json.loads((stored.root / "dataset.json").read_text())["synth"]  # stored bytes as before


def test_lazy_frames_equal_the_stored_ones(stored_and_lazy):
    stored, lazy = stored_and_lazy
    _forget_casts()
    assert lazy.lazy.section_box(0)[2][0] < 150.0  # sections are strict parts of the street
    for f in reversed(range(stored.num_frames)):  # any order
        for c in range(stored.rig.num_cameras):
            np.testing.assert_array_equal(lazy.image(f, c), stored.image(f, c))
            np.testing.assert_array_equal(lazy.gt_depth(f, c), stored.gt_depth(f, c))
            np.testing.assert_array_equal(lazy.gt_ids(f, c), stored.gt_ids(f, c))
            np.testing.assert_array_equal(read_image(lazy.image_path(f, c), lazy.rig.sizes[c]),
                                          read_image(stored.image_path(f, c), stored.rig.sizes[c]))


def test_billboard_views_read_lazy_images(stored_and_lazy):
    from billboards.views import views_from_dataset

    stored, lazy = stored_and_lazy
    a, b = views_from_dataset(stored), views_from_dataset(lazy)
    for i in (0, len(a) - 1):
        np.testing.assert_array_equal(a.image(i), b.image(i))


def _frame_digest(args) -> str:
    root, f, c = args
    ds = load_dataset(root)
    return hashlib.sha256(ds.image(f, c).tobytes() + ds.gt_depth(f, c).tobytes()).hexdigest()


def test_lazy_frames_are_the_same_bytes_in_any_process(stored_and_lazy):
    _, lazy = stored_and_lazy
    jobs = [(str(lazy.root), f, c) for f in (5, 0, 3) for c in (2, 0)]
    _forget_casts()
    here = [_frame_digest(j) for j in jobs]
    with ProcessPoolExecutor(2) as pool:
        there = list(pool.map(_frame_digest, jobs[::-1]))[::-1]
    assert here == there


def test_load_scene_of_a_lazy_dataset_and_its_sections(stored_and_lazy):
    stored, lazy = stored_and_lazy
    whole = load_scene(lazy.root)
    assert whole.digest() == load_scene(stored.root).digest()
    lo, hi = (40.0, -np.inf), (90.0, np.inf)
    assert _same_scene(scene_section(lazy, lo, hi), section_reference(whole, lo, hi))
    assert _same_scene(scene_section(lazy.root, lo, hi), scene_section(stored.root, lo, hi))


def test_lazy_recon_writes_the_stored_cloud(stored_and_lazy, tmp_path):
    from recon.fusion import FusionConfig
    from recon.pipeline import ReconConfig, main as recon_main

    stored, lazy = stored_and_lazy
    conf = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1))
    a = recon_main(conf, stored.root, tmp_path / "a", progress=False)
    b = recon_main(conf, lazy.root, tmp_path / "b", progress=False)
    assert a.read_bytes() == b.read_bytes()


def test_lazy_images_are_kept_on_disk_within_a_bound(stored_and_lazy, tmp_path, monkeypatch):
    """A cast image is kept as a PNG in the dataset's cache and read back the same in any
    process; a cut-off file is cast again; the least recently read go beyond the bound; 0 (or
    an unwritable dataset) keeps none; a bad bound names the variable."""
    import shutil

    from data_synth.lazy_cache import CACHE_ENV, cache_limit_bytes

    stored, lazy = stored_and_lazy
    root = tmp_path / "lazy"
    shutil.copytree(lazy.root, root, ignore=shutil.ignore_patterns("cache"))  # as made
    ds = load_dataset(root)
    _forget_casts()
    cache = ds.lazy.cache()
    assert cache.directory.parent == root.resolve() / "cache"
    want = stored.image(4, 1)
    np.testing.assert_array_equal(ds.image(4, 1), want)  # cast, then kept
    kept = cache.path(4, 1)
    assert kept.is_file() and (cache.hits, cache.misses) == (0, 1)
    _forget_casts()  # a fresh process: nothing cast in memory, the file is read
    np.testing.assert_array_equal(ds.image(4, 1), want)
    assert ds.lazy.cache().hits == 1
    with ProcessPoolExecutor(1) as pool:
        assert pool.submit(_frame_digest, (str(root), 4, 1)).result() == _frame_digest((str(root), 4, 1))
    kept.write_bytes(kept.read_bytes()[:-40])  # cut off: cast again, and kept whole
    np.testing.assert_array_equal(ds.image(4, 1), want)
    np.testing.assert_array_equal(read_image(kept), want)

    per_image = kept.stat().st_size
    monkeypatch.setenv(CACHE_ENV, str(2.5 * per_image / 2**20))  # room for about two images
    _forget_casts()
    small = ds.lazy.cache()
    for f in range(ds.num_frames):
        ds.image(f, 0)
    small.sweep()
    total = sum(size for _, size, _ in small.files())
    assert small.evicted > 0 and 0 < total <= small.limit
    assert small.path(ds.num_frames - 1, 0).is_file()  # the most recent stays

    monkeypatch.setenv(CACHE_ENV, "0")
    _forget_casts()
    shutil.rmtree(root / "cache")
    assert ds.lazy.cache() is None
    np.testing.assert_array_equal(ds.image(2, 2), stored.image(2, 2))
    assert not (root / "cache").exists()
    for bad in ("-1", "nan", "lots"):
        monkeypatch.setenv(CACHE_ENV, bad)
        with pytest.raises(ValueError, match=CACHE_ENV):
            cache_limit_bytes()

    monkeypatch.delenv(CACHE_ENV)
    _forget_casts()
    (root / "cache").write_text("not a directory")  # nothing can be kept: each read casts
    np.testing.assert_array_equal(ds.image(3, 0), stored.image(3, 0))
    np.testing.assert_array_equal(ds.image(3, 0), stored.image(3, 0))


def test_long_lazy_street_is_small(tmp_path):
    cfg = SynthConfig(street=StreetConfig(length=2000.0), frames=frames_for_spacing(2000.0, 3.0), lazy=True)
    out = write_dataset(cfg, tmp_path / "long", progress=False)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    ds = load_dataset(out)
    assert ds.num_frames == 2 * 668 and size < 3_000_000
    k, lo, hi = ds.lazy.section_box(ds.num_frames // 4)
    assert 1000.0 - 300.0 < lo[0] < 1000.0 < hi[0] < 1000.0 + 300.0


def test_frames_for_spacing():
    assert frames_for_spacing(60.0, 3.0) == 21 and frames_for_spacing(2000.0, 3.0) == 668
    assert frames_for_spacing(10.0, 20.0) == 2 and frames_for_spacing(10.0, 3.0) == 5
    with pytest.raises(ValueError):
        frames_for_spacing(10.0, 0.0)


def test_lazy_dataset_errors_name_the_file(stored_and_lazy, tmp_path):
    import shutil

    _, lazy = stored_and_lazy
    copy = tmp_path / "copy"
    shutil.copytree(lazy.root, copy)
    poses = json.loads((copy / "poses.json").read_text())
    poses["frames"][1]["world_from_rig"][0][3] += 1.0
    (copy / "poses.json").write_text(json.dumps(poses))
    with pytest.raises(DataFormatError, match="poses.json"):
        load_dataset(copy)
    shutil.copy(lazy.root / "poses.json", copy / "poses.json")
    manifest = json.loads((copy / "dataset.json").read_text())
    manifest["lazy"]["tile_m"] = -1
    (copy / "dataset.json").write_text(json.dumps(manifest))
    sources_module._SOURCES.clear()
    with pytest.raises(DataFormatError, match="dataset.json"):
        load_dataset(copy)
    with pytest.raises(DataFormatError, match="dataset.json"):
        read_image(copy / "images" / "cam0" / "000000.png")


@pytest.mark.parametrize("cam, change, words", [
    (1, lambda c: c.update(width=80, height=60, cx=39.5, cy=29.5), "gives camera 1 a size of 80x60"),
    (0, lambda c: c.update(fx=40.0, fy=40.0), "gives camera 0 other intrinsics"),
    (0, lambda c: c["cam_from_rig"][0].__setitem__(3, 0.3), "gives camera 0 another place on the rig"),
    (0, lambda c: c.update(distortion={"model": "radtan", "k1": 0.01, "k2": 0.0, "p1": 0.0, "p2": 0.0}),
     "gives camera 0 another lens"),
])
def test_lazy_rig_must_be_the_rig_its_images_are_cast_with(stored_and_lazy, tmp_path, cam, change, words):
    """The images follow the settings' rig: a rig.json edited after the dataset was written
    would describe other cameras than the frames', and is refused naming it."""
    import shutil

    _, lazy = stored_and_lazy
    copy = tmp_path / "copy"
    shutil.copytree(lazy.root, copy, ignore=shutil.ignore_patterns("cache"))
    rig = json.loads((copy / "rig.json").read_text())
    change(rig["cameras"][cam])
    (copy / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(DataFormatError, match=words) as info:
        load_dataset(copy)
    assert info.value.path == copy / "rig.json"


def test_lazy_without_ground_truth_depth_says_so(tmp_path):
    ds = load_dataset(write_dataset(tiny_config(frames=2, ground_truth_depth=False, lazy=True), tmp_path / "d",
                                    progress=False))
    assert ds.image(0, 0).shape == (120, 160, 3)
    assert ds.has_ground_truth and not ds.has_gt_depth
    with pytest.raises(DataFormatError, match="gt/depth/cam0/000000.npy"):
        ds.gt_depth(0, 0)


def test_lazy_and_stored_settings_do_not_mix(stored_and_lazy, tmp_path):
    stored, _ = stored_and_lazy
    cfg = tiny_config(street=StreetConfig(length=150.0, seed=3), frames=3)
    with pytest.raises(FileExistsError, match="lazy"):
        write_dataset(replace(cfg, lazy=True), stored.root, progress=False)


def test_synth_cli_lazy_and_frame_spacing(tmp_path):
    from bbcity.cli import main

    out = tmp_path / "d"
    assert main(["-q", "synth", "street", "--length", "90", "--frame-spacing", "10", "--lazy", "--out", str(out),
                 "--width", "64", "--height", "48"]) == 0
    ds = load_dataset(out)
    assert ds.num_frames == 2 * 10 and ds.lazy is not None
    assert ds.image(3, 1).shape == (48, 64, 3)
    with pytest.raises(SystemExit):
        main(["-q", "synth", "street", "--frames", "5", "--frame-spacing", "3", "--out", str(tmp_path / "e")])


def test_lazy_dataset_with_unbounded_supersampling_is_refused(stored_and_lazy, tmp_path):
    """Issue 35: spp 100000 in a lazy dataset's settings made check --deep cast for ever."""
    import shutil

    _, lazy = stored_and_lazy
    copy = tmp_path / "lazy"
    shutil.copytree(lazy.root, copy)
    doc = json.loads((copy / "dataset.json").read_text())
    doc["synth"]["spp"] = 100_000
    (copy / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(DataFormatError, match=r"spp must be at most 16") as err:
        load_dataset(copy)
    assert err.value.path == copy / "dataset.json"
    with pytest.raises(ValueError, match="spp must be at most"):
        SynthConfig(spp=17)
