"""The JSON report written beside every render: timings, counters and error against run time."""

from __future__ import annotations

import json
import platform
import sys
from importlib import metadata

import numpy as np

from vastray.render.imageio import atomic_path


def package_version() -> str:
    """The installed vastray's version."""
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
        "vastray": package_version(),
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


def strict_json(value):
    """``value`` with every non-finite float replaced by None: reports are strict JSON (RFC
    8259 has no NaN or Infinity), so any parser reads them. Where this happens is
    documented: ``psnr_db`` is null for identical images."""
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, (float, np.floating)) and not np.isfinite(value):
        return None
    return value


def write_report(path, report: dict) -> None:
    """Write the report as indented, strict JSON (no NaN/Infinity), atomically."""
    def default(obj):
        if isinstance(obj, (np.integer,)):
            return int(obj)
        if isinstance(obj, (np.floating,)):
            return float(obj)
        if isinstance(obj, (set, frozenset)):
            return sorted(obj)
        raise TypeError(f"not JSON serialisable: {type(obj)}")

    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(strict_json(report), fh, indent=1, default=default, allow_nan=False)
        fh.write("\n")
