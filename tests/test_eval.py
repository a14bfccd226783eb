"""`bbcity eval`: the seen-pixel mask, the Poisson-mesh baseline, the methods dict, the report."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from billboards.geometry import KINDS
from render.camera import look_at
from render.eval_methods import SYNTHESISED
from render.seen import back_project, seen_mask

from .conftest import tiny_config, write_ground_truth_cloud
from .test_build import small_config

W, H = 64, 48
K = np.array([[50.0, 0.0, (W - 1) / 2], [0.0, 50.0, (H - 1) / 2], [0.0, 0.0, 1.0]])


def plane_depth(K, pose, size, point, normal) -> np.ndarray:
    """(h, w) float32 z-depth of the plane through ``point`` with ``normal`` (NaN where missed)."""
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # camera frame, z = 1
    d = rays @ pose[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(point) - pose[:3, 3]) @ normal) / (d @ normal)
    return np.where(t > 0, t, np.nan).astype(np.float32)


def test_seen_mask_hidden_visible_and_nan_points():
    # two cameras at y = 0 looking along +y at a wall y = 5 that fills their images
    cams = [look_at(np.array([x, 0.0, 1.5]), np.array([x, 10.0, 1.5])) for x in (-1.0, 1.0)]
    depths = [plane_depth(K, c, (W, H), [0, 5.0, 0], np.array([0, 1.0, 0])) for c in cams]
    points = np.array([
        [0.0, 5.0, 1.5],       # on the wall, in both images: seen
        [0.3, 5.0, 2.0],       # on the wall: seen
        [0.0, 8.0, 1.5],       # behind the wall from every camera: unseen
        [np.nan, 5.0, 1.5],    # no surface (sky): unseen
        [0.0, 5.0, 40.0],      # on the wall's plane but outside both images: unseen
        [0.0, -3.0, 1.5],      # behind the cameras: unseen
    ])
    seen = seen_mask(points, np.stack([K, K]), np.stack(cams), depths)
    assert seen.tolist() == [True, True, False, False, False, False]
    # a camera that sees behind the wall (beside it, at y = 6) sees the hidden point
    side = look_at(np.array([0.0, 6.0, 1.5]), np.array([0.0, 10.0, 1.5]))
    side_depth = plane_depth(K, side, (W, H), [0, 8.0, 0], np.array([0, 1.0, 0]))
    seen = seen_mask(points, np.stack([K, K, K]), np.stack([*cams, side]), [*depths, side_depth])
    assert seen.tolist() == [True, True, True, False, False, False]
    # NaN depth in the camera (it saw nothing there) means unseen
    assert not seen_mask(points[:1], K[None], cams[0][None], [np.full((H, W), np.nan, np.float32)])[0]
    with pytest.raises(ValueError):
        seen_mask(points, np.stack([K, K]), np.stack(cams), depths[:1])


def test_seen_mask_at_a_grazing_angle():
    """The road seen from 2 m up changes depth by far more than the tolerance between
    neighbouring pixels; the bilinear inverse depth still matches every point on it."""
    cam = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 20.0, 1.0]))
    depth = plane_depth(K, cam, (W, H), [0, 0, 0.0], np.array([0, 0, 1.0]))
    rng = np.random.default_rng(0)
    ground = np.stack([rng.uniform(-4, 4, 2000), rng.uniform(6, 30, 2000), np.zeros(2000)], 1)
    seen = seen_mask(ground, K[None], cam[None], [depth])
    cam_pts = (ground - cam[:3, 3]) @ cam[:3, :3]
    u = K[0, 0] * cam_pts[:, 0] / cam_pts[:, 2] + K[0, 2]
    v = K[1, 1] * cam_pts[:, 1] / cam_pts[:, 2] + K[1, 2]
    inside = (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
    assert inside.sum() > 500 and np.array_equal(seen, inside)
    near = ground[:, 1] < 15  # (farther, 0.5 m above the road lies within a pixel of the road at that depth)
    assert not seen_mask(ground[near] + [0, 0, 0.5], K[None], cam[None], [depth]).any()


def test_back_project_round_trips():
    cam = look_at(np.array([1e6, 2e6, 2.0]), np.array([1e6 + 3, 2e6 + 10, 1.0]))
    depth = plane_depth(K, cam, (W, H), [0, 2e6 + 12, 0.0], np.array([0, 1.0, 0]))
    pts = back_project(depth, K, cam)
    finite = np.isfinite(depth).reshape(-1)
    np.testing.assert_allclose(pts[finite, 1], 2e6 + 12, atol=1e-3)
    assert np.all(np.isnan(pts[~finite]))


def test_poisson_mesh_of_a_wall_shows_its_colours():
    from render.baselines import PoissonMesh

    rng = np.random.default_rng(0)
    n = 20000
    wall_y = 10.0 + rng.normal(0, 0.002, n)  # (a plane of zero thickness makes Poisson's isosurface speckle)
    pts = np.stack([rng.uniform(-5, 5, n), wall_y, rng.uniform(0, 5, n)], 1) + [1e6, 2e6, 0]
    colours = np.stack([(pts[:, 0] - 1e6 + 5) / 10 * 255, np.full(n, 100), pts[:, 2] / 5 * 255], 1).astype(np.uint8)
    mesh = PoissonMesh(pts, colours, None, depth=7, viewpoints=np.array([[1e6, 2e6, 2.0]]))
    V, T = len(mesh.vertices), len(mesh.triangles)
    assert V > 100 and T > 100 and mesh.nbytes == V * 15 + T * 12
    Kc = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    pose = look_at(np.array([1e6, 2e6, 2.5]), np.array([1e6, 2e6 + 10, 2.5]))
    image = mesh.render(Kc, pose, (160, 120)).astype(int)
    u, v = np.meshgrid(np.arange(160), np.arange(120))
    x, z = (u - 79.5) / 100 * 10, 2.5 - (v - 59.5) / 100 * 10
    inner = (np.abs(x) < 4.5) & (z > 0.5) & (z < 4.5)
    expected_r, expected_b = (x + 5) / 10 * 255, z / 5 * 255
    assert np.abs(image[..., 0] - expected_r)[inner].mean() < 4 and np.abs(image[..., 2] - expected_b)[inner].mean() < 4
    assert np.all(image[(np.abs(x) > 6)] == 0)  # beyond the wall's ends: trimmed away, black


def test_work_precision_plot_and_markdown(tmp_path):
    from render.eval_report import markdown, work_precision_plot
    from render.eval_scores import work_precision_points

    summary = {f"{m}, {w}": {"psnr": 20.0, "psnr_geometry": 21.0, "psnr_seen": p + (w == "off path") * -2,
                             "ssim": 0.5, "ssim_geometry": 0.5, "ssim_seen": 0.6, "seen_fraction": 0.8}
               for m, p in (("model", 25.0), ("Poisson mesh", 22.0), ("Poisson depth 8", 20.0),
                            ("point projection", 18.0)) for w in ("on path", "off path")}
    summary["point projection, off path"]["psnr_seen"] = float("nan")
    info = {"model": {"bytes": 10_000_000}, "Poisson mesh": {"bytes": 30_000_000, "build_s": 3.0},
            "Poisson depth 8": {"bytes": 2_000_000, "build_s": 1.0}, "point projection": {"bytes": 50_000_000}}
    points = work_precision_points(summary, info, 10)
    assert {p["label"] for p in points if p["family"] == "Poisson mesh"} == {"depth 10", "depth 8"}
    report = {"views": 2, "held_out": True, "size": [64, 48], "summary": summary,
              "bytes": {k: v["bytes"] for k, v in info.items()}, "methods": info, "work_precision": points}
    out = work_precision_plot(report, tmp_path / "wp.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = markdown(report)
    assert "Poisson depth 8" in text and "n/a" in text and "Work-precision" in text


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """The tiny street with frames 5 m apart (neighbouring frames overlap), its ground-truth
    cloud (as recon writes it, without normals) and a model built with every 3rd frame held out."""
    from billboards.build import main as build_main
    from data_synth import write_dataset

    root = tmp_path_factory.mktemp("dense")
    dataset = write_dataset(tiny_config(frames=7), root / "street", progress=False)
    cloud = write_ground_truth_cloud(dataset, root / "cloud.ply")
    model = build_main(small_config(holdout=3), cloud, dataset, root / "model").model
    return dataset, cloud, model


def test_seen_pixels_of_held_out_views(street):
    from capture import load_dataset
    from data_synth import load_scene, truth_view
    from render.eval_views import off_path
    from render.seen import SeenConfig, seen_in_dataset

    dataset, _, _ = street
    ds, scene = load_dataset(dataset), load_scene(dataset)
    K, size = ds.rig.intrinsics[0], tuple(ds.rig.sizes[0])
    pose = ds.world_from_cam(4, 0)
    _, depth = truth_view(scene, K, pose, size)
    own = seen_in_dataset(depth, K, pose, ds, [4])
    assert np.array_equal(own, np.isfinite(depth))  # a capture camera sees all it shows (NaN sky: unseen)
    neighbours = seen_in_dataset(depth, K, pose, ds, [3, 5])
    assert 0.3 < neighbours.mean() < np.isfinite(depth).mean()
    assert not seen_in_dataset(depth, K, pose, ds, [3, 5], SeenConfig(max_distance=1.0)).any()  # none near
    moved = off_path(pose)
    _, depth_off = truth_view(scene, K, moved, size)
    assert seen_in_dataset(depth_off, K, moved, ds, [3, 4, 5]).mean() < np.isfinite(depth_off).mean()


@pytest.mark.parametrize("points", [np.ones((50, 3)), np.ones((1, 3)), np.zeros((0, 3))],
                         ids=["one point repeated", "one point", "empty"])
def test_poisson_mesh_refuses_a_cloud_that_spans_no_space(points):
    """Open3D's Poisson crashes the process (SIGSEGV) on one point repeated: refused first."""
    from core.errors import InputError
    from render.baselines import PoissonMesh

    with pytest.raises(InputError, match=r"points spread in space: the cloud's \d+ points span 0 m"):
        PoissonMesh(points, np.full((len(points), 3), 128, np.uint8), depth=7)


def test_eval_refuses_a_cloud_of_one_point_repeated_naming_it(street, tmp_path, caplog):
    from bbcity.cli import main as cli_main
    from recon.cloud_io import PlyStreamWriter

    tiny_dataset, _, model = street
    cloud = tmp_path / "same.ply"
    with PlyStreamWriter(cloud, normals=False) as writer:
        writer.append(np.full((50, 3), 3.0), np.full((50, 3), 128, np.uint8))
    assert cli_main(["-q", "eval", str(model), str(tiny_dataset), "--cloud", str(cloud), "--views", "1",
                     "--training-views", "0", "--out", str(tmp_path / "eval")]) == 2
    assert f"{cloud}: its 50 points span no space" in caplog.text


@pytest.mark.slow
def test_eval_cli_on_the_tiny_street(street, tmp_path):
    from bbcity.cli import main as cli_main
    from billboards import model_reader as billboard_model
    from billboards.sky import Sky, write_sky
    from core.fileio import read_png

    tiny_dataset, tiny_cloud, model = street
    held_out = billboard_model.load(model).info["held_out_frames"]
    assert held_out == [1, 4, 7, 10, 13]  # 14 frames, every 3rd from the middle of each triple
    write_sky(model, Sky(np.full((16, 3), 0.8, np.float32)))
    out = tmp_path / "eval"
    assert cli_main(["-q", "eval", str(model), str(tiny_dataset), "--cloud", str(tiny_cloud), "--views", "2",
                     "--out", str(out), "--poisson-depth", "7", "--workprecision-depths", "6", "7",
                     "--models", str(model), "--billboards-only", str(model), "--panel-width", "120",
                     "--training-views", "1"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["held_out"] and report["frames"] == [1, 13] and report["sky"]
    methods = ("model", "model: model", "billboards only", "Poisson mesh", "Poisson depth 6", "point projection")
    assert set(report["summary"]) == {f"{m}, {v}" for m in methods for v in ("on path", "off path", "training")}
    assert len(report["training_frames"]) == 1 and report["training_frames"][0] not in held_out
    for name, m in report["summary"].items():
        assert 5 < m["psnr"] < 100 and -1 <= m["ssim"] <= 1, name
        assert 5 < m["psnr_seen"] < 100 and 0 < m["seen_fraction"] <= 1, name  # (a training view sees all)
        assert 0 <= m["coverage_seen"] <= 1, name
    on = report["summary"]["model, on path"]
    assert on["seen_fraction"] > 0.3 and on["psnr_seen"] > on["psnr_geometry"] - 3
    assert on["coverage_seen"] > 0.5   # the model draws most of what the capture saw
    assert report["summary"]["model: model, on path"]["psnr_seen"] == pytest.approx(on["psnr_seen"])
    for name in methods:
        assert report["bytes"][name] > 0
    assert report["bytes"]["Poisson depth 6"] < report["bytes"]["Poisson mesh"]
    assert {"model", "Poisson mesh", "point projection"} <= {p["family"] for p in report["work_precision"]}
    assert (out / "workprecision.png").is_file() and "off path" in (out / "eval.md").read_text()
    split = [report["summary"]["model, on path"][f"psnr_seen_{k}"] for k in ("facade", "ground", "billboard", "plane")]
    assert any(v is not None for v in split) and all(v is None or 5 < v <= 100 for v in split)
    assert report["summary"]["Poisson mesh, on path"]["psnr_seen_facade"] is None   # (a model's quads only)
    assert "kind of quad" in (out / "eval.md").read_text()
    # synthesised ground (none in this model) is scored apart: no pixel, no score (its mark is no kind)
    assert on["synthesised_fraction"] == 0 and on["psnr_geometry_synthesised"] is None
    assert SYNTHESISED not in KINDS
    # the near field: seen pixels nearer than 5 m, for every method
    assert report["config"]["near"] == 5.0 and "The near field" in (out / "eval.md").read_text()
    assert all(m["psnr_seen_near"] is None or 5 < m["psnr_seen_near"] <= 100 for m in report["summary"].values())
    assert any(m["psnr_seen_near"] is not None for m in report["summary"].values())
    assert len(report["images"]) == 5 and report["images"][-1].endswith("_training.png")
    panel = read_png(out / report["images"][0])
    assert panel.shape == (90, 480, 3)  # ground truth | model | model: model | Poisson mesh, 120×90 each
    plain = tmp_path / "plain"
    assert cli_main(["-q", "eval", str(model), str(tiny_dataset), "--views", "1", "--out", str(plain), "--no-sky",
                     "--panel-width", "0"]) == 0
    report = json.loads((plain / "eval.json").read_text())
    assert not report["sky"] and set(report["summary"]) >= {"model, on path", "model, off path"}
    assert "images" not in report and not list(plain.glob("view_*.png"))


def test_poisson_meshed_in_the_background_is_drawn_and_its_error_raised_by_the_call():
    from bbcity.executor import process_scope
    from core.errors import InputError
    from render.baselines import poisson_arrays
    from render.eval_methods import LazyPoisson

    rng = np.random.default_rng(0)
    xy = rng.uniform(-2, 2, (20_000, 2))
    cloud = {"points": np.c_[xy, np.full(len(xy), 5.0)], "colours": np.full((len(xy), 3), 200, np.uint8),
             "normals": np.tile([0.0, 0.0, -1.0], (len(xy), 1)), "viewpoints": None}
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    def meshed(pool, depth):
        return pool.submit(poisson_arrays, cloud["points"], cloud["colours"], cloud["normals"], depth=depth)

    with process_scope(1) as pool:
        started = LazyPoisson(cloud, 6, 0.05, meshed(pool, 6))
        image = started(K, np.eye(4), (64, 48))
        assert started.seconds > 0 and started.nbytes > 0
        assert image.shape == (48, 64, 3) and (image[20:28, 28:36] > 150).all()  # the plane, in front
        # meshed here on first use: the same image
        assert np.array_equal(LazyPoisson(cloud, 6, 0.05)(K, np.eye(4), (64, 48)), image)
        bad = LazyPoisson(cloud, 17, 0.05, meshed(pool, 17))  # refused in the worker: raised by the first call
        with pytest.raises(InputError, match="depth"):
            bad(K, np.eye(4), (64, 48))


def test_seen_masks_without_per_image_depth_are_cast_from_the_scene(tiny_dataset, tmp_path):
    """A dataset written without gt/depth and gt/ids (synth --no-gt-depth): eval casts the
    capture cameras' depth from the scene, and the seen masks are those of the stored depth."""
    from capture import load_dataset
    from render.eval_config import EvalConfig
    from render.evaluate import prepare_views

    copy = tmp_path / "street"
    shutil.copytree(tiny_dataset, copy, ignore=shutil.ignore_patterns("depth", "ids"))
    assert load_dataset(copy).has_ground_truth and not load_dataset(copy).has_gt_depth
    config = EvalConfig(size=(96, 72))
    stored = prepare_views(tiny_dataset, [1], [0, 1, 2], config)
    cast = prepare_views(copy, [1], [0, 1, 2], config)
    for a, b in zip(stored, cast, strict=True):
        assert a.seen.any() and np.mean(a.seen != b.seen) <= 0.005
    # at the capture camera's own size a viewpoint of the capture takes its stored image and depth:
    # the renders the copy without stored depth makes, bit for bit
    stored = prepare_views(tiny_dataset, [1], [0, 1, 2], EvalConfig(), training=[2])
    cast = prepare_views(copy, [1], [0, 1, 2], EvalConfig(), training=[2])
    assert [v.where for v in stored] == ["on path", "off path", "training"]
    for a, b in zip(stored, cast, strict=True):
        assert np.array_equal(a.truth, b.truth) and np.array_equal(a.geometry, b.geometry)
    # the stored images are the renders only as truth_view makes them: its supersampling, not cast when read
    from data_synth import stores_truth

    assert stores_truth(tiny_dataset)
    scene = json.loads((tiny_dataset / "gt" / "scene.json").read_text())
    for name, synth in (("spp", {**scene["synth"], "spp": 1}), ("lazy", {**scene["synth"], "lazy": True}),
                        ("none", None)):
        other = tmp_path / f"other_{name}"
        (other / "gt").mkdir(parents=True)
        (other / "gt" / "scene.json").write_text(json.dumps({**scene, "synth": synth}))
        assert not stores_truth(other)


def test_eval_takes_its_poisson_meshes_from_the_clouds_cache(street, tmp_path):
    import shutil
    from concurrent.futures import Executor

    from billboards import model_reader as billboard_model
    from render.eval_config import EvalConfig
    from render.evaluate import evaluate_views
    from render.poisson_cache import PoissonCache

    tiny_dataset, tiny_cloud, model = street
    cloud = shutil.copy(tiny_cloud, tmp_path / "cloud.ply")  # a cache of its own
    drawable = billboard_model.load(model)
    config = EvalConfig(views=1, poisson_depth=7, workprecision_depths=(6,), panel_width=0, training_views=0)

    class NoWorkers(Executor):
        def submit(self, fn, /, *args, **kwargs):
            raise AssertionError("a worker was asked to mesh a cloud whose mesh is kept")

    first = evaluate_views(drawable, tiny_dataset, cloud, config=config)
    cache = PoissonCache.of(cloud)
    assert cache.path(7, config.trim_quantile).is_file() and cache.path(6, config.trim_quantile).is_file()
    again = evaluate_views(drawable, tiny_dataset, cloud, config=config, executor=NoWorkers())
    for name in ("Poisson mesh, on path", "Poisson depth 6, off path"):
        assert again["summary"][name]["psnr"] == first["summary"][name]["psnr"], name
