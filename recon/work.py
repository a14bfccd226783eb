"""A recon WORK directory, read: what ``bbcity recon`` wrote and what it was made from.

WORK holds ``cloud.ply`` (or its tiles), ``recon_report.json`` and, when the poses were not
the dataset's own, ``poses.json``. :class:`Work` is the one reader of it: the dataset it was
reconstructed from (found relative to WORK first, and only when its files are the ones recon
read), the poses file recon wrote, the holdout it was made with.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.fileio import DataFormatError, read_json

#: The report recon writes into WORK.
REPORT = "recon_report.json"

#: The poses a recon used when they are not the dataset's own, beside the cloud (``bbcity build
#: WORK``, ``eval`` and ``render`` read them through the model's ``info["poses"]``).
WORK_POSES = "poses.json"

#: The files that name a dataset's capture: a dataset whose files differ is another capture.
DATASET_IDENTITY = ("rig.json", "poses.json", "dataset.json")


def file_digest(path: os.PathLike | str) -> str:
    """SHA-256 of a file's bytes (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def dataset_digest(dataset_dir: os.PathLike | str) -> str:
    """SHA-256 of the dataset's :data:`DATASET_IDENTITY` files (those present, named and in order):
    what a WORK records of the dataset it was reconstructed from."""
    h = hashlib.sha256()
    for name in DATASET_IDENTITY:
        path = Path(dataset_dir) / name
        if path.is_file():
            h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@dataclass(frozen=True)
class Work:
    """A recon WORK directory: ``path`` and its ``report`` (recon_report.json, a JSON object)."""

    path: Path
    report: dict

    @classmethod
    def open(cls, path: os.PathLike | str) -> "Work":
        """Read WORK's report; a missing or malformed one is a :class:`DataFormatError` naming it."""
        path = Path(path)
        report = read_json(path / REPORT)
        if not isinstance(report, dict):
            raise DataFormatError(path / REPORT, "is not a JSON object")
        return cls(path, report)

    @property
    def report_path(self) -> Path:
        return self.path / REPORT

    @property
    def cloud(self) -> Path:
        """The fused cloud, ``WORK/cloud.ply``."""
        return self.path / "cloud.ply"

    def dataset(self) -> Path:
        """The dataset WORK was built from, the same from any current directory.

        The report names it relative to WORK and by absolute path, with a digest of its files
        (:func:`dataset_digest`): the relative one wins (WORK and its dataset moved together),
        then the absolute one (WORK moved alone), and either only when its files are the ones
        recon read; another dataset found there is refused (pass --images).
        """
        report, path = self.report, self.report_path
        named = report.get("dataset")
        if not isinstance(named, str):
            raise DataFormatError(path, "does not name the dataset; pass --images")
        relative = report.get("dataset_from_work")
        digest = report.get("dataset_digest")
        candidates = [self.path / relative] if isinstance(relative, str) else []
        if Path(named).is_absolute():
            candidates.append(Path(named))
        if not candidates:  # written before reports named it absolutely: relative to an unknown directory
            raise DataFormatError(path, f"names the dataset {named!r} relative to the directory recon ran in; "
                                        "pass --images")
        found = [c for c in candidates if c.is_dir()]
        for candidate in found:
            if not isinstance(digest, str) or dataset_digest(candidate) == digest:  # older reports hold no digest
                return candidate.resolve()
        if found:
            raise DataFormatError(path, f"its dataset is not at {found[0]} any more: that folder holds another "
                                        "capture (its rig.json, poses.json or dataset.json differ); pass --images")
        raise DataFormatError(path, f"its dataset {named} is gone (nor is it at {relative} from the work "
                                    "directory); pass --images")

    def poses_file(self) -> Path | None:
        """The poses.json recon wrote into WORK (its "poses_file": the poses were not the
        dataset's own), else None (the dataset's poses.json). It is read in WORK, wherever WORK
        was when recon ran, and only when it is the file recon wrote (its "poses_digest")."""
        name = self.report.get("poses_file")
        if not isinstance(name, str):
            return None
        path = self.path / Path(name).name
        if not path.is_file():
            raise DataFormatError(self.report_path, f"its poses file {path} is missing (the cloud lies in the frame "
                                                    "of those poses; rerun recon or pass --poses)")
        digest = self.report.get("poses_digest")
        if isinstance(digest, str) and file_digest(path) != digest:
            raise DataFormatError(path, "not the poses file recon wrote (changed or truncated since; the cloud lies "
                                        "in the frame of those poses): rerun recon or pass --poses")
        return path

    def holdout(self) -> int:
        """The ``--holdout`` WORK was made with (0 when its report predates it); a value that is
        no holdout is one error naming the report and the key."""
        config = self.report.get("config")
        holdout = config.get("holdout", 0) if isinstance(config, dict) else 0
        if isinstance(holdout, bool) or not isinstance(holdout, int) or holdout < 0 or holdout == 1:
            raise DataFormatError(self.report_path, f"config.holdout must be 0 (none) or an integer ≥ 2, "
                                                    f"got {holdout!r}")
        return holdout

    def max_depth(self) -> float:
        """The farthest depth WORK's stereo kept, metres (inf: no limit; the report writes it
        "Infinity"); a missing or malformed one is an error naming the report."""
        try:
            value = self.report["config"]["trinocular"]["stereo"]["max_depth"]
            return np.inf if value is None else float(value)
        except (KeyError, TypeError, ValueError) as e:
            raise DataFormatError(self.report_path, f"config.trinocular.stereo.max_depth is missing or no "
                                                    f"number ({e})") from None
