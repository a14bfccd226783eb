// Frustum culling over a model's octree (render/culling.py): the six planes of a view-projection
// (Gribb–Hartmann), nodes tested from the root, a node inside every plane taken whole, one
// outside any plane dropped with its subtree, a partial leaf kept whole. Boxes are padded by how
// far a quad reaches beyond its leaf, so the result is conservative.

// Planes (6 × [a, b, c, d], unit inward normals) of a row-major view-projection matrix.
export function frustumPlanes(m) {
  const row = (i) => [m[i * 4], m[i * 4 + 1], m[i * 4 + 2], m[i * 4 + 3]];
  const r0 = row(0), r1 = row(1), r2 = row(2), r3 = row(3);
  const planes = [];
  for (const [s, r] of [[1, r0], [-1, r0], [1, r1], [-1, r1], [1, r2], [-1, r2]]) {
    const p = r3.map((v, k) => v + s * r[k]);
    const n = Math.hypot(p[0], p[1], p[2]);
    planes.push(p.map((v) => v / n));
  }
  return planes;
}

const PLANE_REL_EPS = 1e-5;  // render/culling.py: float32 clip coordinates on the GPU are this coarse

// 0: outside, 1: partial (or unsure), 2: inside — box [lo − pad, hi + pad] against the planes by its
// centre's distance ± its half-extent along each normal, within render/culling.py's tolerance.
export function classifyBox(planes, lo, hi, pad) {
  let inside = true;
  for (const [a, b, c, d] of planes) {
    const cx = 0.5 * (lo[0] + hi[0]), cy = 0.5 * (lo[1] + hi[1]), cz = 0.5 * (lo[2] + hi[2]);
    const ext = Math.abs(a) * (0.5 * (hi[0] - lo[0]) + pad) + Math.abs(b) * (0.5 * (hi[1] - lo[1]) + pad)
              + Math.abs(c) * (0.5 * (hi[2] - lo[2]) + pad);
    const dist = a * cx + b * cy + c * cz + d;
    const tol = PLANE_REL_EPS * (Math.abs(a * cx) + Math.abs(b * cy) + Math.abs(c * cz) + Math.abs(d) + ext);
    if (dist + ext < -tol) return 0;
    if (dist - ext <= tol) inside = false;
  }
  return inside ? 2 : 1;
}

// Billboard ranges [begin, end) (model order) of the nodes in the frustum; `visit(begin, end)`
// is called once per range. bounds: Float32Array (k·6: min xyz, max xyz), children: Int32Array
// (k·8, −1 none), range: Int32Array (k·2). Returns nodes tested.
export function cullNodes(planes, bounds, children, range, pad, visit) {
  if (bounds.length === 0) return 0;
  const stack = [0];
  const lo = [0, 0, 0], hi = [0, 0, 0];
  let tested = 0;
  while (stack.length) {
    const node = stack.pop();
    for (let k = 0; k < 3; ++k) { lo[k] = bounds[node * 6 + k]; hi[k] = bounds[node * 6 + 3 + k]; }
    ++tested;
    const c = classifyBox(planes, lo, hi, pad);
    if (c === 0) continue;
    let leaf = true;
    if (c === 1) {
      for (let j = 0; j < 8; ++j) {
        const child = children[node * 8 + j];
        if (child >= 0) { stack.push(child); leaf = false; }
      }
    }
    if (c === 2 || leaf) visit(range[node * 2], range[node * 2 + 1]);
  }
  return tested;
}
