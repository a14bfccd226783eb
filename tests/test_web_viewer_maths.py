"""The web viewer's pure maths (share/viewer/*.js, run in Node) against its Python twins: the
direction brackets (model.js viewBracket / render.view_brackets), the camera (camera.js /
share.web_camera + render.camera) and the octree frustum culling (culling.js / render.culling)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from billboards.geometry import billboard_radius
from billboards.octree import OctreeConfig, build_octree
from render.camera import gl_camera
from render.culling import frustum_cull_nodes, frustum_planes, ranges_to_mask
from render.view_brackets import storage_slots, view_brackets
from share.web_camera import view_camera

NODE = shutil.which("node")
VIEWER = (Path(__file__).resolve().parents[1] / "share" / "viewer").as_uri()
pytestmark = pytest.mark.skipif(NODE is None, reason="Node.js (node) is not installed")

HEAD = "import {readFileSync} from 'node:fs';\nconst data = JSON.parse(readFileSync(process.argv[2], 'utf8'));\n"


def run_node(tmp_path: Path, script: str, data) -> list:
    """Run the ES module ``script`` (@VIEWER@ → the viewer's folder URL) on ``data``; its JSON output."""
    (tmp_path / "in.json").write_text(json.dumps(data))
    js = tmp_path / "run.mjs"
    js.write_text(HEAD + script.replace("@VIEWER@", VIEWER))
    done = subprocess.run([NODE, str(js), str(tmp_path / "in.json")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


# ----------------------------------------------------------------------------------------------
# direction brackets

BRACKET_JS = """import {viewBracket} from '@VIEWER@/model.js';
const out = data.cases.map(([eye, c, baseYaw, t]) => {
  const {yaw, pitch, slots} = data.tables[t];
  const dirs = new Int32Array(4).fill(7), weights = new Float64Array(4).fill(3);
  viewBracket(eye, c[0], c[1], c[2], baseYaw, yaw, pitch, slots, dirs, weights);
  return [Array.from(dirs.subarray(0, slots)), Array.from(weights.subarray(0, slots))];
});
process.stdout.write(JSON.stringify(out));
"""

YAWS = np.deg2rad(np.arange(-93.0, 93.5, 6.0))  # 32 sampled yaws
TABLES = [(YAWS, np.zeros(1)), (YAWS, np.deg2rad([0.0, 40.0])), (YAWS, np.deg2rad([-20.0, 10.0, 45.0]))]


def bracket_cases(rng) -> list:
    cases = []
    for t, (yaws, pitches) in enumerate(TABLES):
        for _ in range(400):  # random views, some far from the model origin
            c = rng.normal(0, 30, 3) + (rng.uniform(-1e5, 1e5, 3) if rng.random() < 0.2 else 0)
            cases.append((c + rng.normal(0, 10, 3), c, rng.uniform(-4, 4), t))
        c = np.array([12.3, -4.56, 7.89])
        for base in (0.0, -math.pi, math.pi, 3 * math.pi, -1e3, 1e6, -1e9 * math.pi, 12345.678):
            for d in ((0, 0, 5), (0, 0, -5), (0, 0, 0), (3, 0, 0), (-3, 0, 0), (0, 1e-7, 2), (1e-6, 0, -2)):
                cases.append((c + d, c, base, t))  # straight above / below, at the centre, huge base yaws
        for k, y in enumerate(yaws):  # exactly (or within rounding of) a sampled yaw, and half-way
            for z in (0.0, 4.0):
                cases.append((c + (7, 0, z), c, -y, t))
                cases.append((c + (7, 0, z), c, 2 * math.pi - y, t))
                if k + 1 < len(yaws):
                    cases.append((c + (7, 0, z), c, -(y + yaws[k + 1]) / 2, t))
        for y in (yaws[0] - 1e-3, yaws[-1] + 1e-3, yaws[0] - 0.5, yaws[-1] + 0.5, math.pi, -math.pi + 1e-9):
            cases.append((c + (7 * math.cos(y), 7 * math.sin(y), 1), c, 0.0, t))  # beyond the table's ends
        for p in list(pitches) + [pitches[0] - 0.1, pitches[-1] + 0.1, 1.5, -1.5]:
            cases.append((c + (5 * math.cos(p), 0, 5 * math.sin(p)), c, 0.3, t))  # on / beyond a pitch
    return [([float(v) for v in eye], [float(v) for v in c], float(b), t) for eye, c, b, t in cases]


def test_view_bracket_matches_view_brackets(tmp_path):
    cases = bracket_cases(np.random.default_rng(1))
    tables = [dict(yaw=[float(v) for v in y], pitch=[float(v) for v in p], slots=storage_slots(len(p)))
              for y, p in TABLES]
    out = run_node(tmp_path, BRACKET_JS, dict(cases=cases, tables=tables))
    assert len(out) == len(cases)
    bad = []
    for (eye, c, base, t), (js_dirs, js_weights) in zip(cases, out):
        yaws, pitches = TABLES[t]
        dirs, weights = view_brackets(eye, np.array([c]), np.array([base]), yaws, pitches)
        assert len(js_dirs) == dirs.shape[1] == storage_slots(len(pitches))
        if js_dirs != dirs[0].tolist() or not np.allclose(js_weights, weights[0], rtol=0, atol=1e-6):
            bad.append((eye, c, base, t, js_dirs, js_weights, dirs[0].tolist(), weights[0].tolist()))
    assert not bad, f"{len(bad)} of {len(cases)} brackets differ, e.g. {bad[:3]}"


# ----------------------------------------------------------------------------------------------
# camera

CAMERA_JS = """import {viewCamera, projection, viewMatrix, worldFromPixel} from '@VIEWER@/camera.js';
const out = data.map(([view, w, h, origin]) => {
  const cam = viewCamera(view, w, h);
  const eye = cam.eye.map((v, k) => v - origin[k]);
  return {K: cam.K, R: cam.R, proj: projection(cam.K, w, h), view: viewMatrix(cam.R, eye), wfp: worldFromPixel(cam)};
});
process.stdout.write(JSON.stringify(out));
"""

BIG = (1e6 + 0.123456789, -2.5e6 + 0.987654321, 31.7)
VIEWS = [((0, 0, 0, 0, 0), (640, 480), (0, 0, 0)), ((1, 2, 3, 90, 0, 45), (1, 1), (0, 0, 0)),
         ((-5, 7, 1.5, -135, 30, 90), (1920, 1080), (1, 2, 3)), ((3, 4, 5, 720.5, -89.9, 1), (479, 1081), (0, 0, 0)),
         ((BIG[0] + 3, BIG[1] - 7, 35, 33.3, 89.9, 170), (800, 600), BIG), ((10, -20, 2, -1000, -45, 60.5), (33, 17), (9, 9, 9))]


def test_view_camera_matches_python(tmp_path):
    rng = np.random.default_rng(2)
    views = list(VIEWS) + [((*rng.normal(0, 50, 3), rng.uniform(-720, 720), rng.uniform(-89, 89), rng.uniform(1, 170)),
                            (int(rng.integers(1, 2000)), int(rng.integers(1, 2000))), tuple(rng.normal(0, 100, 3)))
                           for _ in range(40)]
    data = [([float(v) for v in view], w, h, [float(v) for v in origin]) for view, (w, h), origin in views]
    out = run_node(tmp_path, CAMERA_JS, data)
    for (view, w, h, origin), js in zip(data, out):
        K, T = view_camera(view, (w, h))
        cam = gl_camera(K, T, (w, h), origin)
        msg = f"view {view}, size {(w, h)}, origin {origin}"
        np.testing.assert_allclose(js["K"], K[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=1e-12, err_msg=msg)
        np.testing.assert_allclose(np.reshape(js["R"], (3, 3)), T[:3, :3], rtol=0, atol=1e-12, err_msg=msg)
        np.testing.assert_allclose(np.reshape(js["proj"], (4, 4)), cam.projection, rtol=1e-5, atol=1e-6, err_msg=msg)
        scale = max(1.0, float(np.abs(cam.eye).max()))
        np.testing.assert_allclose(np.reshape(js["view"], (4, 4)), cam.view, rtol=1e-5, atol=1e-6 * scale, err_msg=msg)
        wfp = T[:3, :3] @ np.linalg.inv(K)
        np.testing.assert_allclose(np.reshape(js["wfp"], (3, 3)), wfp, rtol=1e-9, atol=1e-12 * np.abs(wfp).max(),
                                   err_msg=msg)


# ----------------------------------------------------------------------------------------------
# frustum culling

CULL_JS = """import {viewCamera, projection, viewMatrix, multiply, fround} from '@VIEWER@/camera.js';
import {cullNodes, frustumPlanes} from '@VIEWER@/culling.js';
const bounds = Float32Array.from(data.bounds), children = Int32Array.from(data.children);
const range = Int32Array.from(data.range);
const out = data.cases.map(([view, w, h, pad]) => {
  const cam = viewCamera(view, w, h);
  const eye = cam.eye.map((v, k) => v - data.origin[k]);  // as WebModel.prepare
  const vp = multiply(fround(projection(cam.K, w, h)), fround(viewMatrix(cam.R, eye)));
  const planes = frustumPlanes(vp), ranges = [];
  const tested = cullNodes(planes, bounds, children, range, pad, (b, e) => ranges.push([b, e]));
  return {vp, planes, ranges, tested};
});
process.stdout.write(JSON.stringify(out));
"""


@pytest.fixture(scope="module")
def octree():
    """Billboards in occupied 0.5 m voxels of a town-like cloud: ground, walls and scattered points."""
    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(-30, 30, (3000, 2)), rng.uniform(0, 0.3, 3000)]
    wall = np.c_[rng.uniform(-20, 20, 1500), np.full(1500, 8.0), rng.uniform(0, 10, 1500)]
    cloud = rng.normal(0, 12, (1500, 3)) + (0, 0, 6)
    return build_octree(np.concatenate([ground, wall, cloud]) + BIG, OctreeConfig(voxel_size=0.5, min_points=1))


def test_cull_nodes_matches_frustum_cull_nodes(tmp_path, octree):
    origin = octree.origin
    bounds = (octree.node_bounds() - origin).astype(np.float32)
    children = octree.node_children.astype(np.int32)
    rng_ = octree.node_range.astype(np.int32)
    centres = octree.centres() - origin
    n = len(centres)
    radius = billboard_radius(octree.voxel_size)
    rng = np.random.default_rng(4)
    cases = []
    for i in range(160):
        eye = np.array(BIG) + rng.uniform((-40, -40, 0.5), (40, 40, 30)) * (3 if i % 10 == 0 else 1)
        view = [*eye, rng.uniform(-180, 180), rng.uniform(-60, 60), rng.uniform(15, 120)]
        cases.append(([float(v) for v in view], int(rng.integers(16, 1600)), int(rng.integers(16, 1200)),
                      0.0 if i % 2 else radius))
    data = dict(origin=[float(v) for v in origin], bounds=bounds.ravel().tolist(), children=children.ravel().tolist(),
                range=rng_.ravel().tolist(), cases=cases)
    out = run_node(tmp_path, CULL_JS, data)
    stats = dict(partial=0)
    for (view, w, h, pad), js in zip(cases, out):
        msg = f"view {view}, size {(w, h)}, pad {pad}"
        K, T = view_camera(view, (w, h))
        cam = gl_camera(K, T, (w, h), origin)
        vp = cam.projection.astype(np.float64) @ cam.view.astype(np.float64)  # as BillboardRenderer
        np.testing.assert_allclose(np.reshape(js["vp"], (4, 4)), vp, rtol=1e-12, atol=1e-12 * np.abs(vp).max(),
                                   err_msg=msg)
        planes = frustum_planes(vp)
        np.testing.assert_allclose(js["planes"], planes, rtol=1e-9, atol=1e-12 * np.abs(planes).max(), err_msg=msg)
        js_mask = ranges_to_mask(np.array(js["ranges"], np.int64).reshape(-1, 2), n)
        # both keep partial leaves whole, boxes grown by pad per axis, within the same tolerance
        whole = ranges_to_mask(frustum_cull_nodes(planes, bounds, children, rng_, pad=pad).visible_ranges, n)
        assert np.array_equal(js_mask, whole), f"{msg}: {np.flatnonzero(js_mask != whole)[:10]}"
        if pad:  # the model's pad: the desktop's draw set (partial leaves split per billboard) is never cut
            refined = frustum_cull_nodes(planes, bounds, children, rng_, pad=pad, centres=centres, radius=radius)
            missing = np.flatnonzero(ranges_to_mask(refined.visible_ranges, n) & ~js_mask)
            assert not len(missing), f"{msg}: JS drops {len(missing)} billboards the desktop draws, e.g. {missing[:10]}"
        stats["partial"] += int(0 < js_mask.sum() < n)
    assert stats["partial"] > 20, stats  # the views do cut the model
