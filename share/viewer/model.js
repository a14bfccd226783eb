// One model (or tile) on the GPU, drawn as render/gpu_decode.py draws it without level of detail:
// eigen-textures decoded once per sampled direction into a decoded atlas (billboard_decode.glsl,
// one point per tile), quads drawn blending the direction bracket around the eye
// (billboard.glsl), the facade layer's columns as slits. The files are share/web_model.py's.

import {cullNodes, frustumPlanes} from './culling.js';
import {glMat, fround, multiply, viewMatrix} from './camera.js';

const QUAD_WORDS = 17;   // centre 3f, base_yaw f, kind i, size f, blocks i, origin 2f, weights 4f, corner_dz 4f
const DECODE_WORDS = 5;  // origin 2i, slot 2i, direction i
const BLEND_WORDS = 9;   // source 2i, target 2i, blocks i, weights 4f
// Quads are drawn as indexed triangles, their record repeated at each of their 4 corners, not as
// instances: SwiftShader (software WebGL) pays per instance about what llvmpipe pays per draw
// (the street's 38 000 quads took 180 ms instanced). The shaders' corner from gl_VertexID is the
// same: vertex 4q + c is corner c of quad q.
const CORNERS = 4;
const PREBLEND_TEXEL_PX = 2.0;  // render.gpu_decode.PREBLEND_TEXEL_PX
const DECODED_UNIT = 6;

const DTYPES = {'<f4': Float32Array, '<i4': Int32Array, '|u1': Uint8Array};

async function fetchBytes(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.arrayBuffer();
}

// Directions and weights per storage slot for a quad at `c` seen from `eye` (model coordinates):
// render/view_brackets.py's view_brackets for one quad. Writes dirs[0..S), weights[0..S).
export function viewBracket(eye, cx, cy, cz, baseYaw, yawOffsets, pitches, slots, dirs, weights) {
  const f = Math.fround;
  const vx = f(f(eye[0]) - f(cx)), vy = f(f(eye[1]) - f(cy)), vz = f(f(eye[2]) - f(cz));
  let yaw = Math.atan2(vy, vx) - baseYaw;
  const m = (Math.PI - yaw) % (2 * Math.PI);
  yaw = Math.PI - (m < 0 ? m + 2 * Math.PI : m);
  const pitch = Math.atan2(vz, Math.hypot(vx, vy));
  const [y0, y1, fy] = bracket(interp(yaw, yawOffsets), yawOffsets.length);
  const [p0, p1, fp] = bracket(interp(pitch, pitches), pitches.length);
  const dy = yawOffsets.length;
  for (let s = 0; s < slots; ++s) { dirs[s] = -1; weights[s] = 0; }
  for (const [p, wp] of [[p0, f(1 - fp)], [p1, fp]]) {
    for (const [y, wy] of [[y0, f(1 - fy)], [y1, fy]]) {
      const w = f(wp * wy);
      const slot = slots === 2 ? (y & 1) : (p & 1) * 2 + (y & 1);
      weights[slot] += w;
      if (w > 0) dirs[slot] = p * dy + y;
    }
  }
  for (let s = 0; s < slots; ++s) {
    if (weights[s] <= 0) dirs[s] = -1;
    weights[s] = f(weights[s]);
  }
}

// numpy's interp of x over increasing xp against 0, 1, …: clamped at both ends.
function interp(x, xp) {
  const n = xp.length;
  if (n === 1 || x <= xp[0]) return 0;
  if (x >= xp[n - 1]) return n - 1;
  let i = 0;
  while (xp[i + 1] < x) ++i;
  return i + (x - xp[i]) / (xp[i + 1] - xp[i]);
}

// billboards.decode.bracket: neighbouring indices and the float32 weight of the second.
function bracket(index, count) {
  const x = Math.min(Math.max(index, 0), count - 1);
  const i0 = Math.min(Math.floor(x), Math.max(count - 2, 0));
  return [i0, Math.min(i0 + 1, count - 1), Math.fround(x - i0)];
}

export class WebModel {
  // gl: WebGL2 context; base: URL of the model's folder; programs: {draw_s2_l1: …, decode: …}.
  static async load(gl, base, programs) {
    const doc = JSON.parse(new TextDecoder().decode(await fetchBytes(`${base}/model.json`)));
    const fetches = [fetchBytes(`${base}/${doc.tables.file}`),
                     ...doc.pages.map((p) => fetchBytes(`${base}/${p.file}`)),
                     ...doc.coef_pages.map((p) => fetchBytes(`${base}/${p.file}`))];
    const [tables, ...pages] = await Promise.all(fetches);
    return new WebModel(gl, doc, tables, pages.slice(0, doc.pages.length), pages.slice(doc.pages.length), programs);
  }

  constructor(gl, doc, tables, pages, coefPages, programs) {
    this.gl = gl;
    this.doc = doc;
    this.origin = doc.origin;
    this.t = {};
    for (const [name, e] of Object.entries(doc.tables.arrays)) {
      const type = DTYPES[e.dtype];
      const count = e.shape.reduce((a, b) => a * b, 1);
      this.t[name] = new type(tables, e.offset, count);
    }
    this.slots = doc.storage_slots;
    this.n = doc.billboards;
    this.columns = doc.columns;
    this.held = new Int32Array(this.n * this.slots).fill(-1);  // direction each position's slot holds
    this.marked = new Uint8Array(this.columns);
    this.quads = new ArrayBuffer(Math.max(this.columns, 1) * QUAD_WORDS * 4 * CORNERS);
    this.quadF = new Float32Array(this.quads);
    this.quadI = new Int32Array(this.quads);
    this.decodes = new Int32Array(1024 * DECODE_WORDS);
    this.blends = new ArrayBuffer(1024 * BLEND_WORDS * 4 * CORNERS);
    this.viewBlends();
    this.dirs = new Int32Array(4);
    this.weights = new Float64Array(4);
    this.programs = programs;
    this.objects = [];
    this.upload(pages, coefPages);
    this.gpuBytes = doc.gpu_bytes;
  }

  viewBlends() {
    this.blendI = new Int32Array(this.blends);
    this.blendF = new Float32Array(this.blends);
  }

  upload(pages, coefPages) {
    const gl = this.gl, doc = this.doc;
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    const f16 = doc.tile_mode === 'f16';
    this.tiles = this.pageArray(doc.pages, pages, doc.atlas_width, f16 ? gl.RGBA16F : gl.RGBA8, gl.RGBA,
                                f16 ? gl.HALF_FLOAT : gl.UNSIGNED_BYTE, f16 ? Uint16Array : Uint8Array, 4);
    this.sampling(gl.TEXTURE_2D_ARRAY, gl.LINEAR);
    const coef = {u8: [gl.R8, gl.UNSIGNED_BYTE, Uint8Array], f16: [gl.R16F, gl.HALF_FLOAT, Uint16Array],
                  f32: [gl.R32F, gl.FLOAT, Float32Array]}[doc.coef_mode];
    this.coefs = this.pageArray(doc.coef_pages, coefPages, doc.coef_width, coef[0], gl.RED, coef[1], coef[2], 1);
    const table = this.t.slot_table;
    const tableShape = doc.tables.arrays.slot_table.shape;  // rows, 3·slots_per_row, 4
    this.slotTable = this.keep(gl.createTexture());
    gl.bindTexture(gl.TEXTURE_2D, this.slotTable);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, tableShape[1], tableShape[0]);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, tableShape[1], tableShape[0], gl.RGBA, gl.FLOAT, table);
    this.sampling(gl.TEXTURE_2D, gl.NEAREST);
    delete this.t.slot_table;
    // the decode pass writes unclamped values (the blend clamps): a half-float target
    [this.decoded, this.decodedFbo] = this.atlasTarget(gl.RGBA16F, doc.decoded_size);
    [this.viewTiles, this.viewFbo] = this.atlasTarget(gl.RGBA8, doc.view_size);
    this.quadBuffers = [this.keep(gl.createBuffer()), this.keep(gl.createBuffer())];
    this.indexBuffer = this.keep(gl.createBuffer());
    const indices = new Uint32Array(Math.max(this.columns, 1) * 6);
    for (let q = 0; q < this.columns; ++q) indices.set([0, 1, 2, 2, 1, 3].map((c) => 4 * q + c), q * 6);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, null);
    this.decodeBuffer = this.keep(gl.createBuffer());
    this.blendBuffer = this.keep(gl.createBuffer());
    this.drawVaos = {};
    for (const view of [0, 1]) {
      for (const linear of [0, 1]) {
        const prog = this.programs[`draw_s${this.slots}_v${view}_l${linear}`];
        this.drawVaos[`${view}${linear}`] = this.vertexArray(prog, this.quadBuffers[view], QUAD_WORDS * 4, this.indexBuffer, [
          ['in_centre', 3, 'f', 0], ['in_base_yaw', 1, 'f', 3], ['in_kind', 1, 'i', 4], ['in_size', 1, 'f', 5],
          ['in_blocks', 1, 'i', 6], ['in_origin', 2, 'f', 7], ['in_weights', 4, 'f', 9], ['in_corner_dz', 4, 'f', 13]]);
      }
    }
    this.blendVao = this.vertexArray(this.programs[`blend_s${this.slots}`], this.blendBuffer, BLEND_WORDS * 4, this.indexBuffer, [
      ['in_source', 2, 'i', 0], ['in_target', 2, 'i', 2], ['in_blocks', 1, 'i', 4], ['in_weights', 4, 'f', 5]]);
    this.decodeVao = this.vertexArray(this.programs.decode, this.decodeBuffer, DECODE_WORDS * 4, null, [
      ['in_origin', 2, 'i', 0], ['in_slot', 2, 'i', 2], ['in_direction', 1, 'i', 4]]);
  }

  keep(obj) { this.objects.push(obj); return obj; }

  // Filter (gl.NEAREST or gl.LINEAR) and clamp the texture bound to `target`.
  sampling(target, filter) {
    const gl = this.gl;
    gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, filter);
    gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, filter);
    gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  // An atlas a pass renders into: a bilinear texture of `internal` format and [w, h] texels
  // (sampled only within its tiles) and its framebuffer.
  atlasTarget(internal, [w, h]) {
    const gl = this.gl, tex = this.keep(gl.createTexture()), fbo = this.keep(gl.createFramebuffer());
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, internal, w, h);
    this.sampling(gl.TEXTURE_2D, gl.LINEAR);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    const complete = gl.checkFramebufferStatus(gl.FRAMEBUFFER) === gl.FRAMEBUFFER_COMPLETE;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (!complete) throw new Error('this browser cannot render into the atlases (EXT_color_buffer_float)');
    return [tex, fbo];
  }

  // A texture array of pages (one layer each, the tallest page's height), NEAREST.
  pageArray(entries, buffers, width, internal, format, type, View, components) {
    const gl = this.gl;
    const tex = this.keep(gl.createTexture());
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
    const height = Math.max(1, ...entries.map((p) => p.height));
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, internal, Math.max(width, 1), height, Math.max(entries.length, 1));
    entries.forEach((p, layer) => {
      const data = new View(buffers[layer], 0, p.width * p.height * components);
      gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, layer, p.width, p.height, 1, format, type, data);
    });
    this.sampling(gl.TEXTURE_2D_ARRAY, gl.NEAREST);
    return tex;
  }

  // A vertex array of `prog`'s attributes, one record per vertex in `buffer` (and `indices`, if any).
  vertexArray(prog, buffer, stride, indices, attributes) {
    const gl = this.gl;
    const vao = this.keep(gl.createVertexArray());
    gl.bindVertexArray(vao);
    if (indices) gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, indices);
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    for (const [name, size, kind, word] of attributes) {
      const loc = gl.getAttribLocation(prog, name);
      if (loc < 0) continue;  // dropped by the compiler
      gl.enableVertexAttribArray(loc);
      if (kind === 'i') gl.vertexAttribIPointer(loc, size, gl.INT, stride, word * 4);
      else gl.vertexAttribPointer(loc, size, gl.FLOAT, false, stride, word * 4);
    }
    gl.bindVertexArray(null);
    return vao;
  }

  // The columns to draw from `cam` ({R, eye (world)}, viewProj row-major): whole columns of every
  // billboard in the frustum, in position order (as the desktop draws them). Returns their count.
  visibleColumns(viewProj, cull) {
    const t = this.t, marked = this.marked;
    marked.fill(0);
    let tested = 0;
    if (!cull) marked.fill(1);
    else {
      const columnOf = t.column_of;
      tested = cullNodes(frustumPlanes(viewProj), t.node_bounds, t.node_children, t.node_range, this.doc.pad,
                         (begin, end) => { for (let b = begin; b < end; ++b) marked[columnOf[b]] = 1; });
    }
    this.nodesTested = tested;
    this.list = this.list || new Int32Array(this.columns);
    let count = 0;
    for (let c = 0; c < this.columns; ++c) if (marked[c]) this.list[count++] = c;
    return count;
  }

  // Everything a draw from `cam` ({R, eye (world), K}; proj: row-major GL projection) needs before
  // the frame's framebuffer is bound: the columns in the frustum, their direction brackets, the
  // tiles decoded and the large quads pre-blended (render.gpu_decode: quads whose texel spans
  // PREBLEND_TEXEL_PX pixels or more are blended once per texel into the RGBA8 view atlas). Each
  // pass that writes an atlas leaves the default framebuffer bound; the frame's pass is never cut.
  // Returns {quads, instances, decoded, blended, nodes}.
  prepare(cam, proj, {cull = true} = {}) {
    const t = this.t, doc = this.doc, S = this.slots;
    const eye = [cam.eye[0] - this.origin[0], cam.eye[1] - this.origin[1], cam.eye[2] - this.origin[2]];
    this.eye = eye;
    this.view = fround(viewMatrix(cam.R, eye));
    const count = this.visibleColumns(multiply(fround(proj), this.view), cull);
    const tile = doc.tile, yawOffsets = doc.yaw_offsets, pitches = doc.pitches, focal = cam.K[0];
    const centres = t.centres, starts = t.column_start, counts = t.column_count, held = this.held;
    const qF = this.quadF, qI = this.quadI, dirs = this.dirs, weights = this.weights;
    let decodes = 0, instances = 0, front = 0, back = count, blended = 0;
    for (let i = 0; i < count; ++i) {
      const col = this.list[i], start = starts[col], n = counts[col], end = start + n - 1;
      const cx = 0.5 * (centres[start * 3] + centres[end * 3]);
      const cy = 0.5 * (centres[start * 3 + 1] + centres[end * 3 + 1]);
      const cz = 0.5 * (centres[start * 3 + 2] + centres[end * 3 + 2]);
      viewBracket(eye, cx, cy, cz, t.base_yaw[start], yawOffsets, pitches, S, dirs, weights);
      for (let p = start; p <= end; ++p) {
        for (let s = 0; s < S; ++s) {
          const d = dirs[s];
          if (d < 0 || held[p * S + s] === d) continue;
          decodes = this.addDecode(decodes, p, s, d, tile);
          held[p * S + s] = d;
        }
      }
      const dist = Math.hypot(cx - eye[0], cy - eye[1], cz - eye[2]);
      const texelPx = dist > 0 ? focal * t.edge[start] / (tile * dist) : Infinity;
      let used = 0;
      for (let s = 0; s < S; ++s) used += weights[s] !== 0 ? 1 : 0;
      const blend = texelPx >= PREBLEND_TEXEL_PX && used > 1;
      const o = (blend ? --back : front++) * QUAD_WORDS * CORNERS;  // decoded-atlas quads first, then the view atlas's
      const origin = blend ? t.view_origin : t.decoded_origin;
      qF[o] = cx; qF[o + 1] = cy; qF[o + 2] = cz;
      qF[o + 3] = t.base_yaw[start];
      qI[o + 4] = t.kind[start];
      qF[o + 5] = t.edge[start];
      qI[o + 6] = n;
      qF[o + 7] = origin[start * 2]; qF[o + 8] = origin[start * 2 + 1];
      for (let s = 0; s < 4; ++s) qF[o + 9 + s] = s < S ? weights[s] : 0;
      for (let k = 0; k < 4; ++k) qF[o + 13 + k] = t.corner_dz[start * 4 + k];
      for (let c = 1; c < CORNERS; ++c) qF.copyWithin(o + c * QUAD_WORDS, o, o + QUAD_WORDS);
      if ((blended + 1) * BLEND_WORDS * 4 * CORNERS > this.blends.byteLength) {
        const grown = new ArrayBuffer(this.blends.byteLength * 2);
        new Uint8Array(grown).set(new Uint8Array(this.blends));
        this.blends = grown;
        this.viewBlends();
      }
      if (blend) {
        const b = blended++ * BLEND_WORDS * CORNERS;
        this.blendI[b] = t.decoded_origin[start * 2]; this.blendI[b + 1] = t.decoded_origin[start * 2 + 1];
        this.blendI[b + 2] = t.view_origin[start * 2]; this.blendI[b + 3] = t.view_origin[start * 2 + 1];
        this.blendI[b + 4] = n;
        for (let s = 0; s < 4; ++s) this.blendF[b + 5 + s] = s < S ? weights[s] : 0;
        for (let c = 1; c < CORNERS; ++c) this.blendF.copyWithin(b + c * BLEND_WORDS, b, b + BLEND_WORDS);
      }
      instances += n;
    }
    if (decodes) this.runDecode(decodes);
    if (blended) this.runBlend(blended);
    this.counts = [front, count - front];
    return {quads: count, instances, decoded: decodes, blended, nodes: this.nodesTested};
  }

  // Draw what prepare() planned into the bound framebuffer (viewport = the camera's size):
  // one instanced draw from the decoded atlas, one from the view atlas.
  emit(proj, {linear = true} = {}) {
    const gl = this.gl, doc = this.doc, S = this.slots;
    if (!this.counts) return;
    const sources = [[this.decoded, doc.decoded_size, 0], [this.viewTiles, doc.view_size, this.counts[0]]];
    sources.forEach(([atlas, atlasSize, first], view) => {
      const n = this.counts[view];
      if (!n) return;
      const prog = this.programs[`draw_s${S}_v${view}_l${linear ? 1 : 0}`];
      gl.bindBuffer(gl.ARRAY_BUFFER, this.quadBuffers[view]);
      gl.bufferData(gl.ARRAY_BUFFER, this.quadF.subarray(first * QUAD_WORDS * CORNERS, (first + n) * QUAD_WORDS * CORNERS),
                    gl.STREAM_DRAW);
      gl.useProgram(prog);
      gl.activeTexture(gl.TEXTURE0 + DECODED_UNIT);
      gl.bindTexture(gl.TEXTURE_2D, atlas);
      uniforms(gl, prog, {
        u_tiles_in: ['1i', DECODED_UNIT], u_atlas_texel: ['2f', 1 / atlasSize[0], 1 / atlasSize[1]],
        u_projection: ['m4', glMat(proj)], u_view: ['m4', glMat(this.view)], u_eye: ['3f', ...this.eye.map(Math.fround)],
        u_spherical: ['1i', doc.spherical ? 1 : 0], u_tile: ['1i', doc.tile]});
      gl.bindVertexArray(this.drawVaos[`${view}${linear ? 1 : 0}`]);
      gl.drawElements(gl.TRIANGLES, 6 * n, gl.UNSIGNED_INT, 0);
    });
    gl.bindVertexArray(null);
    this.counts = null;
  }

  addDecode(k, position, slot, direction, tile) {
    if ((k + 1) * DECODE_WORDS > this.decodes.length) {
      const grown = new Int32Array(this.decodes.length * 2);
      grown.set(this.decodes);
      this.decodes = grown;
    }
    const t = this.t, o = k * DECODE_WORDS, b = position;
    this.decodes[o] = t.decoded_origin[b * 2] + slot * tile;
    this.decodes[o + 1] = t.decoded_origin[b * 2 + 1];
    this.decodes[o + 2] = t.first_slot[b];
    this.decodes[o + 3] = t.rank[b];
    this.decodes[o + 4] = direction;
    return k + 1;
  }

  // The decode pass: `count` tiles into the decoded atlas, one point each.
  runDecode(count) {
    const gl = this.gl, doc = this.doc, prog = this.programs.decode;
    gl.useProgram(prog);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.decodeBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, this.decodes.subarray(0, count * DECODE_WORDS), gl.STREAM_DRAW);
    const units = [[this.tiles, gl.TEXTURE_2D_ARRAY, 'u_tiles'], [this.coefs, gl.TEXTURE_2D_ARRAY, 'u_coefs'],
                   [this.slotTable, gl.TEXTURE_2D, 'u_slot_table']];
    const values = {u_linear: ['1i', 0], u_decoded_size: ['2f', ...doc.decoded_size]};
    units.forEach(([tex, target, name], unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(target, tex);
      values[name] = ['1i', unit];
    });
    for (const [name, v] of Object.entries(doc.uniforms)) values[name] = ['1i', v];
    uniforms(gl, prog, values);
    this.offscreen(this.decodedFbo, doc.decoded_size, this.decodeVao, count, true);
  }

  // The pre-blend pass: `count` runs' bracket tiles blended into the view atlas, a quad per run.
  runBlend(count) {
    const gl = this.gl, doc = this.doc, prog = this.programs[`blend_s${this.slots}`];
    gl.useProgram(prog);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.blendBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Uint8Array(this.blends, 0, count * BLEND_WORDS * 4 * CORNERS), gl.STREAM_DRAW);
    gl.activeTexture(gl.TEXTURE0 + DECODED_UNIT);
    gl.bindTexture(gl.TEXTURE_2D, this.decoded);
    uniforms(gl, prog, {u_tile: ['1i', doc.tile], u_decoded: ['1i', DECODED_UNIT],
                        u_target_size: ['2f', ...doc.view_size]});
    this.offscreen(this.viewFbo, doc.view_size, this.blendVao, count);
  }

  // Draw `count` points (one a tile) or indexed quads into an atlas's framebuffer without depth;
  // the default framebuffer bound after.
  offscreen(fbo, size, vao, count, points = false) {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.viewport(0, 0, size[0], size[1]);
    gl.disable(gl.DEPTH_TEST);
    gl.bindVertexArray(vao);
    if (points) gl.drawArrays(gl.POINTS, 0, count);
    else gl.drawElements(gl.TRIANGLES, 6 * count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  release() {
    const gl = this.gl;
    for (const obj of this.objects.reverse()) {
      if (obj instanceof WebGLTexture) gl.deleteTexture(obj);
      else if (obj instanceof WebGLBuffer) gl.deleteBuffer(obj);
      else if (obj instanceof WebGLFramebuffer) gl.deleteFramebuffer(obj);
      else if (obj instanceof WebGLVertexArrayObject) gl.deleteVertexArray(obj);
    }
    this.objects = [];
    this.t = {};
  }
}

// Set uniforms the program uses: {name: ['1i' | '2f' | '3f' | 'm4' | 'm3', ...values]}.
export function uniforms(gl, prog, values) {
  for (const [name, [kind, ...v]] of Object.entries(values)) {
    const loc = gl.getUniformLocation(prog, name);
    if (loc === null) continue;
    if (kind === '1i') gl.uniform1i(loc, v[0]);
    else if (kind === '1f') gl.uniform1f(loc, v[0]);
    else if (kind === '2f') gl.uniform2f(loc, v[0], v[1]);
    else if (kind === '3f') gl.uniform3f(loc, v[0], v[1], v[2]);
    else if (kind === 'm4') gl.uniformMatrix4fv(loc, false, v[0]);
    else if (kind === 'm3') gl.uniformMatrix3fv(loc, false, v[0]);
  }
}
