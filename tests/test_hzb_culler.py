"""The HZB culler on the box scene of the occlusion tests: the unculled image, hidden boxes culled."""

from __future__ import annotations

import numpy as np
import pytest

from render.hzb_culler import HzbConfig, HzbCuller

from .boxes import BoxRenderer
from .test_render_culling import (H, W, auto_trials, gl, reference_image, render_frame, seen_ids,  # noqa: F401
                                  street_scene, view_proj)


@pytest.mark.parametrize("config", [{}, dict(temporal=False), dict(span=1, cut_reads=1), dict(span=2)])
@pytest.mark.parametrize("grouped", [False, True])
def test_hzb_culling_matches_the_unculled_image(gl, config, grouped):  # noqa: F811
    ctx, fbo = gl
    lo, hi, g = street_scene()
    n = len(lo)
    groups = np.arange(n) // 10 if grouped else None
    with BoxRenderer(ctx, lo, hi) as boxes, HzbCuller(ctx, W, H, mode="hzb", config=HzbConfig(**config)) as culler:
        original = culler.cull
        culler.cull = lambda *a, **k: original(*a, **k, groups=groups)
        for f in range(6):  # walking sideways and turning: later frames start from earlier ones
            eye = np.array([0.8 * f, 0.3 * f, 0.2 * f])
            vp = view_proj(eye, eye + [0.05 * f, 10, 0], aspect=W / H, near=0.1, far=200)
            ref = reference_image(ctx, fbo, boxes, vp)
            image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
            np.testing.assert_array_equal(image, ref)
            seen = seen_ids(ref, n)
            assert not (seen & ~culler.visible).any(), f"frame {f}: a visible box was culled"
            assert stats.queries == 0 and stats.depth_reads >= 1 and stats.objects_drawn == culler.visible.sum()
            if f == 0:
                assert culler.visible[g["wall"]].all() and culler.visible[g["peek"]].all()
                assert culler.visible[g["hidden"]].mean() < 0.3, "boxes behind the wall were drawn"
            if f > 0 and config.get("temporal", True):
                assert stats.objects_temporal > 0 and stats.depth_reads == 1
        if grouped:
            assert stats.culled_by_parent > 0


def test_hzb_camera_inside_a_box_empty_scene_and_modes(gl):  # noqa: F811
    ctx, fbo = gl
    lo, hi, _ = street_scene()
    lo = np.concatenate([lo, [[-0.5, -0.5, -0.5]]])  # a box around the eye: never culled, hides the rest
    hi = np.concatenate([hi, [[0.5, 3.0, 0.5]]])
    n = len(lo)
    vp = view_proj((0, 0, 0), (0, 10, 0), aspect=W / H, near=0.1, far=200)
    with BoxRenderer(ctx, lo, hi) as boxes, HzbCuller(ctx, W, H, mode="hzb") as culler:
        for _ in range(2):
            image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
            np.testing.assert_array_equal(image, reference_image(ctx, fbo, boxes, vp))
            assert culler.visible[n - 1] and stats.objects_drawn < n // 2
        empty = np.zeros((0, 3))
        image, stats = render_frame(ctx, fbo, boxes, culler, vp, empty, empty)
        assert (image == 0).all() and stats.objects == 0 and stats.draw_calls == 0 and stats.depth_reads == 0
        culler.mode = "frustum"  # everything drawn, no read-back
        image, stats = render_frame(ctx, fbo, boxes, culler, vp, lo, hi)
        assert stats.objects_drawn == n and stats.depth_reads == 0 and not stats.active
        with pytest.raises(ValueError):
            culler.mode = "occlusion"  # hardware queries are OcclusionCuller's
        with pytest.raises(ValueError, match="groups"):
            culler.cull(vp, lo, hi, np.stack([np.arange(n), np.arange(1, n + 1)], 1), lambda r: None,
                        groups=np.arange(n)[::-1])
    culler.release()
    culler.release()
    with pytest.raises(ValueError):
        HzbConfig(span=0)
    with pytest.raises(ValueError):
        HzbConfig(cut_reads=0)


def test_hzb_auto_switches_off_when_nothing_is_hidden(gl):  # noqa: F811
    ctx, fbo = gl
    cfg = HzbConfig(auto_window=3, auto_backoff=4, auto_backoff_max=8)
    active, culler = auto_trials(ctx, fbo, lambda c, w, h: HzbCuller(c, w, h, mode="auto", config=cfg), 12)
    assert active == [True] * 2 + [False] * 4 + [True] * 2 + [False] * 4  # a losing trial: 2 frames
    assert culler.last_decision["pays"] is False
