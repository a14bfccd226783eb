// The viewer's camera: OpenCV cameras (K, world_from_cam) as GL matrices, as render/camera.py
// builds them, and the link's view x,y,z,yaw,pitch[,fov] as share/web_camera.py reads it.
// Matrices here are row-major arrays of 16 numbers (float64); glMat() gives the column-major
// Float32Array a GLSL mat4 uniform takes.

export const DEFAULT_FOV_DEG = 60.0;
const RAD = Math.PI / 180;

// world_from_cam rotation (row-major 9) of a camera looking along heading yaw° and elevation pitch°.
export function viewRotation(yawDeg, pitchDeg) {
  const a = yawDeg * RAD, b = pitchDeg * RAD;
  const f = [Math.cos(b) * Math.cos(a), Math.cos(b) * Math.sin(a), Math.sin(b)];
  const r = [Math.sin(a), -Math.cos(a), 0.0];
  const d = [f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]];  // f × r
  return [r[0], d[0], f[0], r[1], d[1], f[1], r[2], d[2], f[2]];  // columns: right, down, forward
}

// The OpenCV camera of a view [x, y, z, yaw, pitch, fov] for a w×h image: {K: [fx, fy, cx, cy], R, eye}.
export function viewCamera(view, w, h) {
  const fov = view.length > 5 ? view[5] : DEFAULT_FOV_DEG;
  const f = 0.5 * h / Math.tan(fov * RAD / 2);
  return {K: [f, f, (w - 1) / 2, (h - 1) / 2], R: viewRotation(view[3], view[4]), eye: [view[0], view[1], view[2]]};
}

// A path pose (rotation row by row, then the eye) as a camera with the intrinsics of a view's fov.
export function poseCamera(row, fov, w, h) {
  const cam = viewCamera([0, 0, 0, 0, 0, fov], w, h);
  return {K: cam.K, R: row.slice(0, 9), eye: row.slice(9, 12)};
}

// The view [x, y, z, yaw, pitch] of a camera (its roll dropped).
export function cameraView(cam) {
  const f = [cam.R[2], cam.R[5], cam.R[8]];
  return [cam.eye[0], cam.eye[1], cam.eye[2], Math.atan2(f[1], f[0]) / RAD,
          Math.atan2(f[2], Math.hypot(f[0], f[1])) / RAD];
}

// GL projection reproducing the pinhole K for a w×h image (render.camera.projection_from_K).
export function projection(K, w, h, near = 0.1, far = 2000.0) {
  const [fx, fy, cx, cy] = K;
  return [2 * fx / w, 0, 1 - 2 * (cx + 0.5) / w, 0,
          0, 2 * fy / h, 2 * (cy + 0.5) / h - 1, 0,
          0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
          0, 0, -1, 0];
}

// GL view matrix: GL eye from model coordinates, eye = camera centre − model origin (render.camera._view).
export function viewMatrix(R, eye) {
  // cam_from_model = [Rᵀ | −Rᵀ·eye]; GL_FROM_CV = diag(1, −1, −1, 1)
  const m = new Array(16).fill(0);
  for (let i = 0; i < 3; ++i) {
    const s = i === 0 ? 1 : -1;
    for (let j = 0; j < 3; ++j) m[i * 4 + j] = s * R[j * 3 + i];
    m[i * 4 + 3] = -s * (R[i] * eye[0] + R[3 + i] * eye[1] + R[6 + i] * eye[2]);
  }
  m[15] = 1;
  return m;
}

export function multiply(a, b) {
  const m = new Array(16).fill(0);
  for (let i = 0; i < 4; ++i)
    for (let j = 0; j < 4; ++j)
      for (let k = 0; k < 4; ++k) m[i * 4 + j] += a[i * 4 + k] * b[k * 4 + j];
  return m;
}

// Row-major (float32-rounded, as the desktop's float32 matrices are) → column-major Float32Array.
export function glMat(m) {
  const n = Math.round(Math.sqrt(m.length));
  const out = new Float32Array(m.length);
  for (let i = 0; i < n; ++i) for (let j = 0; j < n; ++j) out[j * n + i] = m[i * n + j];
  return out;
}

// Row-major matrix with every entry rounded to float32 (the desktop multiplies float32 matrices).
export function fround(m) {
  return m.map(Math.fround);
}

// world_from_pixel = R·K⁻¹ (row-major 3×3) for the sky pass.
export function worldFromPixel(cam) {
  const [fx, fy, cx, cy] = cam.K;
  const kinv = [1 / fx, 0, -cx / fx, 0, 1 / fy, -cy / fy, 0, 0, 1];
  const out = new Array(9).fill(0);
  for (let i = 0; i < 3; ++i)
    for (let j = 0; j < 3; ++j)
      for (let k = 0; k < 3; ++k) out[i * 3 + j] += cam.R[i * 3 + k] * kinv[k * 3 + j];
  return out;
}
