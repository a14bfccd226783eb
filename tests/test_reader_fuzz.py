"""Readers fuzzed with hypothesis: any input gives a result or one DataFormatError naming the file."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from core import DataFormatError
from core.fileio import load_npy, read_npy_header, read_png, write_png

from . import fuzzing


from capture import Rig, load_poses, save_poses
from data_synth import RigConfig, make_rig
from data_synth.rig import yaw_pose

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

json_values = fuzzing.json_values()


@SETTINGS
@given(path=st.lists(st.integers(0, 50), max_size=5), value=json_values)
def test_rig_json_reader(tmp_path, path, value):
    good = make_rig(RigConfig()).to_json()
    target = tmp_path / "rig.json"
    target.write_text(json.dumps(fuzzing.mutate(good, path, value)))
    try:
        rig = Rig.load(target)
    except DataFormatError as e:
        assert str(target) in str(e)
    else:
        assert np.all(np.isfinite(rig.intrinsics)) and np.all(np.isfinite(rig.cam_from_rig))


@SETTINGS
@given(path=st.lists(st.integers(0, 50), max_size=6), value=json_values)
def test_poses_json_reader(tmp_path, path, value):
    target = tmp_path / "poses.json"
    save_poses(target, yaw_pose(np.arange(3.0), np.zeros(3), np.zeros(3)), np.zeros(3, np.int32))
    target.write_text(json.dumps(fuzzing.mutate(json.loads(target.read_text()), path, value)))
    try:
        poses, names = load_poses(target)
    except DataFormatError as e:
        assert str(target) in str(e)
    else:
        unknown = np.isnan(poses).all(axis=(1, 2))  # "world_from_rig": null, a frame without a pose
        assert poses.dtype == np.float64 and np.all(np.isfinite(poses[~unknown])) and len(names) == len(poses)


@SETTINGS
@given(data=st.binary(max_size=300), keep=st.integers(0, 200))
@example(data=b"\x00\x00\x00\x00\x00\x00(", keep=121)  # header garbage that numpy's tokenizer rejects
def test_npy_reader(tmp_path, data, keep):
    buf = io.BytesIO()
    original = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.save(buf, original)
    full = buf.getvalue()
    target = tmp_path / "a.npy"
    written = full[:keep] + data  # a valid prefix, then anything
    target.write_bytes(written)
    try:
        array = load_npy(target, max_bytes=1 << 20)
    except DataFormatError as e:
        assert str(target) in str(e)
    else:  # what loads is exactly the data its header describes: nothing cut, nothing after it
        offset = read_npy_header(target)[3]
        assert len(written) - offset == array.nbytes and array.tobytes(order="A") == written[offset:]
        if written[:offset] == full[:offset]:
            assert array.shape == original.shape and array.dtype == original.dtype


@pytest.mark.parametrize("shape", ["(1000000000000,)", "(100000, 100000, 100)"])
def test_npy_reader_refuses_huge_headers_without_allocating(tmp_path, shape):
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': %s, }" % shape
    header = header + " " * (127 - 10 - len(header)) + "\n"
    target = tmp_path / "huge.npy"
    target.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode() + b"\0" * 64)
    with pytest.raises(DataFormatError, match="exceeds the limit"):
        load_npy(target)


@SETTINGS
@given(cut=st.integers(0, 2000), junk=st.binary(max_size=40))
def test_png_reader(tmp_path, cut, junk):
    target = tmp_path / "x.png"
    write_png(target, np.random.default_rng(0).integers(0, 256, (16, 20, 3), dtype=np.uint8))
    data = target.read_bytes()
    target.write_bytes(data[:cut] + junk)
    try:
        image = read_png(target, (20, 16))
    except DataFormatError as e:
        assert str(target) in str(e)
    else:
        assert image.shape == (16, 20, 3) and image.dtype == np.uint8
