"""Shared fixtures: tiny synthetic datasets made on the fly."""

from __future__ import annotations

import pytest

from capture import load_dataset
from data_synth import RigConfig, StreetConfig, SynthConfig, write_dataset


#: A small landscape rig (the geometry of the pre-portrait default: 75° hfov, pitched up 10°)
#: whose images hold facades at a fine pixel footprint: the pipeline tests' rig, apart from
#: the default portrait rig that data_synth.rig describes (tests/test_synth_coverage.py).
SMALL_RIG = dict(width=160, height=120, hfov_deg=75.0, pitch_deg=10.0)


def tiny_config(seed: int = 0, **overrides) -> SynthConfig:
    """A 30 m street, 3 frames per pass, 160×120 images: renders in about a second."""
    base = dict(scene="street", street=StreetConfig(length=30.0, seed=seed),
                rig=RigConfig(**SMALL_RIG), frames=3, spp=2)
    base.update(overrides)
    return SynthConfig(**base)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Path of a tiny street dataset, written once per test session (read-only for tests)."""
    return write_dataset(tiny_config(), tmp_path_factory.mktemp("tiny") / "street", progress=False)


@pytest.fixture(scope="module")
def ctx():
    """A headless OpenGL context (EGL), one per test module."""
    from render.context import create_context

    context = create_context()
    yield context
    context.release()


def write_ground_truth_cloud(dataset_dir, path, cameras=(0,), stride: int = 2):
    """The dataset's ground-truth depth of ``cameras`` in every frame, back-projected into a
    PLY cloud at ``path`` (as recon writes it, without normals); returns ``path``."""
    from recon.cloud_io import PlyStreamWriter
    from recon.points import depth_to_points

    ds = load_dataset(dataset_dir)
    with PlyStreamWriter(path, normals=False) as writer:
        for f in range(ds.num_frames):
            for c in cameras:
                pts, cols, _ = depth_to_points(ds.gt_depth(f, c), ds.rig.intrinsics[c], ds.world_from_cam(f, c),
                                               ds.image(f, c), stride=stride)
                writer.append(pts, cols)
    return path
