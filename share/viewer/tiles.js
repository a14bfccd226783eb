// The tiles of a site (one for a plain model) made resident nearest first within a GPU budget:
// a tile's files are fetched in the background (at most MAX_LOADS at once) and uploaded when
// they have all arrived; tiles beyond the budget are released, farthest first. Every resident
// tile is drawn; a tile outside the view costs its octree root's test.

import {WebModel} from './model.js';

const MAX_LOADS = 2;

export class TileStreamer {
  // tiles: site.json's [{name, dir, lo, hi, gpu_bytes}]; budget: bytes; programs: compiled programs.
  constructor(gl, tiles, budget, programs, onError) {
    this.gl = gl;
    this.tiles = tiles.map((t, i) => ({...t, index: i, model: null, loading: false, distance: 0}));
    this.budget = budget;
    this.programs = programs;
    this.onError = onError;
    this.residentBytes = 0;
    this.peakBytes = 0;
    this.loads = 0;
    this.releases = 0;
  }

  // Tiles nearest `eye` (world) first that fit the budget (the nearest always).
  wanted(eye) {
    for (const t of this.tiles) {
      let s = 0;
      for (let k = 0; k < 3; ++k) {
        const gap = Math.max(t.lo[k] - eye[k], eye[k] - t.hi[k], 0);
        s += gap * gap;
      }
      t.distance = Math.sqrt(s);
    }
    const order = [...this.tiles].sort((a, b) => a.distance - b.distance || a.index - b.index);
    const want = new Set();
    let bytes = 0;
    for (const t of order) {
      if (want.size && bytes + t.gpu_bytes > this.budget) break;
      want.add(t);
      bytes += t.gpu_bytes;
    }
    return [order, want];
  }

  // Release what the eye moved away from; start loading what it came near.
  update(eye) {
    const [order, want] = this.wanted(eye);
    for (const t of order.slice().reverse()) {
      if (t.model && !want.has(t)) this.release(t);
    }
    let loading = this.tiles.filter((t) => t.loading).length;
    for (const t of order) {
      if (loading >= MAX_LOADS) break;
      if (!want.has(t) || t.model || t.loading) continue;
      if (this.residentBytes + this.loadingBytes() + t.gpu_bytes > this.budget && this.residentBytes > 0) break;
      t.loading = true;
      ++loading;
      WebModel.load(this.gl, t.dir, this.programs).then((model) => {
        t.loading = false;
        t.model = model;
        this.residentBytes += model.gpuBytes;
        this.peakBytes = Math.max(this.peakBytes, this.residentBytes);
        ++this.loads;
        if (this.residentBytes > this.budget && this.tiles.filter((u) => u.model).length > 1) this.release(t);
      }).catch((e) => { t.loading = false; this.onError(`${t.dir}: ${e.message}`); });
    }
  }

  loadingBytes() {
    return this.tiles.reduce((s, t) => s + (t.loading ? t.gpu_bytes : 0), 0);
  }

  release(t) {
    t.model.release();
    this.residentBytes -= t.model.gpuBytes;
    t.model = null;
    ++this.releases;
  }

  get resident() { return this.tiles.filter((t) => t.model).length; }

  // Tiles wanted for `eye` that are not resident yet.
  pending(eye) {
    const [, want] = this.wanted(eye);
    return [...want].filter((t) => !t.model).length;
  }

  // Plan every resident tile's draw from `cam` (decoding and pre-blending what it needs,
  // WebModel.prepare), nearest first; returns summed stats.
  prepare(cam, proj, options) {
    const total = {quads: 0, instances: 0, decoded: 0, blended: 0, nodes: 0, tiles: 0};
    this.drawn = [...this.tiles].sort((a, b) => a.distance - b.distance).filter((t) => t.model);
    for (const t of this.drawn) {
      const s = t.model.prepare(cam, proj, options);
      for (const k of ['quads', 'instances', 'decoded', 'blended', 'nodes']) total[k] += s[k];
      total.tiles += 1;
    }
    return total;
  }

  // Draw what prepare() planned into the bound framebuffer.
  emit(proj, options) {
    for (const t of this.drawn || []) if (t.model) t.model.emit(proj, options);
    this.drawn = null;
  }
}
