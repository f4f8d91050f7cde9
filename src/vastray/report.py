"""The JSON report written beside every render: timings, counters and error against run time."""

from __future__ import annotations

import json
import platform
import sys
from importlib import metadata

import numpy as np

from vastray.render.imageio import atomic_path


def _version() -> str:
    try:
        return metadata.version("vastray")
    except metadata.PackageNotFoundError:
        return "unknown"


def build_report(*, store: str, settings: dict, seconds: dict, counters: dict,
                 error: dict | None = None, reference: str | None = None,
                 scheduler: str = "image") -> dict:
    """Assemble a report dictionary (see DESIGN.md, "Reports").

    ``error`` (MSE, PSNR, max difference against ``reference``) sits beside the run time so a
    reader sees what accuracy the time bought.
    """
    report = {
        "vastray": _version(),
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "command": " ".join(sys.argv),
        "store": store,
        "scheduler": scheduler,
        "settings": settings,
        "seconds": seconds,
        "counters": counters,
    }
    if error is not None:
        report["error"] = dict(error, reference=reference)
        report["error_vs_time"] = [{"seconds": seconds.get("total"), **error}]
    return report


def write_report(path, report: dict) -> None:
    """Write the report as indented JSON, atomically."""
    def default(obj):
        if isinstance(obj, (np.integer,)):
            return int(obj)
        if isinstance(obj, (np.floating,)):
            return float(obj)
        if isinstance(obj, (set, frozenset)):
            return sorted(obj)
        raise TypeError(f"not JSON serialisable: {type(obj)}")

    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(report, fh, indent=1, default=default)
        fh.write("\n")
