"""The benchmark's report: sections of rows with their notes, written as ``report.json``
(NaN as null) and ``report.md`` (NaN as n/a), with the machine and library versions."""

from __future__ import annotations

import json
import logging
import os
import platform
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.fileio import json_ready, write_bytes, write_json

logger = logging.getLogger(__name__)


@dataclass
class Report:
    """Sections of rows; each row a dict. Serialised to report.json and report.md."""

    settings: dict
    sections: dict[str, list[dict]] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)

    def add(self, section: str, row: dict) -> None:
        self.sections.setdefault(section, []).append(row)
        logger.info("%s: %s", section, row)

    def write(self, out: Path) -> None:
        import cv2
        import open3d

        machine = {"python": platform.python_version(), "platform": platform.platform(),
                   "cpus": os.cpu_count(), "numpy": np.__version__, "open3d": open3d.__version__,
                   "opencv": cv2.__version__}
        write_json(out / "report.json", json_ready({"machine": machine, "settings": self.settings,
                                                    "sections": self.sections, "notes": self.notes}))
        lines = ["# bbcity benchmark", "", "Machine: " + ", ".join(f"{k} {v}" for k, v in machine.items()),
                 "", "Settings: " + json.dumps(self.settings), ""]
        for name, rows in self.sections.items():
            lines += [f"## {name}", ""]
            if name in self.notes:
                lines += [self.notes[name], ""]
            keys = list(dict.fromkeys(k for r in rows for k in r))
            lines += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
            for r in rows:
                lines.append("| " + " | ".join(_fmt(r.get(k, "")) for k in keys) + " |")
            lines.append("")
        write_bytes(out / "report.md", "\n".join(lines).encode())


def _fmt(value) -> str:
    if isinstance(value, float):
        return "n/a" if not np.isfinite(value) else f"{value:.4g}"
    return str(value)
