"""Transients: what a few cameras saw in front of a surface (a passing car) stays out of
its texture; smooth view dependence stays in."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from billboards.texels import OCCLUDED, TRANSPARENT, UNSEEN, VISIBLE, nanmedian_along, reject_transients, \
    reject_transients_reference


def _stack(B=3, d=12, t=4, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.integers(60, 180, (B, 1, t, t, 3))
    colour = np.clip(base + rng.integers(-3, 4, (B, d, t, t, 3)), 0, 255).astype(np.uint8)
    status = np.full((B, d, t, t), VISIBLE, np.uint8)
    return colour, status


def test_a_car_in_two_directions_is_rejected_and_a_smooth_reflection_kept():
    colour, status = _stack()
    colour[0, 3:5, 1:3, 1:3] = (250, 20, 20)                        # a red car seen from two directions
    ramp = (40 + 12 * np.arange(12)).astype(np.uint8)                # block 1: glass brightening with the angle
    colour[1] = ramp[:, None, None, None]
    status[2, 2:] = UNSEEN                                           # block 2: only two cameras measured
    colour[2, 0, 0, 0] = (255, 255, 255)
    out = reject_transients(colour, status)
    rejected = (out == OCCLUDED) & (status == VISIBLE)
    expected = np.zeros_like(rejected)
    expected[0, 3:5, 1:3, 1:3] = True
    assert np.array_equal(rejected, expected)
    assert np.array_equal(out[status != VISIBLE], status[status != VISIBLE])   # only visible samples change


@pytest.mark.parametrize("seed", [1, 2])
def test_reject_transients_matches_the_reference(seed):
    rng = np.random.default_rng(seed)
    colour = rng.integers(0, 256, (4, 9, 3, 3, 3)).astype(np.uint8)
    colour[:2] = (colour[:2] // 16 + 100).astype(np.uint8)             # two nearly constant blocks …
    colour[:2, rng.integers(0, 9, 3)] = 255                            # … with outliers
    status = rng.choice([VISIBLE, VISIBLE, VISIBLE, TRANSPARENT, UNSEEN, OCCLUDED], (4, 9, 3, 3)).astype(np.uint8)
    views = rng.integers(-1, 5, (4, 9))                              # cameras sampling several directions
    for args in ((None,), (views,), (views, 20.0, 2.0, 4)):
        np.testing.assert_array_equal(reject_transients(colour, status, *args),
                                      reject_transients_reference(colour, status, *args))


def test_a_camera_counts_once():
    """One camera that sampled most directions saw a car; three others did not: the car goes."""
    colour, status = _stack(B=1, d=8)
    views = np.array([[5, 5, 5, 5, 5, 1, 2, 3]])
    colour[0, :5] = (250, 20, 20)
    out = reject_transients(colour, status, views)
    assert np.all(out[0, :5] == OCCLUDED) and np.all(out[0, 5:] == VISIBLE)
    assert np.all(reject_transients(colour, status)[0, :5] == VISIBLE)  # counted per direction, the car would win


@pytest.mark.slow
def test_a_passing_car_stays_out_of_the_ground_texture(tmp_path):
    """A red car painted into one frame's road: with transients rejected the ground blocks'
    textures are those of the clean street; without, the car shows in them."""
    import dataclasses
    import shutil

    from billboards.build import main as build_main
    from billboards.geometry import GROUND, DirectionConfig
    from billboards.layer import LayerConfig
    from billboards.decode import decode_directions
    from billboards.model_reader import load
    from capture import load_dataset
    from data_synth import write_dataset
    from core.fileio import write_png

    from .conftest import tiny_config, write_ground_truth_cloud
    from .test_build import small_config

    # frames 1.3 m apart: a road block beside the path is seen from several moments
    clean = write_dataset(tiny_config(frames=24, return_pass=False), tmp_path / "clean", progress=False)
    cloud = write_ground_truth_cloud(clean, tmp_path / "cloud.ply", cameras=(0, 1, 2))
    car = tmp_path / "car"
    shutil.copytree(clean, car)
    ds = load_dataset(car)
    for cam in range(3):                                              # one moment: every camera sees the car
        image = ds.image(12, cam)
        image[int(0.7 * image.shape[0]):, 40:100] = (230, 20, 20)     # on the road below the facades
        write_png(ds.image_path(12, cam), image)

    def ground_textures(dataset, transients):
        # (ground continued where the cloud has none is seen from fewer moments: one sighting cannot
        # be told from a transient, so only the measured ground is compared)
        config = small_config(layer=LayerConfig(facades=False, ground_reach=0.0), photometry=None)
        # directions 6° apart over 192°, as by default: a road block is sampled from several frames
        sampling = dataclasses.replace(config.sampling, transients=transients, directions=DirectionConfig())
        config = dataclasses.replace(config, sampling=sampling)
        model = load(build_main(config, cloud, dataset, tmp_path / f"model-{dataset.name}-{transients}").model)
        ground = np.flatnonzero(model.kind == GROUND)
        return decode_directions(model, ground)

    reference = ground_textures(clean, True)
    kept = ground_textures(car, True)
    smeared = ground_textures(car, False)
    assert len(reference) > 20

    def redness(tex):  # how much red beyond the clean texture, per texel
        return np.clip((tex[..., 0] - tex[..., 1]) - (reference[..., 0] - reference[..., 1]), 0, None)

    car_texels = (redness(smeared) > 0.2).sum()
    assert car_texels > 200                                            # the car is in the textures …
    assert (redness(kept) > 0.2).sum() < 0.05 * car_texels             # … unless rejected


@pytest.mark.parametrize("shape, axis", [((40, 7, 4, 4, 3), 1), ((9, 1, 3), 1), ((6, 12, 2), 1), ((5, 8), 0)])
def test_nanmedian_along_is_numpys(shape, axis):
    """Odd and even counts, a line of one, lines with no number (NaN), halves (.5)."""
    rng = np.random.default_rng(len(shape))
    x = rng.integers(0, 256, shape).astype(np.float32)
    x[rng.random(shape) < 0.4] = np.nan
    x[0] = np.nan
    x[(slice(None),) * axis + (slice(0, 1),)] = np.nan
    x.reshape(-1)[:1] = 7.0  # a line of one number
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy warns of the lines of no number
        expected = np.nanmedian(x, axis=axis, keepdims=True)
    got = nanmedian_along(x, axis)
    assert got.dtype == expected.dtype and np.array_equal(got, expected, equal_nan=True)
