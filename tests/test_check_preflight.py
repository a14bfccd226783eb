"""``bbcity check``: inconsistent datasets are refused up front (issue 35).

Each case copies one tiny, complete synthetic dataset, damages one thing and asserts that
``bbcity check`` (the cheap checks every stage's reader runs) or ``bbcity check --deep``
(decoding every image and ground-truth array) exits 2 with one line naming the file and key.
"""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from bbcity.cli import main
from capture import load_dataset
from core.fileio import DataFormatError


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A complete 2 + 2-frame, 3-camera, 48×64 street dataset with ground truth (read-only)."""
    out = tmp_path_factory.mktemp("preflight") / "ds"
    assert main(["-q", "synth", "street", "--length", "6", "--frames", "2", "--width", "48", "--height", "64",
                 "--workers", "1", "--out", str(out)]) == 0
    return out


def _edit(path, change) -> None:
    """Rewrite the JSON file ``path`` after ``change`` (dict → None) edits it in place."""
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _copy(dataset, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    return root


def _check(root, caplog, *extra) -> int:
    caplog.clear()
    return main(["check", str(root), *extra])


def _error_line(caplog) -> str:
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "\n" not in errors[0], errors
    return errors[0]


def _same_centre(rig) -> None:
    rig["cameras"][1]["cam_from_rig"] = rig["cameras"][0]["cam_from_rig"]


def _one_camera_far_apart(root) -> None:
    """Camera 0 alone, its frames 100 m apart: no neighbour is a stereo partner."""
    _edit(root / "rig.json", lambda d: d.update(cameras=d["cameras"][:1]))
    _edit(root / "dataset.json", lambda d: d.update(cameras=1))

    def spread(poses):
        for i, frame in enumerate(poses["frames"]):
            frame["world_from_rig"][0][3] = 100.0 * i
    _edit(root / "poses.json", spread)


#: name → (damage(root), file the message names, words it holds)
CHEAP = {
    "reference camera out of range": (lambda r: _edit(r / "rig.json", lambda d: d.update(reference_camera=3)),
                                      "rig.json", "reference_camera"),
    "reference camera a string": (lambda r: _edit(r / "rig.json", lambda d: d.update(reference_camera="0")),
                                  "rig.json", "reference_camera"),
    "reference camera a bool": (lambda r: _edit(r / "rig.json", lambda d: d.update(reference_camera=True)),
                                "rig.json", "reference_camera"),
    "unknown camera model": (lambda r: _edit(r / "rig.json", lambda d: d["cameras"][1].update(model="fisheye624")),
                             "rig.json", "cameras[1].model"),
    "frames disagree with poses": (lambda r: _edit(r / "dataset.json", lambda d: d.update(frames=5)),
                                   "dataset.json", '"frames"'),
    "cameras disagree with the rig": (lambda r: _edit(r / "dataset.json", lambda d: d.update(cameras=2)),
                                      "dataset.json", '"cameras"'),
    "image size disagrees with the rig": (lambda r: _edit(r / "dataset.json", lambda d: d.update(image_size=[64, 48])),
                                          "dataset.json", '"image_size"'),
    "ground truth without gt/": (lambda r: shutil.rmtree(r / "gt"), "dataset.json", '"ground_truth"'),
    "principal point cx far outside": (lambda r: _edit(r / "rig.json", lambda d: d["cameras"][0].update(cx=500.0)),
                                       "rig.json", "cameras[0].cx"),
    "principal point cy far outside": (lambda r: _edit(r / "rig.json", lambda d: d["cameras"][2].update(cy=-200.0)),
                                       "rig.json", "cameras[2].cy"),
    "stereo pair without a baseline": (lambda r: _edit(r / "rig.json", _same_centre), "rig.json",
                                       "share their optical centre"),
    "one camera without stereo partners": (_one_camera_far_apart, "poses.json", "no frame of this one-camera capture"),
}


@pytest.mark.parametrize("case", list(CHEAP))
def test_check_refuses_an_inconsistent_dataset(case, dataset, tmp_path, caplog):
    damage, name, key = CHEAP[case]
    root = _copy(dataset, tmp_path)
    damage(root)
    assert _check(root, caplog) == 2
    line = _error_line(caplog)
    assert str(root / name) in line and key in line


def _depth(root):
    return root / "gt" / "depth" / "cam1" / "000002.npy"


def _resize_image(root):
    path = root / "images" / "cam2" / "000001.png"
    cv2.imwrite(str(path), np.zeros((48, 64, 3), np.uint8))  # landscape where the rig says 48x64 portrait


def _flat_camera(root) -> None:
    for path in (root / "images" / "cam1").glob("*.png"):
        cv2.imwrite(str(path), np.zeros((64, 48, 3), np.uint8))


def _ids(root):
    return root / "gt" / "ids" / "cam0" / "000001.npy"


def _set_ids(root, value: int) -> None:
    ids = np.load(_ids(root))
    ids[:4] = value
    np.save(_ids(root), ids)


#: name → (damage(root), file the message names, words it holds): what only --deep finds
DEEP = {
    "ground-truth depth all NaN": (lambda r: np.save(_depth(r), np.full((64, 48), np.nan, np.float32)),
                                   _depth, "NaN everywhere"),
    "ground-truth depth of the wrong shape": (lambda r: np.save(_depth(r), np.ones((48, 64), np.float32)),
                                              _depth, "shape (48, 64), expected (64, 48)"),
    "ground-truth depth missing": (lambda r: _depth(r).unlink(), _depth, "missing"),
    "image of the wrong size": (_resize_image, lambda r: r / "images" / "cam2" / "000001.png", "expected 48x64"),
    "a camera's images all one flat colour": (_flat_camera, lambda r: r / "images" / "cam1", "one flat colour"),
    "object ids beyond the scene's": (lambda r: _set_ids(r, 10 ** 6), _ids, "object ids outside −1"),
    "object ids below −1": (lambda r: _set_ids(r, -7), _ids, "object ids outside −1"),
    "depth without ids": (lambda r: shutil.rmtree(r / "gt" / "ids"), lambda r: r / "gt" / "ids",
                          "while gt/depth is there"),
}


@pytest.mark.parametrize("case", list(DEEP))
def test_deep_check_refuses_bad_arrays(case, dataset, tmp_path, caplog):
    damage, where, words = DEEP[case]
    root = _copy(dataset, tmp_path)
    damage(root)
    assert _check(root, caplog) == 0  # the cheap check does not decode arrays
    assert _check(root, caplog, "--deep") == 2
    line = _error_line(caplog)
    assert str(where(root)) in line and words in line


def test_valid_datasets_pass(dataset, tmp_path, caplog):
    """The generator's dataset, and the variants a user's own capture may have: no
    dataset.json, rig.json without "reference_camera" or "model", a principal point a
    little outside the image, no per-image ground truth."""
    assert _check(dataset, caplog) == 0 and _check(dataset, caplog, "--deep") == 0
    root = _copy(dataset, tmp_path)
    (root / "dataset.json").unlink()
    shutil.rmtree(root / "gt" / "depth")
    shutil.rmtree(root / "gt" / "ids")

    def plain(d):
        del d["reference_camera"]
        del d["cameras"][0]["model"]
        d["cameras"][1].update(cx=-20.0, cy=100.0)
    _edit(root / "rig.json", plain)
    assert _check(root, caplog) == 0 and _check(root, caplog, "--deep") == 0


def test_every_stage_refuses_what_check_refuses(dataset, tmp_path, caplog):
    """The checks live in the reader (load_dataset), so recon refuses the dataset before any work."""
    root = _copy(dataset, tmp_path)
    _edit(root / "dataset.json", lambda d: d.update(frames=5))
    with pytest.raises(DataFormatError, match='"frames" is 5'):
        load_dataset(root)
    caplog.clear()
    assert main(["recon", str(root), "--out", str(tmp_path / "work"), "--workers", "1"]) == 2
    assert str(root / "dataset.json") in _error_line(caplog)
    assert not (tmp_path / "work" / "cloud.ply").exists()


def test_stages_warn_of_ground_truth_that_gt_lacks(dataset, tmp_path, caplog):
    """A synthetic dataset copied without gt/ (as a capture without ground truth): check refuses
    it, the stages read it as such a capture with a warning naming dataset.json."""
    root = tmp_path / "copy"
    shutil.copytree(dataset, root, ignore=shutil.ignore_patterns("gt"))
    with pytest.raises(DataFormatError, match='"ground_truth" is true'):
        load_dataset(root, strict=True)
    caplog.clear()
    ds = load_dataset(root)
    assert not ds.has_ground_truth
    assert any(r.levelname == "WARNING" and str(root / "dataset.json") in r.getMessage() for r in caplog.records)
