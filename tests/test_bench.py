"""`bbcity bench`: the report's structure, and the whole quick bench end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bbcity.bench import run_bench
from bbcity.bench_city import added_metre_seconds
from bbcity.bench_config import BenchConfig
from bbcity.bench_report import Report


def test_report_writes_nan_as_null_and_markdown_as_na(tmp_path):
    report = Report(settings={"x": 1})
    report.add("Section", {"what": "a", "value": float("nan"), "n": np.int64(3), "r": np.float32(0.5)})
    report.notes["Section"] = "a note"
    report.write(tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    assert data["sections"]["Section"] == [{"what": "a", "value": None, "n": 3, "r": 0.5}]
    assert {"python", "numpy", "open3d", "opencv"} <= set(data["machine"])
    md = (tmp_path / "report.md").read_text()
    assert "| a | n/a | 3 | 0.5 |" in md and "a note" in md


def test_config_refuses_bad_settings():
    with pytest.raises(ValueError):
        BenchConfig(scene="moon")
    with pytest.raises(ValueError):
        BenchConfig(scales=())
    quick = BenchConfig.quick_config(scene="town")
    assert quick.quick and quick.scene == "town" and quick.scales == (1, 2)


def test_bench_rig_is_the_default_rig_scaled_down_when_quick():
    from data_synth import RigConfig

    default = RigConfig()
    assert BenchConfig().rig() == default  # what `make demo` builds
    quick = BenchConfig.quick_config().rig()
    assert (quick.width, quick.height) == (default.width // 2, default.height // 2)
    assert quick.width * default.height == quick.height * default.width  # same aspect ratio …
    same = ("hfov_deg", "pitch_deg", "baselines", "mount_height")
    assert [getattr(quick, k) for k in same] == [getattr(default, k) for k in same]
    assert abs(quick.vfov_deg - default.vfov_deg) < 1e-9  # … and field of view


@pytest.mark.slow
def test_quick_bench_writes_every_section(tmp_path):
    """The smoke run (about 2 minutes): every section present, each speed paired with a
    same-run baseline, the plots written."""
    run_bench(BenchConfig.quick_config(), tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    sections = data["sections"]
    for name in ("Scene generation", "Pipeline stages", "Scaling", "Octree", "Stereo sweep",
                 "Stereo: trinocular vs single pairs", "Texture sweep", "Sampling against ground truth",
                 "Billboard model", "Rendering: decode", "Rendering: level of detail", "Rendering: culling (street)",
                 "Rendering: culling (town meshes)", "Novel views", "Fit"):
        assert sections.get(name), f"section {name!r} missing or empty"
    fit = sections["Fit"]   # the residual against time: falls from the sampled model's, the plot written
    assert fit[-1]["training pixels PSNR dB"] > fit[0]["training pixels PSNR dB"] and (tmp_path / "fit.png").is_file()
    stages = {r["stage"].strip() for r in sections["Pipeline stages"]}
    assert {"synthesis", "stereo, per frame", "fusion", "octree", "sampling", "PCA", "atlas packing (quantise)",
            "model load + GPU upload"} <= stages
    assert [r["scale"] for r in sections["Scaling"]] == ["1×", "2×"]
    assert all(r["wall s"] is None or r["wall s"] >= 0 for r in sections["Pipeline stages"])
    decode = sections["Rendering: decode"]
    assert any("baseline" in r["decode"] for r in decode)
    assert all(math.isfinite(r["ratio to CPU decode"]) and r["ratio to CPU decode"] > 0 for r in decode)
    assert all(0 < r["fps p5"] <= r["fps"] for r in decode)  # the 95th-percentile frame time is no shorter
    assert {r["decode"] for r in decode} == {"cpu (baseline)", "gpu exact", "gpu LOD"}
    assert {r["view"] for r in decode} == {"facade -y", "facade +y", "along +x", "capture path"}
    assert all(r["overdraw layers"] >= r["overdraw written"] > 0 for r in decode
               if r["cull"] == "frustum" and r["view"] != "capture path" and "gpu" in r["decode"])
    lod = sections["Rendering: level of detail"]
    assert {r["size"] for r in lod} == {"1280×720", "1920×1080"}
    assert all(r["PSNR vs exact dB"] > 20 for r in lod if r["decode"] == "gpu LOD")
    assert all(r["ratio to exact"] == 1 for r in lod if "baseline" in r["decode"])
    street = sections["Rendering: culling (street)"]
    assert all(r["ratio to frustum"] == 1 for r in street if r["cull"] == "frustum (baseline)")
    town = {r["cull"]: r for r in sections["Rendering: culling (town meshes)"]}
    assert town["occlusion"]["drawn"] < town["frustum"]["drawn"] <= town["none"]["drawn"]
    methods = {r["method"] for r in sections["Novel views"]}
    assert {"billboards", "point projection (baseline)", "uncompressed billboards",
            "Poisson mesh, depth 10 (baseline)", "Poisson depth 8"} <= methods
    for png in ("scaling.png", "stereo_sweep.png", "texture_sweep.png", "novel_views_workprecision.png"):
        assert (tmp_path / png).stat().st_size > 1000
    assert "## Scaling" in (tmp_path / "report.md").read_text()
    assert "Executors: Dask against the local pool" not in sections    # --scene executor runs it


def test_executor_section_pairs_each_executor_with_the_pool_and_compares_their_outputs(tmp_path, monkeypatch):
    """The section's report from stand-in runs (each writes its outputs and takes fixed
    seconds): medians, the speed against the pool, and which files differ."""
    import bbcity.bench_executor as section

    monkeypatch.setattr("data_synth.write_dataset", lambda *a, **k: None)
    seconds = {"local": (2.0, 4.0), "dask": (3.0, 5.0)}

    def run(kind, workers, dataset, root):
        (root / "model").mkdir(parents=True)
        (root / "model" / "a.npy").write_bytes(b"same")
        (root / "model" / "b.npy").write_bytes(kind.encode() if kind == "dask" and differ else b"same")
        (root / "model" / "build_report.json").write_text(kind)            # reports hold timings: not compared
        return seconds[kind]

    monkeypatch.setattr(section, "_run", run)
    for differ, outputs in ((False, "byte-identical"), (True, "differ: model/b.npy")):
        report = Report(settings={})
        section.bench_executor(BenchConfig(repeats=1, workers=2), report, tmp_path / str(differ))
        rows = {r["executor"]: r for r in report.sections["Executors: Dask against the local pool"]}
        assert rows["local process pool (baseline)"]["outputs"] == "baseline"
        dask = rows["Dask LocalCluster"]
        assert dask["outputs"] == outputs
        assert dask["recon s"] == 3.0 and dask["build s"] == 5.0 and dask["total s"] == 8.0
        assert dask["speed vs local"] == pytest.approx(6.0 / 8.0)


@pytest.mark.slow
def test_quick_city_bench_measures_each_scale_and_the_spread(tmp_path):
    """The city section at 1× and 2× of a 6 m street (about 2 minutes): a row per scale with
    every stage's peak memory and the viewer's walk under its budget, and the spread row."""
    run_bench(BenchConfig.quick_config(scene="city", city_scales=(1, 2), city_gpu_budget_mb=64, city_lazy=True),
              tmp_path)
    rows = json.loads((tmp_path / "report.json").read_text())["sections"]["City scale"]
    assert [r["scale"] for r in rows] == ["1×", "2×", "max / min"]
    for r in rows[:2]:
        assert r["tiles"] >= 1 and r["billboards"] > 0 and r["dataset MB on disk"] > 0
        for key in ("reconstruction peak MB (main)", "reconstruction peak MB (worker)", "build peak MB (main)",
                    "build peak MB (worker)", "viewer peak MB"):
            assert r[key] > 50
        assert 0 < r["GPU peak MB"] <= r["GPU budget MB"] == 64
        assert r["first frame ms"] > 0 and r["max frame ms"] > 0
    assert rows[0]["build CPU s per m, vs 1×"] == 1
    assert all(v is None or v >= 1 for k, v in rows[2].items() if k != "scale")


def test_seconds_per_added_metre_do_not_count_a_fixed_cost():
    """A fixed cost makes seconds per metre fall with the length; per metre added beyond the
    first street they stay equal exactly when the time is linear in the length."""
    lengths = [120.0, 480.0, 1920.0]
    linear = [20.0 + 0.5 * x for x in lengths]
    np.testing.assert_allclose(added_metre_seconds(lengths, linear), [0.5, 0.5], rtol=1e-12)
    per_metre = np.divide(linear, lengths)
    assert per_metre[0] / per_metre[-1] > 1.25  # what the fixed cost does to seconds per metre
    quadratic = [1e-3 * x * x for x in lengths]
    growth = added_metre_seconds(lengths, quadratic)
    assert growth[1] / growth[0] == pytest.approx((1920 + 120) / (480 + 120), rel=1e-12)
    assert len(added_metre_seconds([120.0], [3.0])) == 0
    for bad in (([120.0, 120.0], [1.0, 2.0]), ([480.0, 120.0], [2.0, 1.0]), ([120.0, 480.0], [1.0]),
                ([120.0, float("nan")], [1.0, 2.0])):
        with pytest.raises(ValueError):
            added_metre_seconds(*bad)
