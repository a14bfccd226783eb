"""Ground-truth view-dependent billboard textures, and texture error against them.

The truth for billboard ``b`` seen from direction (ψ, φ) at distance ``D``:

* the voxel is the axis-aligned cube [c − s/2, c + s/2] around the centre ``c``;
* the quad frame (normal, right, up) is :func:`geometry.quad_frames` (ψ, φ) and
  its texel centres are :func:`geometry.texel_points`;
* the viewer is ``e = c + D·unit_vectors(ψ, φ)`` (the true viewing direction,
  also when quads are not pitched);
* each texel is supersampled by ``spp × spp`` points spread uniformly over the
  texel on the quad (sub-offsets ``(k + ½)/spp − ½`` texels, as the renderer
  stratifies pixels); each point ``p`` gives a ray from ``e`` along ``p − e``;
* the ray is cut to the voxel's slab: it is cast from its entry into the cube,
  ``max(t_in, 0)`` (:func:`geometry.ray_box_interval`), and its first hit counts
  only if it lies before ``t_out``. Geometry in front of the voxel (a pillar
  between the viewer and a wall) is therefore ignored, and whatever lies behind
  the voxel never shows. The slab is half-open, [t_in, t_out), made robust by
  :data:`SLAB_EPS`: a surface lying exactly on a face that two voxels share (an
  axis-aligned synthetic facade on a grid plane) belongs to the voxel behind the
  face as seen from the viewer, never to both or to a float32 coin toss;
* alpha = share of the sub-rays that hit inside the slab; RGB = mean shaded
  colour of those hits (the sky never enters; fully transparent texels are 0).

RGB is *straight* (not premultiplied by alpha).
"""

from __future__ import annotations

import numpy as np

from data_synth import raycast
from data_synth.raycast import Renderer
from data_synth.scene import Scene

from core.errors import InputError

from .geometry import quad_frames, ray_box_interval, texel_offsets, unit_vectors


#: Metres. Rays start SLAB_EPS before the voxel's entry face and hits must lie SLAB_EPS before
#: its exit face, so surfaces on the faces are assigned deterministically despite float32 casting.
SLAB_EPS = 1e-3


def _sub_offsets(spp: int) -> np.ndarray:
    """(spp,) float64 sub-sample offsets within a texel, in texels, from −½ to ½ exclusive."""
    return (np.arange(spp, dtype=np.float64) + 0.5) / spp - 0.5


def truth_textures(scene: Scene, centres: np.ndarray, size: float, yaw: np.ndarray, pitch: np.ndarray,
                   distance: np.ndarray, tile: int, pitched: bool = False, spp: int = 2,
                   renderer: Renderer | None = None, box_centres: np.ndarray | None = None) -> np.ndarray:
    """Ground-truth textures of billboards, each seen from one direction (see the module docstring).

    scene: the ground-truth scene; centres (m, 3) float64 quad centres, world
    (box_centres: the voxel cubes' centres when the quads sit off them; default the same);
    size: voxel (and quad) edge, metres; yaw, pitch (m,) float64 radians of the
    direction toward the viewer; distance (m,) float64 viewer distance from the
    centre, metres (> 0); tile: texture edge t in texels; pitched: quads tilt
    with the pitch (:func:`geometry.quad_frames`); spp: sub-rays per texel axis;
    renderer: a :class:`Renderer` of ``scene`` to reuse (built if None).

    Returns (m, t, t, 4) float32 RGBA in [0, 1], [:, row, col], row 0 at the top.
    Memory is bounded by MAX_RAYS_PER_CHUNK rays per chunk of samples.
    """
    centres = np.asarray(centres, dtype=np.float64)
    boxes = centres if box_centres is None else np.asarray(box_centres, dtype=np.float64)
    if boxes.shape != centres.shape:
        raise InputError(f"box_centres must be shaped like centres {centres.shape}, got {boxes.shape}")
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise InputError(f"centres must be (m, 3), got {centres.shape}")
    m = len(centres)
    try:
        yaw, pitch, distance = (np.broadcast_to(np.asarray(a, dtype=np.float64), (m,))
                                for a in (yaw, pitch, distance))
    except ValueError as exc:
        raise InputError(f"yaw, pitch and distance must be ({m},) like centres") from exc
    size = float(size)
    tile, spp = int(tile), int(spp)
    if not (np.isfinite(size) and size > 0) or tile < 1 or spp < 1:
        raise InputError(f"need size > 0, tile ≥ 1 and spp ≥ 1, got {size}, {tile}, {spp}")
    if not all(np.all(np.isfinite(a)) for a in (centres, yaw, pitch, distance)):
        raise InputError("centres, yaw, pitch and distance must be finite")
    if np.any(distance <= 0):
        raise InputError("distance must be positive")
    if renderer is None:
        renderer = Renderer(scene)
    elif renderer.scene is not scene:
        raise InputError("renderer was built for a different scene")

    out = np.zeros((m, tile, tile, 4), dtype=np.float32)
    if m == 0:
        return out
    texel = texel_offsets(tile) * size                    # (t,) along right (cols) and −up (rows)
    sub = _sub_offsets(spp) * (size / tile)               # (spp,)
    # Offset of every sub-ray point along right (cols) and −up (rows), metres: index texel·spp + sub.
    a = (texel[:, None] + sub[None, :]).ravel()           # (t·spp,)
    rays_per_sample = (tile * spp) ** 2
    chunk = max(1, raycast.MAX_RAYS_PER_CHUNK // rays_per_sample)
    half = 0.5 * size
    for s0 in range(0, m, chunk):
        s1 = min(m, s0 + chunk)
        c = centres[s0:s1]                                                  # (k, 3)
        b = boxes[s0:s1]
        _, right, up = quad_frames(yaw[s0:s1], pitch[s0:s1], pitched)       # (k, 3)
        eye = c + distance[s0:s1, None] * unit_vectors(yaw[s0:s1], pitch[s0:s1])
        # Sub-ray points (k, t·spp, t·spp, 3), index [sample, row·spp + dv, col·spp + du].
        p = (c[:, None, None, :]
             + a[None, None, :, None] * right[:, None, None, :]
             - a[None, :, None, None] * up[:, None, None, :])
        d = p - eye[:, None, None, :]
        t_in, t_out = ray_box_interval(eye[:, None, None, :], d,
                                       (b - half)[:, None, None, :], (b + half)[:, None, None, :])
        with np.errstate(divide="ignore"):  # d = 0 only if the viewer sits on the quad: no ray
            eps = SLAB_EPS / np.linalg.norm(d, axis=-1)                     # SLAB_EPS in units of t
        t0 = np.maximum(t_in - eps, 0.0)
        t1 = t_out - eps
        inside = t0 < t1                                                    # the ray meets the cube ahead
        hit = np.zeros(inside.shape, dtype=bool)
        colour = np.zeros(inside.shape + (3,))
        if inside.any():
            d_in = d[inside]
            origins = np.broadcast_to(eye[:, None, None, :], d.shape)[inside] + t0[inside, None] * d_in
            t, _, col = renderer.cast(origins, d_in, t_max=t1[inside] - t0[inside])
            ok = np.isfinite(t)
            hit[inside] = ok
            colour[inside] = np.where(ok[:, None], col, 0.0)
        k = s1 - s0
        hit = hit.reshape(k, tile, spp, tile, spp)
        colour = colour.reshape(k, tile, spp, tile, spp, 3)
        count = hit.sum(axis=(2, 4))                                        # (k, t, t)
        rgb = colour.sum(axis=(2, 4)) / np.maximum(count, 1)[..., None]
        out[s0:s1, ..., :3] = np.clip(rgb, 0.0, 1.0)
        out[s0:s1, ..., 3] = count / float(spp * spp)
    return out


def texture_psnr(estimate: np.ndarray, truth: np.ndarray, min_alpha: float = 0.5) -> dict:
    """Texture error of estimated billboard textures against the truth.

    estimate, truth: (m, t, t, 4) float RGBA in [0, 1], straight (not premultiplied) RGB.
    Returns a dict:
      psnr_rgb: PSNR (dB, peak 1) of RGB over the texels whose truth alpha ≥ min_alpha;
                NaN if there are none, inf if they agree exactly;
      alpha_agreement: share of all texels where (estimate alpha ≥ ½) == (truth alpha ≥ ½);
      texels: how many texels the PSNR covers.
    """
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if estimate.shape != truth.shape or truth.ndim != 4 or truth.shape[-1] != 4:
        raise InputError(f"estimate and truth must both be (m, t, t, 4), got {estimate.shape}, {truth.shape}")
    mask = truth[..., 3] >= min_alpha
    n = int(mask.sum())
    if n == 0:
        psnr = float("nan")
    else:
        mse = float(np.mean((estimate[mask, :3] - truth[mask, :3]) ** 2))
        psnr = float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))
    agree = (estimate[..., 3] >= 0.5) == (truth[..., 3] >= 0.5)
    return {"psnr_rgb": psnr, "alpha_agreement": float(agree.mean()) if agree.size else float("nan"),
            "texels": n}
