"""The exported GLB opened by three.js (its GLTFLoader, pinned in tests/npm) in headless Chromium:
it loads, holds every quad where share.gltf put it, and draws."""

from __future__ import annotations

import functools
import http.server
import threading

import numpy as np
import pytest
from playwright.sync_api import sync_playwright

from billboards.model_writer import save
from share.browser import BROWSER_GL, chromium_path
from share.gltf import export_gltf

from .test_export_gltf import NPM, read_glb, street_model

SIZE = (320, 240)
PAGE = """<!DOCTYPE html>
<html><body style="margin:0"><canvas id="c" width="%d" height="%d"></canvas>
<script type="importmap">{"imports": {"three": "./three/build/three.module.js", "three/addons/": "./three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
import {GLTFLoader} from 'three/addons/loaders/GLTFLoader.js';
const canvas = document.getElementById('c');
const renderer = new THREE.WebGLRenderer({canvas, antialias: false, preserveDrawingBuffer: true});
new GLTFLoader().load('street.glb', (gltf) => {
  const scene = gltf.scene;
  scene.updateMatrixWorld(true);
  const box = new THREE.Box3().setFromObject(scene);
  let vertices = 0, meshes = 0;
  scene.traverse((o) => { if (o.isMesh) { meshes += 1; vertices += o.geometry.attributes.position.count; } });
  const centre = box.getCenter(new THREE.Vector3()), size = box.getSize(new THREE.Vector3());
  const camera = new THREE.PerspectiveCamera(60, canvas.width / canvas.height, 0.1, 1000);
  camera.position.set(centre.x, centre.y + size.y + 2, centre.z + Math.max(size.x, size.z));
  camera.lookAt(centre);
  renderer.setClearColor(0x000000);
  renderer.render(scene, camera);
  const gl = renderer.getContext(), px = new Uint8Array(canvas.width * canvas.height * 4);
  gl.readPixels(0, 0, canvas.width, canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
  let lit = 0;
  for (let i = 0; i < px.length; i += 4) lit += px[i] + px[i + 1] + px[i + 2] > 0 ? 1 : 0;
  window.result = {meshes, vertices, min: box.min.toArray(), max: box.max.toArray(), lit: lit / (px.length / 4)};
}, undefined, (e) => { window.result = {error: String(e && e.message || e)}; });
</script></body></html>"""


def test_threejs_loads_and_draws_the_glb(tmp_path):
    model_dir = save(street_model(), tmp_path / "model")
    three = NPM / "node_modules" / "three"
    if not three.is_dir():
        pytest.fail("tests/npm/node_modules/three is missing: run `make test` (it runs `npm ci --prefix tests/npm`)")
    glb = tmp_path / "street.glb"
    export_gltf(model_dir, glb)
    (tmp_path / "index.html").write_text(PAGE % SIZE)
    (tmp_path / "three").symlink_to(three)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    handler.log_message = lambda *a: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path(),
                                        args=[*BROWSER_GL["llvmpipe"], "--ignore-gpu-blocklist"])
            try:
                page = browser.new_page(viewport={"width": SIZE[0], "height": SIZE[1]})
                page.goto(f"http://127.0.0.1:{server.server_port}/index.html")
                page.wait_for_function("window.result !== undefined", timeout=60_000)
                result = page.evaluate("window.result")
            finally:
                browser.close()
    finally:
        server.shutdown()
        server.server_close()
    assert "error" not in result, result
    _, world, _, _, _ = read_glb(glb)
    assert result["vertices"] == world.size // 3 and result["meshes"] >= 1
    # glTF (x, y, z) = world (x, z, −y)
    gltf = np.stack([world[..., 0], world[..., 2], -world[..., 1]], -1).reshape(-1, 3)
    np.testing.assert_allclose(result["min"], gltf.min(0), atol=1e-3)
    np.testing.assert_allclose(result["max"], gltf.max(0), atol=1e-3)
    assert result["lit"] > 0.01, f"three.js drew {result['lit']:.1%} of the frame"
