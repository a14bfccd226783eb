// The street viewer: WebGL2, the desktop's shaders, fly/drive controls, the view in the link
// (#x,y,z,yaw,pitch[,fov]) and a HUD with the frame rate. ?size=WxH fixes the canvas size
// (tests, benchmarks); otherwise the canvas fills the window.
//
// window.bbcity, for scripts and tests: ready (a Promise of the first frame with the model),
// firstFrameMs (from navigation start), setView(view), setCamera(pose, K) (a pose as 9 rotation
// numbers row by row then the eye, K = [fx, fy, cx, cy]), walk(poses, K) (the loop shows each
// pose in turn: the ms between its frames), render() (a frame drawn now, its stats),
// pixels() (a frame drawn now, read back: RGBA, bottom row first, base64), idle() (a Promise of every tile the
// view wants being resident), benchmark(rows, K) (poses, each 9 rotation numbers row by row
// then the eye, drawn and read back one by one with intrinsics K = [fx, fy, cx, cy]: each frame's ms), stats().

import {cameraView, poseCamera, projection, viewCamera, DEFAULT_FOV_DEG} from './camera.js';
import {SkyPass} from './sky.js';
import {TileStreamer} from './tiles.js';

const canvas = document.getElementById('view');
const hud = document.getElementById('hud');
const help = document.getElementById('help');
const params = new URLSearchParams(location.search);
const fixed = params.get('size') ? params.get('size').split('x').map(Number) : null;
let ready, failed;
const api = {ready: new Promise((res, rej) => { ready = res; failed = rej; }), firstFrameMs: null, error: null};
window.bbcity = api;

function fail(message) {
  api.error = message;
  hud.textContent = `error: ${message}`;
  failed(new Error(message));
}

function compile(gl, name, sources) {
  const prog = gl.createProgram();
  for (const [stage, type] of [['vertex_shader', gl.VERTEX_SHADER], ['fragment_shader', gl.FRAGMENT_SHADER]]) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, sources[stage]);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(`${name} ${stage}: ${gl.getShaderInfoLog(sh)}`);
    gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(`${name}: ${gl.getProgramInfoLog(prog)}`);
  return prog;
}

function parseView(hash, fallback) {
  const v = hash.replace(/^#/, '').split(',').map(Number);
  if ((v.length === 5 || v.length === 6) && v.every(Number.isFinite)) return v.length === 5 ? [...v, fallback[5]] : v;
  return fallback;
}

async function main() {
  const gl = canvas.getContext('webgl2', {antialias: false, alpha: false, depth: true, preserveDrawingBuffer: false});
  if (!gl) return fail('this browser has no WebGL2');
  if (!gl.getExtension('EXT_color_buffer_float')) return fail('this browser cannot render into float textures');
  const [site, shaders] = await Promise.all(['site.json', 'shaders.json'].map((f) => fetch(f).then((r) => r.json())));
  const programs = {};
  for (const [name, sources] of Object.entries(shaders)) programs[name] = compile(gl, name, sources);
  const sky = site.sky ? new SkyPass(gl, programs.sky, site.sky) : null;
  const tiles = new TileStreamer(gl, site.tiles, site.gpu_budget_bytes, programs, fail);
  let view = parseView(location.hash, [...site.start, site.fov_deg || DEFAULT_FOV_DEG]);
  let mode = 'fly', linear = params.get('filter') !== 'nearest', playing = -1, last = performance.now(), frames = 0, fpsTime = last, fps = 0;
  let stats = {}, hashTime = 0, hashView = '', bench = null;
  const keys = new Set();

  function size() {
    if (fixed) return fixed;
    const r = window.devicePixelRatio || 1;
    return [Math.round(window.innerWidth * r), Math.round(window.innerHeight * r)];
  }

  function camera(w, h) {
    if (bench) return bench;
    return playing >= 0 ? poseCamera(site.path[playing], view[5], w, h) : viewCamera(view, w, h);
  }

  function frame() {
    const [w, h] = size();
    if (canvas.width !== w || canvas.height !== h) {
      canvas.width = w; canvas.height = h;
      canvas.style.width = `${fixed ? w : window.innerWidth}px`;
      canvas.style.height = `${fixed ? h : window.innerHeight}px`;
    }
    const cam = camera(w, h);
    tiles.update(cam.eye);
    const proj = projection(cam.K, w, h), options = {linear, cull: params.get('cull') !== 'none'};
    stats = tiles.prepare(cam, proj, options);  // atlas passes first: the frame's pass is not cut
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, w, h);
    gl.disable(gl.BLEND); gl.disable(gl.CULL_FACE);
    gl.clearColor(0, 0, 0, 1); gl.clearDepth(1);
    gl.depthMask(true);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST); gl.depthFunc(gl.LESS);
    tiles.emit(proj, options);
    if (sky) {  // behind the model: only where it drew nothing (sky.glsl's depth is the far plane)
      gl.depthFunc(gl.LEQUAL); gl.depthMask(false);
      sky.draw(cam, h);
      gl.depthMask(true); gl.depthFunc(gl.LESS);
    }
    stats.resident = tiles.resident; stats.gpuMB = tiles.residentBytes / 1e6;
    if (api.firstFrameMs === null && stats.tiles > 0) {
      api.firstFrameMs = performance.now();
      ready(api.firstFrameMs);
    }
    return stats;
  }

  function move(dt) {
    if (playing >= 0) {
      playing = (playing + 1) % site.path.length;
      return;
    }
    const speed = (keys.has('Shift') ? 12 : 3) * dt;
    const a = view[3] * Math.PI / 180, b = mode === 'fly' ? view[4] * Math.PI / 180 : 0;
    const fwd = [Math.cos(b) * Math.cos(a), Math.cos(b) * Math.sin(a), Math.sin(b)], right = [Math.sin(a), -Math.cos(a), 0];
    const go = (v, s) => { for (let k = 0; k < 3; ++k) view[k] += v[k] * s; };
    if (keys.has('w') || keys.has('ArrowUp')) go(fwd, speed);
    if (keys.has('s') || keys.has('ArrowDown')) go(fwd, -speed);
    if (mode === 'drive') {  // the arrows and A/D steer
      if (keys.has('a') || keys.has('ArrowLeft')) view[3] += 60 * dt;
      if (keys.has('d') || keys.has('ArrowRight')) view[3] -= 60 * dt;
    } else {
      if (keys.has('d') || keys.has('ArrowRight')) go(right, speed);
      if (keys.has('a') || keys.has('ArrowLeft')) go(right, -speed);
      if (keys.has('e')) view[2] += speed;
      if (keys.has('q')) view[2] -= speed;
    }
  }

  function loop(now) {
    move(Math.min((now - last) / 1000, 0.1));
    last = now;
    frame();
    ++frames;
    if (now - fpsTime > 500) {
      fps = frames * 1000 / (now - fpsTime);
      frames = 0; fpsTime = now;
      const v = playing >= 0 ? cameraView(camera(1, 1)) : view;
      hud.textContent = `${fps.toFixed(1)} fps · ${mode}${playing >= 0 ? ' · capture path' : ''}\n` +
        `quads ${stats.quads} · decoded ${stats.decoded} · tiles ${stats.resident}/${site.tiles.length} · ` +
        `GPU ${stats.gpuMB.toFixed(0)} MB\n${v.slice(0, 3).map((x) => x.toFixed(1)).join(', ')} · ` +
        `yaw ${v[3].toFixed(0)}° pitch ${v[4].toFixed(0)}°`;
    }
    const text = view.map((x) => +x.toFixed(3)).join(',');
    if (playing < 0 && text !== hashView && now - hashTime > 250) {
      history.replaceState(null, '', `${location.pathname}${location.search}#${text}`);
      hashView = text; hashTime = now;
    }
    requestAnimationFrame(loop);
  }

  window.addEventListener('hashchange', () => { view = parseView(location.hash, view); playing = -1; });
  window.addEventListener('keydown', (e) => {
    keys.add(e.key.length === 1 ? e.key.toLowerCase() : e.key);
    if (e.key === 'g') mode = mode === 'fly' ? 'drive' : 'fly';
    if (e.key === 'l') linear = !linear;
    if (e.key === 'h') help.hidden = !help.hidden;
    if (e.key === 'p') {
      if (playing >= 0) { view = [...cameraView(camera(1, 1)), view[5]]; playing = -1; }
      else if (site.path.length) playing = 0;
    }
  });
  window.addEventListener('keyup', (e) => keys.delete(e.key.length === 1 ? e.key.toLowerCase() : e.key));
  canvas.addEventListener('pointermove', (e) => {
    if (!(e.buttons & 1)) return;
    view[3] -= e.movementX * 0.2;
    view[4] = Math.max(-89, Math.min(89, view[4] - e.movementY * 0.2));
  });

  Object.assign(api, {
    setView(v) { view = [...v.slice(0, 5), v.length > 5 ? v[5] : view[5]]; playing = -1; bench = null; },
    setCamera(row, K) { bench = {K, R: row.slice(0, 9), eye: row.slice(9, 12)}; },  // until setView
    async walk(rows, K) {  // the loop draws each pose in turn: [ms between frames], peak GPU MB
      const ms = [];
      let last = performance.now();
      for (const row of rows) {
        bench = {K, R: row.slice(0, 9), eye: row.slice(9, 12)};
        await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
        const now = performance.now();
        ms.push(now - last);
        last = now;
      }
      return ms;
    },
    render() { return frame(); },
    pixels() {  // drawn and read in one task: the canvas is cleared once the browser shows it
      frame();
      const [w, h] = size(), px = new Uint8Array(w * h * 4);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
      let s = '';
      for (let i = 0; i < px.length; i += 0x8000) s += String.fromCharCode.apply(null, px.subarray(i, i + 0x8000));
      return btoa(s);
    },
    async idle() {
      for (;;) {
        tiles.update(camera(1, 1).eye);
        if (tiles.pending(camera(1, 1).eye) === 0) return;
        await new Promise((r) => setTimeout(r, 20));
      }
    },
    benchmark(rows, K) {
      const [w, h] = size(), px = new Uint8Array(w * h * 4), ms = [];
      bench = {K, R: rows[0].slice(0, 9), eye: rows[0].slice(9, 12)};
      frame();  // untimed: the first pose's tiles decoded
      for (const row of rows) {
        const t0 = performance.now();
        bench = {K, R: row.slice(0, 9), eye: row.slice(9, 12)};
        frame();
        gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);  // the frame read back, as bbcity fps does
        ms.push(performance.now() - t0);
      }
      bench = null;
      return ms;
    },
    stats() { return {...stats, fps, peakMB: tiles.peakBytes / 1e6, budgetMB: tiles.budget / 1e6,
                      loads: tiles.loads, releases: tiles.releases, pathPoses: site.path.length}; },
  });
  requestAnimationFrame(loop);
}

main().catch((e) => fail(e.message));
