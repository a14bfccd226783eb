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

// 0: outside, 1: partial, 2: inside — box [lo, hi] grown by pad against the planes.
export function classifyBox(planes, lo, hi, pad) {
  let inside = true;
  for (const [a, b, c, d] of planes) {
    const far = a * (a > 0 ? hi[0] : lo[0]) + b * (b > 0 ? hi[1] : lo[1]) + c * (c > 0 ? hi[2] : lo[2]) + d;
    if (far < -pad) return 0;
    const near = a * (a > 0 ? lo[0] : hi[0]) + b * (b > 0 ? lo[1] : hi[1]) + c * (c > 0 ? lo[2] : hi[2]) + d;
    if (near < pad) inside = false;
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
