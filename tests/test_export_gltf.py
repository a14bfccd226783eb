"""glTF export of a billboard model (share.gltf): the Khronos validator's report, quads placed as
the renderer places them, atlas texels equal to the CPU decode, a crack-free ground height field,
an empty model, refusals."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from PIL import Image

from billboards.decode import decode
from billboards.geometry import BILLBOARD, FACADE, GROUND, GROUND_OVERLAP, surface_dz
from billboards.model_writer import save
from core.fileio import DataFormatError
from share.gltf import GltfConfig, export_gltf

from .test_render_gpu import make_model

NPM = Path(__file__).parent / "npm"
ORIGIN = (1e6 + 0.25, -2e6 + 0.5, 12.0)


def run_validator(script: str, target: Path) -> dict:
    """The JSON report of ``tests/npm/<script> target``; fails when the npm packages are missing."""
    if not (NPM / "node_modules").is_dir():
        pytest.fail("tests/npm/node_modules is missing: run `make test` (it runs `npm ci --prefix tests/npm`)")
    if shutil.which("node") is None:
        pytest.fail("node is not installed: run `make test`")
    done = subprocess.run(["node", str(NPM / script), str(target)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def assert_valid_gltf(path: Path) -> dict:
    report = run_validator("validate_gltf.mjs", path)
    issues = report["issues"]
    print(f"glTF validator: {issues['numErrors']} errors, {issues['numWarnings']} warnings, {issues['numInfos']} infos")
    assert issues["numErrors"] == 0, issues["messages"]
    return report


def street_model(seed: int = 0, ground_rows: int = 3):
    """A small model of every kind: 6 billboards, 3 facade blocks and a ground height field of
    ground_rows × 4 blocks (edge 1 m, base yaw 90°) plus one split block apart; d_yaw = 4
    (no yaw offset is 0: the two nearest tie)."""
    rng = np.random.default_rng(seed)
    bb = np.stack([rng.uniform(0, 4, 6), rng.uniform(2, 4, 6), rng.uniform(0.5, 3, 6)], 1)
    fa = np.array([[0.5, 5.0, 0.5], [1.5, 5.0, 0.5], [0.5, 5.0, 1.5]])
    gx, gy = np.meshgrid(np.arange(4) + 0.5, np.arange(ground_rows) - 2.5)
    heights = lambda x, y: 0.1 * x + 0.05 * y * y + 0.02 * np.sin(3 * x * y)   # at the grid's vertices
    cx, cy = gx.reshape(-1), gy.reshape(-1)
    corners = np.stack([heights(cx + dx, cy + dy) for dx, dy in ((-.5, -.5), (.5, -.5), (-.5, .5), (.5, .5))], 1)
    centre_z = corners.mean(1)
    gr = np.stack([cx, cy, centre_z], 1)
    split = np.array([[10.25, -3.25, 0.0]])
    centres = np.concatenate([bb, fa, gr, split])
    kind = np.array([BILLBOARD] * 6 + [FACADE] * 3 + [GROUND] * (len(gr) + 1), np.uint8)
    yaw = np.concatenate([rng.uniform(-np.pi, np.pi, 6), [-np.pi / 2] * 3, [np.pi / 2] * (len(gr) + 1)])
    model = make_model(centres, base_yaw=yaw, tile=8, voxel_size=1.0, d_yaw=4, seed=seed, origin=ORIGIN,
                       page_size=64, holes=True)
    model.kind = kind
    dz = np.zeros((len(centres), 4), np.float32)
    dz[9:9 + len(gr)] = corners - centre_z[:, None]
    model.corner_dz = dz
    model.split = np.zeros(len(centres), np.uint8)
    model.split[-1] = 1
    model.check()
    return model


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return save(street_model(), tmp_path_factory.mktemp("model") / "model")


def read_glb(path: Path):
    """(gltf, positions (q, 4, 3) float64 world, uv (q, 4, 2), image index (q,), images [(H, W, 4) uint8])
    of a GLB written by share.gltf, quads in primitive order."""
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()

    def array(i):
        a = g.accessors[i]
        v = g.bufferViews[a.bufferView]
        dtype = {pygltflib.FLOAT: np.float32, pygltflib.UNSIGNED_INT: np.uint32}[a.componentType]
        width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[a.type]
        return np.frombuffer(blob, dtype, a.count * width, v.byteOffset + (a.byteOffset or 0)).reshape(a.count, width)

    images = []
    for im in g.images:
        v = g.bufferViews[im.bufferView]
        images.append(np.asarray(Image.open(io.BytesIO(blob[v.byteOffset:v.byteOffset + v.byteLength])).convert("RGBA")))
    pos, uv, which = [], [], []
    for prim in (g.meshes[0].primitives if g.meshes else []):
        p = array(prim.attributes.POSITION).astype(np.float64)
        idx = array(prim.indices).reshape(-1, 6)
        np.testing.assert_array_equal(idx, np.arange(len(idx))[:, None] * 4 + [0, 1, 2, 2, 1, 3])
        pos.append(p.reshape(-1, 4, 3))
        uv.append(array(prim.attributes.TEXCOORD_0).astype(np.float64).reshape(-1, 4, 2))
        which.append(np.full(len(idx), g.textures[g.materials[prim.material].pbrMetallicRoughness.baseColorTexture.index].source))
    t = np.asarray(g.nodes[0].translation, np.float64)
    pos = np.concatenate(pos) if pos else np.zeros((0, 4, 3))
    # glTF (X, Y, Z) → world (X, −Z, Y): the 3D Tiles y-up to z-up rotation
    world = np.stack([pos[..., 0] + t[0], -(pos[..., 2] + t[2]), pos[..., 1] + t[1]], -1)
    return (g, world, np.concatenate(uv) if uv else np.zeros((0, 4, 2)),
            np.concatenate(which) if which else np.zeros(0, int), images)


def renderer_corners(model, i: int, overlap: bool = True) -> np.ndarray:
    """(4, 3) float64 corners (model coordinates) of quad i facing its base yaw as billboard_quad.glsl
    places them (corners (0,0), (1,0), (0,1), (1,1)), one quad at a time."""
    c = model.centres[i].astype(np.float64)
    psi = float(model.base_yaw[i])
    s = float(model.edges()[i])
    right = np.array([-np.sin(psi), np.cos(psi), 0.0])
    up = np.array([-np.cos(psi), -np.sin(psi), 0.0]) if model.kind[i] == GROUND else np.array([0.0, 0.0, 1.0])
    out = []
    for cx, cy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        if model.kind[i] == GROUND and overlap:
            cx, cy = (cx - 0.5) * (1 + 2 * GROUND_OVERLAP) + 0.5, (cy - 0.5) * (1 + 2 * GROUND_OVERLAP) + 0.5
        p = c + (cx - 0.5) * s * right + (cy - 0.5) * s * up
        f = (p[:2] - c[:2]) / s + 0.5
        p[2] += surface_dz(model.corner_dz[i].astype(np.float64), f[0], f[1])
        out.append(p)
    return np.array(out)


def test_glb_is_valid_and_quads_are_the_renderers(model_dir, tmp_path):
    from billboards.model_reader import load
    model = load(model_dir)
    out = tmp_path / "street.glb"
    report = export_gltf(model_dir, out)
    assert out.is_file() and report["quads"] == model.num_billboards and report["bytes"] == out.stat().st_size
    assert sorted(p.name for p in tmp_path.iterdir()) == ["street.glb"]     # no temporary left
    info = assert_valid_gltf(out)["info"]
    assert info["totalTriangleCount"] == 2 * model.num_billboards
    g, world, uv, which, images = read_glb(out)
    assert len(world) == model.num_billboards
    assert g.asset.extras["bbcity"]["world_origin"] == list(ORIGIN)
    assert "KHR_materials_unlit" in g.extensionsUsed
    m = g.materials[0]
    assert m.alphaMode == "MASK" and m.alphaCutoff == 0.5 and m.doubleSided and "KHR_materials_unlit" in m.extensions
    for i in (0, 3, 6, 7, 9, 12, 15, model.num_billboards - 1):      # billboards, facades, ground, split ground
        np.testing.assert_allclose(world[i] - model.origin, renderer_corners(model, i), atol=1e-5)


@pytest.mark.parametrize("texture", ["direction", "mean"])
def test_atlas_texels_are_the_cpu_decode(model_dir, tmp_path, texture):
    from billboards.model_reader import load
    model = load(model_dir)
    out = tmp_path / "street.glb"
    export_gltf(model_dir, out, GltfConfig(texture=texture))
    _, _, uv, which, images = read_glb(out)
    n, t = model.num_billboards, model.tile
    if texture == "direction":   # offsets −60, −20, 20, 60°: the two nearest 0 tie, the upper wins
        want = decode(model, np.arange(n), 2.0, 0.0)
    else:                        # the mean tile: the decode without eigen images
        want = decode(_rank0(model), np.arange(n), 0.0)
    grow = np.where(model.kind == GROUND, 1 + 2 * GROUND_OVERLAP, 1.0)
    # the texel centre (row, col) lies at the quad fraction x = (col + ½)/t, y = 1 − (row + ½)/t; corner params grow
    a = (np.arange(t) + 0.5) / t
    x = (a[None, :] - 0.5) / grow[:, None] + 0.5        # (n, t) fractions of the grown quad
    y = (0.5 - a[None, :]) / grow[:, None] + 0.5
    u = uv[:, 0, None, None, 0] + x[:, None, :] * (uv[:, 1, None, None, 0] - uv[:, 0, None, None, 0])   # (n, 1, t)
    v = uv[:, 0, None, None, 1] + y[:, :, None] * (uv[:, 2, None, None, 1] - uv[:, 0, None, None, 1])   # (n, t, 1)
    for i in range(n):
        img = images[which[i]]
        px = u[i] * img.shape[1] - 0.5
        py = v[i] * img.shape[0] - 0.5
        np.testing.assert_allclose(px, np.rint(px), atol=1e-3)
        np.testing.assert_allclose(py, np.rint(py), atol=1e-3)
        got = img[np.rint(py).astype(int), np.rint(px).astype(int)].astype(np.float64) / 255
        np.testing.assert_allclose(got, want[i], atol=1 / 255 + 1e-6)


def _rank0(model):
    """``model`` with every quad's eigen images dropped from the decode (its mean only)."""
    import copy
    m = copy.copy(model)
    m.rank = np.zeros_like(model.rank)
    return m


def test_ground_height_field_has_no_cracks(model_dir, tmp_path):
    from billboards.model_reader import load
    model = load(model_dir)
    out = tmp_path / "exact.glb"
    export_gltf(model_dir, out, GltfConfig(ground_overlap=False))
    assert_valid_gltf(out)
    _, world, _, _, _ = read_glb(out)
    ground = np.flatnonzero((model.kind == GROUND) & (model.split == 0))
    corners = world[ground].reshape(-1, 3)
    key = np.round(corners[:, :2] * 1000).astype(np.int64)        # corners that share a grid vertex
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    assert counts.max() == 4                                        # inner vertices are shared by 4 blocks
    for k in np.flatnonzero(counts > 1):
        same = corners[inverse.reshape(-1) == k]
        np.testing.assert_allclose(same, same[:1].repeat(len(same), 0), atol=1e-5)
    for i in ground:
        np.testing.assert_allclose(world[i] - model.origin, renderer_corners(model, i, overlap=False), atol=1e-5)


def test_many_images_when_one_is_too_small(model_dir, tmp_path):
    from billboards.model_reader import load
    model = load(model_dir)
    out = tmp_path / "small.glb"
    report = export_gltf(model_dir, out, GltfConfig(max_image=36))   # 3 × 3 cells of 12 texels per image
    assert report["images"] == -(-model.num_billboards // 9)
    assert_valid_gltf(out)
    g, world, _, which, images = read_glb(out)
    assert len(g.materials) == len(images) == report["images"] and all(max(i.shape[:2]) <= 36 for i in images)
    assert len(world) == model.num_billboards and np.bincount(which).max() == 9


def test_empty_model_gives_a_valid_glb(tmp_path):
    model = make_model(np.zeros((0, 3)), origin=ORIGIN)
    path = save(model, tmp_path / "empty")
    report = export_gltf(path, tmp_path / "empty.glb")
    assert report["quads"] == 0 and report["images"] == 0
    assert_valid_gltf(tmp_path / "empty.glb")
    g, world, _, _, _ = read_glb(tmp_path / "empty.glb")
    assert len(world) == 0 and not g.meshes


def test_refusals(model_dir, tmp_path):
    out = tmp_path / "street.glb"
    out.write_bytes(b"keep")
    with pytest.raises(FileExistsError, match="street.glb"):
        export_gltf(model_dir, out)
    assert out.read_bytes() == b"keep"
    with pytest.raises(FileNotFoundError, match="missing"):
        export_gltf(model_dir, tmp_path / "missing" / "street.glb")
    with pytest.raises(DataFormatError, match="manifest.json"):
        export_gltf(tmp_path, tmp_path / "x.glb")
    with pytest.raises(ValueError, match=r"\.glb"):
        export_gltf(model_dir, tmp_path / "x.gltf")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["street.glb"]


@pytest.mark.parametrize("bad", [dict(texture="best"), dict(max_image=8), dict(png_level=10), dict(chunk=0),
                                 dict(ground_overlap=1)])
def test_config_names_the_bad_option(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        GltfConfig(**bad)
