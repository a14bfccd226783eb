"""Photometry: per-image exposure × white-balance gains recovered from overlaps, solvers agree,
grey stays grey, moving objects do not bias, degenerate inputs, and the build gains from it."""

from __future__ import annotations

import pickle
import shutil
from dataclasses import replace

import numpy as np
import pytest

from core.fileio import read_png, write_png
import billboards as billboard_model
from billboards.build import main as build_main
from billboards.photometry import (PhotometryConfig, apply_gains, collect_observations, components, estimate_gains,
                                   prune, solve_fast, solve_gains, solve_reference)
from billboards.views import Views, views_from_dataset
from capture import load_dataset
from data_synth import write_dataset
from recon.cloud_io import read_cloud_arrays

from .conftest import tiny_config, write_ground_truth_cloud
from .test_build import small_config

TOLERANCE = 0.03  # recovered gains match the true ones (up to the gauge) within 3 %


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """A short street with 6 frames per pass (consecutive frames overlap): dataset and GT cloud."""
    root = tmp_path_factory.mktemp("photometry")
    dataset = write_dataset(tiny_config(frames=6), root / "street", progress=False)
    cloud = write_ground_truth_cloud(dataset, root / "cloud.ply")
    points, _ = read_cloud_arrays(cloud)
    return dataset, cloud, points


def _rewrite(src, dst, transform):
    """A copy of dataset ``src`` (without gt/) at ``dst`` whose k-th image (frame-major,
    the order of :func:`views_from_dataset`) is ``transform(k, image)``."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("gt"))
    ds = load_dataset(dst)
    k = 0
    for f in range(ds.num_frames):
        for c in range(ds.rig.num_cameras):
            path = ds.image_path(f, c)
            write_png(path, transform(k, read_png(path)))
            k += 1
    return dst


def _scaled(image, gain):
    return np.clip(np.rint(image.astype(np.float64) * gain), 0, 255).astype(np.uint8)


def _known_gains(num_frames, num_cameras, seed=1):
    """(V, 3) exposure 0.6–1.4 per image times a white balance per camera."""
    rng = np.random.default_rng(seed)
    white = rng.uniform(0.85, 1.15, (num_cameras, 3))
    return rng.uniform(0.6, 1.4, (num_frames * num_cameras, 1)) * np.tile(white, (num_frames, 1))


@pytest.fixture(scope="module")
def perturbed(street, tmp_path_factory):
    dataset, _, _ = street
    ds = load_dataset(dataset)
    gains = _known_gains(ds.num_frames, ds.rig.num_cameras)
    out = _rewrite(dataset, tmp_path_factory.mktemp("perturbed") / "street", lambda k, im: _scaled(im, gains[k]))
    return out, gains


def _gauge_error(solution, true_gains):
    """Largest |recovered / true − 1| over estimated images, the true log gains moved to the
    solver's gauge (mean 0 within each connected component)."""
    truth = np.log(true_gains)
    for c in range(solution.num_components):
        mine = solution.component == c
        truth[mine] -= truth[mine].mean(axis=0)
    ratio = np.exp(solution.log_gains - truth)[solution.estimated]
    return float(np.abs(ratio - 1).max())


def test_config_is_validated():
    PhotometryConfig()
    for bad in (dict(samples=0), dict(min_observations=1), dict(robust_threshold=0.0), dict(dark=250, saturated=250),
                dict(solver="magic"), dict(loss="l1"), dict(blur_sigma=-1.0), dict(cell=0.0), dict(rel_tolerance=-0.1)):
        with pytest.raises(ValueError):
            PhotometryConfig(**bad)


def test_apply_gains_divides_rounds_and_clips():
    image = np.array([[[100, 200, 50], [255, 0, 10]]], np.uint8)
    assert apply_gains(image, np.ones(3)) is image
    out = apply_gains(image, np.array([0.5, 2.0, 1.0]))
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, [[[200, 100, 50], [255, 0, 10]]])   # 510 clipped to 255


@pytest.mark.parametrize("num_images,num_points,split", [(2, 5, False), (6, 40, True), (10, 80, False)])
def test_fast_solver_matches_the_dense_reference(num_images, num_points, split):
    """Random weighted problems, one or two connected components: the same gains and albedos."""
    rng = np.random.default_rng(num_images)
    image, point = [], []
    half = num_images // 2
    for j in range(num_points):
        pool = (np.arange(half) if j % 2 else np.arange(half, num_images)) if split else np.arange(num_images)
        seen = rng.choice(pool, size=rng.integers(2, len(pool) + 1), replace=False)
        image += list(seen)
        point += [j] * len(seen)
    image, point = np.array(image, np.int64), np.array(point, np.int64)
    y = rng.normal(0, 0.3, (num_images, 3))[image] + rng.normal(4, 0.5, (num_points, 3))[point]
    y += rng.normal(0, 0.02, y.shape)
    w = rng.uniform(0.1, 1.0, len(image))
    comp = components(image, point, num_images, num_points)
    assert comp.max() + 1 == (2 if split else 1)
    a_ref, b_ref = solve_reference(image, point, y, w, num_images, num_points, comp)
    a, b = solve_fast(image, point, y, w, num_images, num_points, comp)
    np.testing.assert_allclose(a, a_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b, b_ref, rtol=0, atol=1e-9)
    for c in range(comp.max() + 1):   # the gauge: mean log gain 0 per component
        np.testing.assert_allclose(a[comp == c].mean(axis=0), 0, atol=1e-12)


def test_prune_drops_points_seen_once_and_thin_images():
    image = np.array([0, 1, 0, 2, 1, 2, 3], np.int64)
    point = np.array([0, 0, 1, 1, 2, 2, 3], np.int64)        # point 3 only in image 3
    keep = prune(image, point, 4, 4, min_observations=2, min_image_observations=1)
    np.testing.assert_array_equal(keep, [1, 1, 1, 1, 1, 1, 0])
    keep = prune(image, point, 4, 4, min_observations=2, min_image_observations=3)
    assert not keep.any()                                   # no image has 3 samples: everything goes


def test_known_gains_are_recovered_and_the_solvers_agree(street, perturbed):
    _, _, points = street
    path, gains = perturbed
    views = views_from_dataset(load_dataset(path))
    result = estimate_gains(views, points)
    sol = result.solution
    assert sol.estimated.all() and sol.num_components == 2   # the two passes see opposite sides
    assert _gauge_error(sol, gains) < TOLERANCE
    report = result.report()
    assert report["observations"] > 1000 and report["not_estimated"] == [] and len(report["gains"]) == len(views)
    # Reference (dense lstsq) and fast (reduced, PCG) through the whole reweighting, on fewer tie points.
    few = PhotometryConfig(samples=150, iterations=3)
    obs = collect_observations(views, points, few)
    fast = solve_gains(obs, few, solver="fast")
    ref = solve_gains(obs, few, solver="reference")
    np.testing.assert_allclose(fast.log_gains, ref.log_gains, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(fast.estimated, ref.estimated)


def test_observations_read_in_parallel_are_the_same(street, perturbed):
    from bbcity.executor import WorkerPool

    _, _, points = street
    views = views_from_dataset(load_dataset(perturbed[0]))
    here = collect_observations(views, points)
    with WorkerPool(2) as pool:
        there = collect_observations(views, points, executor=pool)
    assert len(here.image) > 1000 and len(np.unique(here.image)) > 1
    for name in ("image", "point", "rgb"):
        np.testing.assert_array_equal(getattr(here, name), getattr(there, name))
    assert (here.num_images, here.num_points) == (there.num_images, there.num_points)


def test_constant_exposure_gives_unit_gains(street):
    dataset, _, points = street
    result = estimate_gains(views_from_dataset(load_dataset(dataset)), points)
    assert result.solution.estimated.all()
    assert np.abs(result.gains - 1).max() < 0.02


def test_a_moving_object_does_not_bias_the_gains(street, perturbed, tmp_path):
    """A patch painted over a fifth of one image (a passing van) leaves the gains within tolerance."""
    _, _, points = street
    path, gains = perturbed
    target = 4

    def paint(k, image):
        if k == target:
            h, w = image.shape[:2]
            image = image.copy()
            image[h // 4: h // 4 + h // 2, w // 3: w // 3 + w * 2 // 5] = (190, 30, 160)
        return image

    moved = _rewrite(path, tmp_path / "moved", paint)
    views = views_from_dataset(load_dataset(moved))
    result = estimate_gains(views, points)
    assert _gauge_error(result.solution, gains) < TOLERANCE
    # Plain least squares (a threshold nothing exceeds) is pulled off by the patch: a real outlier.
    plain = estimate_gains(views, points, PhotometryConfig(robust_threshold=1e9))
    assert _gauge_error(plain.solution, gains) > 2 * TOLERANCE
    assert _gauge_error(estimate_gains(views, points, PhotometryConfig(loss="huber")).solution, gains) < TOLERANCE
    # The painted observations were discounted by the reweighting.
    sol = result.solution
    assert sol.weights.min() < 0.5


def test_grayscale_capture_gives_grey_gains_and_a_grey_model(street, tmp_path):
    dataset, cloud, points = street
    ds = load_dataset(dataset)
    exposure = _known_gains(ds.num_frames, ds.rig.num_cameras, seed=3)[:, :1]

    def grey(k, image):
        luma = np.rint(image.astype(np.float64) @ [0.299, 0.587, 0.114])
        return _scaled(np.repeat(luma[..., None], 3, axis=2), exposure[k])

    path = _rewrite(dataset, tmp_path / "grey", grey)
    result = estimate_gains(views_from_dataset(load_dataset(path)), points)
    g = result.gains
    assert result.solution.grayscale
    np.testing.assert_array_equal(g[:, 0], g[:, 1])
    np.testing.assert_array_equal(g[:, 0], g[:, 2])
    assert _gauge_error(result.solution, np.repeat(exposure, 3, axis=1)) < TOLERANCE
    built = build_main(small_config(), cloud, path, tmp_path / "model")
    model = billboard_model.load(built.model)
    decoded = billboard_model.decode_directions(model, np.arange(0, model.num_billboards, 5))
    assert np.abs(decoded[..., 0] - decoded[..., 1]).max() <= 1.5 / 255
    assert np.abs(decoded[..., 0] - decoded[..., 2]).max() <= 1.5 / 255


def test_degenerate_inputs_keep_unit_gains(street, tmp_path):
    dataset, _, points = street
    views = views_from_dataset(load_dataset(dataset))

    def subset(index, paths=None):
        index = np.asarray(index)
        return Views(views.K[index], views.world_from_cam[index], views.sizes[index],
                     tuple(paths or [views.paths[i] for i in index]))

    # One image: nothing to compare it with.
    one = estimate_gains(subset([0]), points)
    np.testing.assert_array_equal(one.gains, np.ones((1, 3)))
    assert one.report()["not_estimated"] == [0] and one.report()["components"] == 0
    # Two images of opposite sides of the street (first and last frame, two passes): no overlap.
    apart = estimate_gains(subset([0, len(views) - 1]), points)
    np.testing.assert_array_equal(apart.gains, 1.0)
    assert apart.report()["not_estimated"] == [0, 1]
    # Two overlapping images, both saturated white: every sample is left out.
    white = []
    for i in (0, 1):
        white.append(write_png(tmp_path / f"white{i}.png", np.full_like(read_png(views.paths[i]), 255)))
    clipped = estimate_gains(subset([0, 1], white), points)
    np.testing.assert_array_equal(clipped.gains, 1.0)
    assert clipped.observations == 0
    # No cloud, and photometry off.
    np.testing.assert_array_equal(estimate_gains(subset([0, 1]), np.zeros((0, 3))).gains, 1.0)
    off = estimate_gains(views, points, PhotometryConfig(enabled=False))
    np.testing.assert_array_equal(off.gains, np.ones((len(views), 3)))


def test_build_with_photometry_spends_less_rank_on_exposure(street, perturbed, tmp_path):
    """On the perturbed street the textures without photometry change with the image they come
    from; with it they are nearly those of the constant-exposure street."""
    _, cloud, _ = street
    path, _ = perturbed
    on = build_main(small_config(), cloud, path, tmp_path / "on").report
    off = build_main(small_config(photometry=None), cloud, path, tmp_path / "off").report
    assert on["photometry"]["enabled"] and on["photometry"]["estimated_images"] == on["views"]
    assert off["photometry"] == {"enabled": False} and "photometry_s" in on["stages"]
    assert on["mean_rank"] < off["mean_rank"] - 0.2
    assert on["psnr"]["decoded_rgb_opaque_db"] > off["psnr"]["decoded_rgb_opaque_db"] + 1.0
    assert on["bytes"]["model"] < off["bytes"]["model"]


def test_cli_photometry_option():
    from bbcity.cli import build_parser
    from bbcity.commands.build import build_config_from_args

    parser = build_parser()
    base = ["build", "--cloud", "c.ply", "--out", "m", "--holdout", "0"]
    assert build_config_from_args(parser.parse_args(base)).photometry == PhotometryConfig()
    assert build_config_from_args(parser.parse_args(base + ["--photometry", "off"])).photometry is None
    with pytest.raises(SystemExit):
        parser.parse_args(base + ["--photometry", "maybe"])


def test_views_kept_in_a_cache_read_back_the_same_in_any_process(street, perturbed, tmp_path, monkeypatch):
    from billboards import views as views_module
    from billboards.views import with_image_cache

    dataset, gains = perturbed
    plain = replace(views_from_dataset(load_dataset(dataset)), gains=gains)
    cached = with_image_cache(plain, tmp_path / "images")
    assert cached.cache == tmp_path / "images" and plain.cache is None
    first = [cached.image(i) for i in range(len(cached))]  # decoded and kept
    assert len(list((tmp_path / "images").glob("*.npy"))) == len(cached)
    assert all(np.array_equal(first[i], plain.read_image(i)) for i in range(len(cached)))
    again = pickle.loads(pickle.dumps(cached))  # as a worker has it: read back, not decoded
    monkeypatch.setattr(views_module, "read_png", lambda *a: pytest.fail("decoded a kept image"))
    for i in range(len(cached)):
        assert np.array_equal(again.image(i), first[i])
    monkeypatch.undo()
    # other gains are other images; a damaged file is read and kept again
    other = replace(cached, gains=gains * 1.1)
    assert not np.array_equal(other.image(0), first[0])
    damaged = sorted((tmp_path / "images").glob("000001-*.npy"))
    for path in damaged:
        path.write_bytes(b"\x93NUMPY garbage")
    assert np.array_equal(cached.image(1), first[1]) and np.load(damaged[0]).shape == first[1].shape
    # images that do not fit: no cache
    monkeypatch.setattr(views_module, "IMAGE_CACHE_BYTES", 1000)
    assert with_image_cache(plain, tmp_path / "small").cache is None
