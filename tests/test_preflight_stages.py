"""``bbcity check --deep`` is a complete pre-flight for recon, build and eval (issue 35).

Variants of one tiny synthetic dataset, each what a user's capture may hold (images of other
PNG kinds, a black frame, no dataset.json, gaps in the frame numbering, a frame without a pose,
a lens, world coordinates of a UTM zone, no per-image ground truth, no ground truth at all, two
cameras, one frame, a lazy dataset), are combined into a few datasets. Each must pass ``check --deep``, and then
recon, build and eval must all run on it (exit 0; fast settings): nothing that check
passed may fail on input in a stage. What check refuses is in tests/test_check_preflight.py.

One case lies beyond any pre-flight, and its test says so: images that contradict their rig
(the focal length of rig.json is not the lens the images were taken with) pass check, recon
finds nothing to match and writes an empty cloud with a warning, and build refuses that cloud
in one line naming it.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from bbcity.cli import main
from core.fileio import read_png, write_png

#: the fast settings of the stages (the variants are about input, not quality)
RECON = ("--voxel-size", "0.1", "--workers", "1")
BUILD = ("--voxel-size", "0.5", "--tile", "8", "--directions", "4", "--workers", "1")
EVAL = ("--workprecision-depths",)  # the Poisson baseline at depth 10 only


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A 3 + 3-frame, 3-camera, 96×72 street dataset with ground truth (read-only), and a lazy
    one of the same settings."""
    root = tmp_path_factory.mktemp("preflight")
    common = ["--length", "20", "--frames", "3", "--width", "96", "--height", "72", "--spp", "1", "--workers", "1"]
    assert main(["-q", "synth", "street", "--out", str(root / "stored"), *common]) == 0
    assert main(["-q", "synth", "street", "--out", str(root / "lazy"), "--lazy", *common]) == 0
    return root


def _edit(path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _image(root, frame: int, cam: int):
    return root / "images" / f"cam{cam}" / f"{frame:06d}.png"


def _as_mode(root, frame: int, cam: int, mode: str) -> None:
    """Rewrite one image as a PNG of PIL ``mode`` ("RGBA", "L", "P", "I;16": 16 bits grey)."""
    path = _image(root, frame, cam)
    rgb = read_png(path)
    if mode == "I;16":
        Image.fromarray((rgb.mean(axis=2) * 257).astype(np.uint16)).save(path)
    else:
        Image.fromarray(rgb).convert(mode).save(path)


def _renumber(root, every: int) -> None:
    """Frame i becomes frame i·every (gaps in the numbering), images and ground truth alike."""
    poses = json.loads((root / "poses.json").read_text())
    for frame in reversed(poses["frames"]):
        new = f"{int(frame['name']) * every:06d}"
        for path in root.glob(f"*/**/{frame['name']}.*"):
            path.rename(path.with_name(new + path.suffix))
        frame["name"] = new
    (root / "poses.json").write_text(json.dumps(poses))


def _keep_cameras(root, keep: list[int]) -> None:
    """A rig of the cameras ``keep`` (renumbered 0, 1, …), their images and ground truth."""
    _edit(root / "rig.json", lambda d: d.update(cameras=[d["cameras"][c] for c in keep], reference_camera=0))
    _edit(root / "dataset.json", lambda d: d.update(cameras=len(keep)))
    for folder in (root / "images", root / "gt" / "depth", root / "gt" / "ids"):
        for c in range(3):
            (folder / f"cam{c}").rename(folder / f"old{c}")
        for new, c in enumerate(keep):
            (folder / f"old{c}").rename(folder / f"cam{new}")
        for old in folder.glob("old*"):
            shutil.rmtree(old)


def images_and_metadata(root) -> None:
    """PNGs of every kind a camera or an editor writes, a black frame, no dataset.json, an image
    of no frame, reference camera 1 and no "model" key, a small lens on camera 0 (the images
    are pinhole renders: a lens the calibration got a little wrong), gaps in the frame
    numbering, and the scene's ground truth without per-image depth and ids."""
    for (frame, cam), mode in {(1, 0): "RGBA", (0, 1): "L", (1, 2): "I;16", (2, 0): "P"}.items():
        _as_mode(root, frame, cam, mode)
    write_png(_image(root, 2, 1), np.zeros((72, 96, 3), np.uint8))
    (root / "dataset.json").unlink()
    shutil.copy(_image(root, 0, 0), _image(root, 99, 0))

    def rig(d):
        d["reference_camera"] = 1
        del d["cameras"][2]["model"]
        d["cameras"][0]["distortion"] = {"model": "radtan", "k1": 0.01, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    _edit(root / "rig.json", rig)
    shutil.rmtree(root / "gt" / "depth")
    shutil.rmtree(root / "gt" / "ids")
    _renumber(root, 5)


def real_capture(root) -> None:
    """A capture without ground truth (as KITTI's), of two cameras, in UTM-sized world
    coordinates, with a frame without a pose."""
    _keep_cameras(root, [0, 1])

    def poses(d):
        for frame in d["frames"]:
            frame["world_from_rig"][0][3] += 500_000.0
            frame["world_from_rig"][1][3] += 4_000_000.0
        d["frames"][4]["world_from_rig"] = None
    _edit(root / "poses.json", poses)
    shutil.rmtree(root / "gt")
    _edit(root / "dataset.json", lambda d: d.update(ground_truth=False))


def one_frame(root) -> None:
    """A capture of one frame, its ground-truth depth partly NaN (sky where the renderer saw
    something)."""
    _edit(root / "poses.json", lambda d: d.update(frames=d["frames"][:1]))
    _edit(root / "dataset.json", lambda d: d.update(frames=1))
    depth = root / "gt" / "depth" / "cam0" / "000000.npy"
    values = np.load(depth)
    values[:30] = np.nan
    np.save(depth, values)


#: variant → (source dataset, change(root))
VARIANTS = {"images and metadata": ("stored", images_and_metadata), "real capture": ("stored", real_capture),
            "one frame": ("stored", one_frame), "lazy": ("lazy", lambda root: None)}


def _stages(root, tmp_path) -> dict[str, int]:
    """Exit codes of check --deep, recon, build and eval on ``root`` (fast settings of the stages)."""
    work, model = tmp_path / "work", tmp_path / "model"
    codes = {"check": main(["check", str(root), "--deep"])}
    codes["recon"] = main(["-q", "recon", str(root), "--out", str(work), *RECON])
    codes["build"] = main(["-q", "build", str(work), "--out", str(model), *BUILD]) if codes["recon"] == 0 else None
    codes["eval"] = (main(["-q", "eval", str(model), str(root), "--cloud", str(work / "cloud.ply"), *EVAL,
                           "--out", str(tmp_path / "eval")]) if codes["build"] == 0 else None)
    return codes


@pytest.mark.slow
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_what_check_passes_every_stage_runs(variant, base, tmp_path):
    source, change = VARIANTS[variant]
    root = tmp_path / "ds"
    shutil.copytree(base / source, root)
    change(root)
    assert _stages(root, tmp_path) == {"check": 0, "recon": 0, "build": 0, "eval": 0}
    model = json.loads((tmp_path / "eval" / "eval.json").read_text())["summary"]["model, on path"]
    assert model["psnr_covered"] > 12.0  # where the model draws, it draws the scene (not at another place)


@pytest.mark.slow
def test_images_that_contradict_their_rig_are_one_line_at_build(base, tmp_path, caplog):
    """Beyond a pre-flight: rig.json's focal length is not the images' (check cannot know), so
    recon matches nothing and warns, and build refuses the empty cloud naming it."""
    root = tmp_path / "ds"
    shutil.copytree(base / "stored", root)
    _edit(root / "rig.json", lambda d: d["cameras"][0].update(fx=1.0, fy=1.0))
    caplog.clear()
    codes = _stages(root, tmp_path)
    assert codes == {"check": 0, "recon": 0, "build": 2, "eval": None}
    assert any(r.levelname == "WARNING" and "no points reconstructed" in r.getMessage() for r in caplog.records)
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and str(tmp_path / "work" / "cloud.ply") in errors[0] and "no points" in errors[0]
