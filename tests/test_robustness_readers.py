"""Robustness of the readers not fuzzed elsewhere: point clouds (PLY in every
encoding, PCD), .npy headers and contents, PNG chunks, render pose files.

Each input gives a correct result or one DataFormatError naming the file; nothing
allocates what a header merely claims, and no pickle is ever loaded. The JSON manifests
(rig.json, poses.json, the model's manifest.json) and prefix+junk .npy/PNG files are
fuzzed in test_reader_fuzz.py and test_atlas_model.py.
"""

from __future__ import annotations

import json
import pickle
import resource
import struct
import tracemalloc
import zlib

import cv2
import numpy as np
import open3d as o3d
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from core.fileio import DataFormatError, load_npy, read_png

from . import fuzzing

from billboards import model_reader as bm
from recon.cloud_io import PlyStreamWriter, read_cloud, read_cloud_arrays
from render.camera import look_at
from render.paths import file_poses, save_poses_json

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
READERS = [read_cloud, read_cloud_arrays]


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _read(reader, path, require_colours=True):
    """(points (n, 3) float64, colours (n, 3) uint8 or None) through either reader."""
    if reader is read_cloud_arrays:
        return read_cloud_arrays(path, require_colours)
    pcd = read_cloud(path, require_colours)
    colours = np.rint(np.asarray(pcd.colors) * 255).astype(np.uint8) if pcd.has_colors() else None
    return np.asarray(pcd.points), colours


def _assert_named(error: DataFormatError, path) -> None:
    assert error.path == path and str(path) in str(error)


# ----------------------------------------------------------------------------------------------
# PLY: every encoding, NaN/inf, truncation, junk, header mutations


def ply_bytes(fmt: str, points: np.ndarray, colours: np.ndarray | None, normals: np.ndarray | None = None,
              count: int | None = None) -> bytes:
    """A PLY cloud in ``fmt`` ("ascii", "binary_little_endian", "binary_big_endian");
    ``count`` overrides the vertex count in the header."""
    order = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}[fmt]
    fields = [(a, order + "f8") for a in "xyz"]
    if normals is not None:
        fields += [(a, order + "f4") for a in ("nx", "ny", "nz")]
    if colours is not None:
        fields += [(a, "u1") for a in ("red", "green", "blue")]
    rows = np.zeros(len(points), np.dtype(fields))
    for i, a in enumerate("xyz"):
        rows[a] = points[:, i]
        if normals is not None:
            rows["n" + a] = normals[:, i]
    if colours is not None:
        for i, a in enumerate(("red", "green", "blue")):
            rows[a] = colours[:, i]
    types = {"f8": "double", "f4": "float", "u1": "uchar"}
    count = len(points) if count is None else count
    header = (f"ply\nformat {fmt} 1.0\ncomment robustness test\nelement vertex {count}\n"
              + "".join(f"property {types[rows.dtype[n].str[1:]]} {n}\n" for n in rows.dtype.names) + "end_header\n")
    if fmt == "ascii":
        body = "".join(" ".join(repr(v.item()) for v in row) + "\n" for row in rows)
        return header.encode() + body.encode()
    return header.encode() + rows.tobytes()


def _cloud(n=5, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, 3)) * 10 + [1e6, -2e6, 30.0], rng.integers(0, 256, (n, 3), dtype=np.uint8),
            rng.normal(size=(n, 3)).astype(np.float32))


FORMATS = ["ascii", "binary_little_endian", "binary_big_endian"]
RTOL = {"open3d_ascii": 1e-5}  # Open3D writes ASCII with 6 significant digits; everything else is exact


@pytest.fixture(scope="module")
def ply_files(tmp_path_factory):
    """Valid clouds as the project and Open3D write them: name → (bytes, points, colours)."""
    root = tmp_path_factory.mktemp("ply")
    points, colours, normals = _cloud()
    out = {fmt: (ply_bytes(fmt, points, colours, normals), points, colours) for fmt in FORMATS}
    with PlyStreamWriter(root / "stream.ply") as writer:
        writer.append(points, colours, normals)
    out["stream"] = ((root / "stream.ply").read_bytes(), points, colours)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colours / 255.0)
    for ascii in (True, False):
        o3d.io.write_point_cloud(str(root / "o3d.ply"), pcd, write_ascii=ascii)
        out[f"open3d_{'ascii' if ascii else 'binary'}"] = ((root / "o3d.ply").read_bytes(), points, colours)
    return out


@pytest.mark.parametrize("name", ["ascii", "binary_little_endian", "binary_big_endian", "stream",
                                  "open3d_ascii", "open3d_binary"])
@pytest.mark.parametrize("reader", READERS)
def test_ply_every_encoding_reads_back(ply_files, tmp_path, name, reader):
    data, points, colours = ply_files[name]
    path = tmp_path / "c.ply"
    path.write_bytes(data)
    got, got_colours = _read(reader, path)
    np.testing.assert_allclose(got, points, rtol=RTOL.get(name, 0), atol=0)
    np.testing.assert_array_equal(got_colours, colours)
    assert got.dtype == np.float64 and got_colours.dtype == np.uint8


@SETTINGS
@given(name=st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "stream", "open3d_ascii",
                             "open3d_binary"]),
       cut=st.integers(0, 700), junk=st.binary(max_size=40), reader=st.sampled_from(READERS))
@example(name="ascii", cut=10_000, junk=b"", reader=read_cloud)
@example(name="open3d_ascii", cut=260, junk=b"", reader=read_cloud)  # a vertex line cut short
def test_ply_truncated_or_followed_by_junk(ply_files, tmp_path, name, cut, junk, reader):
    """Any prefix of a valid cloud, then anything: the cloud (when the data survived, followed by
    nothing but blank lines for ASCII) or one error."""
    data, points, colours = ply_files[name]
    path = tmp_path / "c.ply"
    path.write_bytes(data[:cut] + junk)
    intact = cut >= len(data)  # every encoding here ends its data with a newline or a whole row
    clean = intact and not (junk.strip() if "ascii" in name else junk)
    try:
        got, got_colours = _read(reader, path)
    except DataFormatError as e:
        _assert_named(e, path)
        assert not clean, f"an intact cloud was refused: {e}"
    else:
        assert got.shape[1] == 3 and np.all(np.isfinite(got)) and got_colours.dtype == np.uint8
        assert len(got) == len(got_colours) <= len(points) and (clean or not intact)
        if intact:
            np.testing.assert_allclose(got, points, rtol=RTOL.get(name, 0), atol=0)
            np.testing.assert_array_equal(got_colours, colours)


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@SETTINGS
@given(fmt=st.sampled_from(FORMATS), values=hnp.arrays(np.float64, (3, 3), elements=finite_or_not),
       reader=st.sampled_from(READERS))
@example(fmt="ascii", values=np.array([[0.0, np.nan, 0.0], [1.0, 2.0, 3.0], [-np.inf, 0, 0]]), reader=read_cloud)
def test_ply_nan_and_inf_coordinates(tmp_path, fmt, values, reader):
    path = tmp_path / "c.ply"
    path.write_bytes(ply_bytes(fmt, values, np.zeros((3, 3), np.uint8)))
    bad = int((~np.isfinite(values).all(axis=1)).sum())
    if bad:
        with pytest.raises(DataFormatError, match=f"{bad} of 3 points have NaN or inf") as info:
            _read(reader, path)
        _assert_named(info.value, path)
    else:
        np.testing.assert_array_equal(_read(reader, path)[0], values)


HEADER_WORDS = ["ply", "format", "ascii", "binary_little_endian", "binary_big_endian", "1.0", "element", "vertex",
                "face", "property", "list", "uchar", "int", "float", "double", "x", "y", "z", "red", "green", "blue",
                "comment", "end_header", "0", "1", "5", "-1", "99999999999", "1e3", "é"]


@SETTINGS
@given(name=st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]), line=st.integers(0, 20),
       action=st.sampled_from(["replace", "insert", "delete"]),
       words=st.lists(st.sampled_from(HEADER_WORDS), min_size=0, max_size=5), reader=st.sampled_from(READERS))
@example(name="binary_little_endian", line=3, action="replace", words=["element", "vertex", "99999999999"],
         reader=read_cloud)
@example(name="ascii", line=3, action="replace", words=["element", "vertex", "99999999999"], reader=read_cloud)
def test_ply_header_mutations(ply_files, tmp_path, name, line, action, words, reader):
    data, points, _ = ply_files[name]
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode().split("\n")[:-1] + ["end_header"]
    at = line % len(lines)
    new = " ".join(words)
    lines = (lines[:at] + [new] + lines[at + 1:] if action == "replace" else
             lines[:at] + [new] + lines[at:] if action == "insert" else lines[:at] + lines[at + 1:])
    path = tmp_path / "c.ply"
    path.write_bytes("\n".join(lines).encode() + b"\n" + body)
    try:
        got, colours = _read(reader, path, require_colours=False)
    except DataFormatError as e:
        _assert_named(e, path)
    else:
        assert got.ndim == 2 and got.shape[1] == 3 and np.all(np.isfinite(got)) and 0 < len(got) <= len(points)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("count", [200_000_000, 10**12])
@pytest.mark.parametrize("reader", READERS)
def test_ply_header_claiming_more_points_than_the_file_holds(tmp_path, fmt, count, reader):
    """Open3D would allocate (and zero or leave uninitialised) what the header claims: refused first."""
    points, colours, _ = _cloud(2)
    path = tmp_path / "c.ply"
    path.write_bytes(ply_bytes(fmt, points, colours, count=count))
    before = _maxrss_mb()
    with pytest.raises(DataFormatError, match="truncated") as info:
        _read(reader, path)
    _assert_named(info.value, path)
    assert _maxrss_mb() - before < 500


@pytest.mark.parametrize("case, data, message", [
    ("empty file", b"", "not a PLY"),
    ("not a cloud", b"\x89PNG\r\n\x1a\nxxxx", "not a PLY"),
    ("no end_header", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\n", "end_header"),
    ("unknown format", b"ply\nformat binary_middle_endian 1.0\nelement vertex 1\nend_header\n", "format"),
    ("no vertices", b"ply\nformat ascii 1.0\nelement vertex 0\nproperty double x\nproperty double y\n"
                    b"property double z\nend_header\n", "no points"),
    ("face first", b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
                   b"element vertex 1\nproperty double x\nend_header\n3 0 0 0\n1\n", "element vertex"),
    ("list property", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar double x\nproperty double y\n"
                      b"property double z\nend_header\n1 2 3 4\n", "scalar"),
    ("no z", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\nend_header\n1 2\n",
     "x, y or z"),
    ("x twice", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double x\nproperty double y\n"
                b"property double z\nend_header\n1 2 3 4\n", "twice"),
    ("ascii short line", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
                         b"property double z\nend_header\n1 2 3\n44444 5\n", "columns"),
    ("ascii word", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
                   b"property double z\nend_header\n1 two 3\n", "malformed"),
    ("ascii binary bytes", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
                           b"property double z\nend_header\n1 2 \xff\xfe\n", "malformed"),
    ("ascii too few lines", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
                            b"property double z\nend_header\n1 2 3\n4 5 6\n\n\n\n\n\n\n\n\n\n\n\n\n", "truncated"),
    ("colour out of range", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
                            b"property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                            b"end_header\n1 2 3 4 300 6\n", "0…255"),
    ("float colours", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
                      b"property double z\nproperty float red\nproperty float green\nproperty float blue\n"
                      b"end_header\n1 2 3 0.5 0.5 0.5\n", "uchar"),
    ("no colours", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
                   b"property double z\nend_header\n1 2 3\n", "no colours"),
])
@pytest.mark.parametrize("reader", READERS)
def test_ply_malformed_files_name_the_file_and_the_problem(tmp_path, reader, case, data, message):
    path = tmp_path / "c.ply"
    path.write_bytes(data)
    with pytest.raises(DataFormatError, match=message) as info:
        _read(reader, path)
    _assert_named(info.value, path)


# ----------------------------------------------------------------------------------------------
# PCD (read through Open3D after the checks)


@pytest.fixture(scope="module")
def pcd_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("pcd")
    points, colours, _ = _cloud()
    points = points - [1e6, -2e6, 30.0]  # PCD stores float32
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colours / 255.0)
    out = {}
    for name, ascii, compressed in (("ascii", True, False), ("binary", False, False),
                                    ("binary_compressed", False, True)):
        o3d.io.write_point_cloud(str(root / "c.pcd"), pcd, write_ascii=ascii, compressed=compressed)
        out[name] = ((root / "c.pcd").read_bytes(), points, colours)
    return out


@SETTINGS
@given(name=st.sampled_from(["ascii", "binary", "binary_compressed"]), cut=st.integers(0, 400),
       junk=st.binary(max_size=40), reader=st.sampled_from(READERS))
@example(name="ascii", cut=10_000, junk=b"", reader=read_cloud)
def test_pcd_truncated_or_followed_by_junk(pcd_files, tmp_path, name, cut, junk, reader):
    data, points, colours = pcd_files[name]
    path = tmp_path / "c.pcd"
    path.write_bytes(data[:cut] + junk)
    try:
        got, got_colours = _read(reader, path)
    except DataFormatError as e:
        _assert_named(e, path)
        assert cut < len(data) or (junk.strip() if name == "ascii" else junk), f"an intact cloud was refused: {e}"
    else:
        assert got.shape[1] == 3 and np.all(np.isfinite(got)) and len(got) <= len(points)
        if cut >= len(data):
            np.testing.assert_allclose(got, points, rtol=1e-6)
            np.testing.assert_array_equal(got_colours, colours)


@pytest.mark.parametrize("data, message", [
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n"
     b"1 2 3\n4 5 6\n", "truncated"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 200000000\n"
     b"DATA ascii\n1 2 3\n", "truncated"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 200000000\n"
     b"DATA binary\n" + b"\0" * 12, "truncated"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1000\n"
     b"DATA binary_compressed\n" + struct.pack("<II", 10, 999) + b"\0" * 10, "unpacks"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1000\n"
     b"DATA binary_compressed\n" + struct.pack("<II", 10, 12000) + b"\0" * 10, "no points"),  # not LZF data
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n"
     b"1 nan 3\n4 5 6\n", "NaN or inf"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n", "inconsistent"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 0\nDATA ascii\n", "no points"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n", "DATA"),
    (b"", "DATA"),
])
@pytest.mark.parametrize("reader", READERS)
def test_pcd_malformed_files_name_the_file(tmp_path, reader, data, message):
    path = tmp_path / "c.pcd"
    path.write_bytes(data)
    before = _maxrss_mb()
    with pytest.raises(DataFormatError, match=message) as info:
        _read(reader, path, require_colours=False)
    _assert_named(info.value, path)
    assert _maxrss_mb() - before < 500


# ----------------------------------------------------------------------------------------------
# .npy: any header, any array


DESCRS = ["<f4", ">f4", "<f8", "<f2", "|u1", "<i4", "|b1", "<c8", "|O", "<U3", "|V12", "<M8[s]",
          [("x", "<f4"), ("y", "<f4"), ("z", "<f4")], "float32", "nonsense", 5]
SHAPES = st.one_of(
    st.lists(st.one_of(st.integers(-3, 8), st.integers(-2**70, 2**70), st.sampled_from([2**32, 2**63, 2**64])),
             max_size=3).map(tuple),
    st.sampled_from(["(2, 3)", "[2, 3]", "None", "(2.0, 3)", "'a'", "(True, 3)"]))


def npy_bytes(descr, fortran, shape, payload: bytes) -> bytes:
    shape_text = shape if isinstance(shape, str) else repr(shape)
    header = "{'descr': %r, 'fortran_order': %r, 'shape': %s, }" % (descr, fortran, shape_text)
    header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode("latin-1") + payload


@pytest.fixture
def no_pickles(monkeypatch):
    for name in ("load", "loads", "Unpickler"):
        monkeypatch.setattr(pickle, name, lambda *a, **k: pytest.fail("a pickle was loaded"))


@SETTINGS
@given(descr=st.sampled_from(DESCRS), fortran=st.sampled_from([False, True, 0, "no"]), shape=SHAPES,
       payload=st.integers(0, 64).flatmap(lambda n: st.binary(min_size=n, max_size=n)), mmap=st.booleans())
@example(descr="<f4", fortran=False, shape=(2, 3), payload=b"\0" * 24, mmap=False)  # a valid (2, 3) array
@example(descr="<f4", fortran=False, shape=(2**32, 2**32, 3), payload=b"", mmap=False)  # int64 overflow to 0
@example(descr="<f4", fortran=False, shape=(2**64,), payload=b"", mmap=False)  # beyond int64
@example(descr="<f4", fortran=False, shape=(-2, -3), payload=b"\0" * 24, mmap=True)  # negative
@example(descr="|O", fortran=False, shape=(2, 3), payload=pickle.dumps([1, 2]), mmap=False)
@example(descr="<f4", fortran=False, shape="(True, 3)", payload=b"\0" * 12, mmap=False)  # bools pass as ints
def test_npy_header_fuzz(tmp_path, no_pickles, descr, fortran, shape, payload, mmap):
    """Headers with any dtype, order and shape (negative, overflowing int64, huge, not a tuple)."""
    path = tmp_path / "a.npy"
    path.write_bytes(npy_bytes(descr, fortran, shape, payload))
    tracemalloc.start()
    try:
        for load in (lambda: load_npy(path, dtype=np.float32, shape=(None, 3), finite=True, max_bytes=1 << 16),
                     lambda: bm._load_array(path, np.dtype(np.float32), (2, 3), mmap=mmap)):
            try:
                array = load()
            except DataFormatError as e:
                _assert_named(e, path)
            else:
                assert array.dtype == np.float32 and array.ndim == 2 and array.shape[1] == 3
                assert isinstance(array, np.memmap) or np.all(np.isfinite(array))  # maps are checked later
        assert tracemalloc.get_traced_memory()[1] < 1 << 20  # nothing of what the header claims
    finally:
        tracemalloc.stop()


DTYPES = [np.float32, np.float64, np.float16, np.int32, np.uint8, np.bool_, np.complex64, np.dtype(">f4")]


@SETTINGS
@given(array=st.sampled_from(DTYPES).flatmap(
    lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4))),
    fortran=st.booleans())
@example(array=np.array([[0, 1, np.nan]], np.float32), fortran=False)
@example(array=np.array([[0, 1, np.inf], [1, 2, 3]], np.float32), fortran=True)
@example(array=np.zeros((0, 3), np.float32), fortran=False)
def test_npy_wrong_dtype_shape_and_values(tmp_path, array, fortran):
    """A real array of any dtype, shape and values: loaded exactly when it is what was asked for,
    otherwise one error saying what is wrong."""
    path = tmp_path / "a.npy"
    np.save(path, np.asfortranarray(array) if fortran else array, allow_pickle=False)
    want = dict(dtype=np.float32, shape=(None, 3), finite=True)
    ok_dtype = array.dtype == np.dtype(np.float32)  # exact: '>f4' is refused too
    ok_shape = array.ndim == 2 and array.shape[1] == 3
    try:
        got = load_npy(path, **want)
    except DataFormatError as e:
        _assert_named(e, path)
        problem = e.problem
        if not ok_dtype:
            assert "dtype" in problem
        elif not ok_shape:
            assert "shape" in problem
        else:
            assert "NaN or inf" in problem and not np.all(np.isfinite(array))
    else:
        assert ok_dtype and ok_shape and np.all(np.isfinite(array))
        np.testing.assert_array_equal(got, array)


def test_npy_refuses_a_pickle_without_loading_it(tmp_path, no_pickles):
    path = tmp_path / "a.npy"
    np.save(path, np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    with pytest.raises(DataFormatError, match="pickles") as info:
        load_npy(path)
    _assert_named(info.value, path)


# ----------------------------------------------------------------------------------------------
# PNG: arbitrary chunks, other pixel formats, a size mismatch refused before decoding


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bytes(width, height, depth, colour, interlace, pixels: bytes, compress: bool) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr)
            + _chunk(b"IDAT", zlib.compress(pixels) if compress else pixels) + _chunk(b"IEND", b""))


@SETTINGS
@given(width=st.sampled_from([0, 1, 20, 2**31 - 1, 2**32 - 1]), height=st.sampled_from([0, 1, 16, 100000]),
       depth=st.sampled_from([1, 2, 8, 16, 7]), colour=st.sampled_from([0, 2, 3, 4, 6, 5]),
       interlace=st.sampled_from([0, 1, 2]), pixels=st.binary(max_size=1200), compress=st.booleans())
@example(width=20, height=16, depth=8, colour=2, interlace=0, pixels=b"\0" * (16 * 61), compress=True)
def test_png_chunk_fuzz(tmp_path, width, height, depth, colour, interlace, pixels, compress):
    """Well-formed chunks holding anything: an image of the expected size or one error."""
    path = tmp_path / "x.png"
    path.write_bytes(png_bytes(width, height, depth, colour, interlace, pixels, compress))
    for size in ((20, 16), None):
        try:
            image = read_png(path, size)
        except DataFormatError as e:
            _assert_named(e, path)
        else:
            assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
            assert (image.shape[1], image.shape[0]) == (width, height)


def test_png_of_the_wrong_size_is_refused_before_decoding(tmp_path, monkeypatch):
    """A small file can claim a huge image (a decompression bomb): the IHDR is checked first."""
    path = tmp_path / "x.png"
    path.write_bytes(png_bytes(30000, 30000, 8, 2, 0, b"\0" * 1000, True))
    import core.fileio as fileio

    monkeypatch.setattr(fileio.cv2, "imdecode", lambda *a: pytest.fail("decoded before the size check"))
    with pytest.raises(DataFormatError, match="30000x30000, expected 160x120") as info:
        read_png(path, (160, 120))
    _assert_named(info.value, path)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"tEXt", b"a\0b") + _chunk(b"IEND", b""))
    with pytest.raises(DataFormatError, match="IHDR"):
        read_png(path, (160, 120))


@pytest.mark.parametrize("kind", ["grey", "grey16", "rgb16", "rgba", "palette"])
def test_other_png_pixel_formats_read_as_rgb(tmp_path, kind):
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    path = tmp_path / "x.png"
    if kind == "grey":
        cv2.imwrite(str(path), rgb[..., 0])
        want = np.repeat(rgb[..., :1], 3, axis=2)
    elif kind == "grey16":
        cv2.imwrite(str(path), rgb[..., 0].astype(np.uint16) * 257)
        want = np.repeat(rgb[..., :1], 3, axis=2)
    elif kind == "rgb16":
        cv2.imwrite(str(path), rgb[..., ::-1].astype(np.uint16) * 257)
        want = rgb
    elif kind == "rgba":
        cv2.imwrite(str(path), np.concatenate([rgb[..., ::-1], rng.integers(0, 256, (6, 7, 1), np.uint8)], 2))
        want = rgb
    else:  # 8 colours through a palette (PNG colour type 3)
        palette = rng.integers(0, 256, (8, 3), dtype=np.uint8)
        index = rng.integers(0, 8, (6, 7), dtype=np.uint8)
        rows = b"".join(b"\0" + index[r].tobytes() for r in range(6))
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 7, 6, 8, 3, 0, 0, 0))
                         + _chunk(b"PLTE", palette.tobytes()) + _chunk(b"IDAT", zlib.compress(rows))
                         + _chunk(b"IEND", b""))
        want = palette[index]
    np.testing.assert_array_equal(read_png(path, (7, 6)), want)


# ----------------------------------------------------------------------------------------------
# render pose files (bbcity render --path FILE)


@SETTINGS
@given(path=st.lists(st.integers(0, 50), max_size=4), value=fuzzing.json_values())
@example(path=[1, 0, 0], value=float("nan"))
@example(path=[0, 0, 0], value=2.0)  # a scaled rotation
@example(path=[], value=[])
def test_render_pose_file_fuzz(tmp_path, path, value):
    target = tmp_path / "poses.json"
    good = [look_at([0.0, 0, 1.5], [5.0, 1, 1.5]), look_at([1.0, 0, 1.5], [5.0, -1, 2.5])]
    save_poses_json(target, np.stack(good))
    target.write_text(json.dumps(fuzzing.mutate(json.loads(target.read_text()), path, value)))
    try:
        poses = file_poses(target)
    except DataFormatError as e:
        _assert_named(e, target)
    else:
        assert poses.dtype == np.float64 and poses.ndim == 3 and poses.shape[1:] == (4, 4)
        assert np.all(np.isfinite(poses))
        R = poses[:, :3, :3]
        np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)


def test_render_pose_file_with_more_poses_than_frames_is_refused(tmp_path, monkeypatch):
    """Issue 35: 200 001 poses rendered past the frames cap (Ctrl-C then took 25 s and left
    45 540 temporary frames); a path file holds at most as many poses as render makes frames."""
    import render.paths as paths

    monkeypatch.setattr(paths, "MAX_PATH_POSES", 3)
    target = tmp_path / "poses.json"
    save_poses_json(target, np.stack([look_at([float(i), 0, 1.5], [5.0, 1, 1.5]) for i in range(4)]))
    with pytest.raises(DataFormatError, match="holds 4 poses; a path renders at most 3 frames") as err:
        file_poses(target)
    _assert_named(err.value, target)
    save_poses_json(target, np.stack([look_at([float(i), 0, 1.5], [5.0, 1, 1.5]) for i in range(3)]))
    assert len(file_poses(target)) == 3
