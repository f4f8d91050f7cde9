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


def run_header(store: str, scheduler: str, options: dict | None) -> dict:
    """What every report opens with: versions, the command, the store and how it was run
    (``embree``: how this process queried Embree, where it did: ``library.description``)."""
    from vastray.scene.embree.library import description

    header = {
        "vastray": package_version(),
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "command": " ".join(sys.argv),
        "store": store,
        "scheduler": scheduler,
        "options": dict(options or {}),
    }
    embree = description()
    if embree is not None:
        header["embree"] = embree
    return header


def count_overflow(image: np.ndarray, counters: dict, where: str) -> int:
    """Count the pixels of ``image`` ((H, W, 3)) that are NaN or infinite once written as
    float32, as ``counters["nonfinite_pixels"]``, and say so on stderr when there are any:
    such a pixel never reaches a file silently.

    Returns
    -------
    The count.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(np.asarray(image).astype(np.float32)).all(axis=-1)
    count = int(np.count_nonzero(~finite))
    counters["nonfinite_pixels"] = count
    if count:
        print(f"warning: {where}: {count:,} of {finite.size:,} pixels are NaN or infinite in "
              "float32 (a light too strong for the scene's units?); written as they are",
              file=sys.stderr)
    return count


def build_report(*, store: str, settings: dict, seconds: dict, counters: dict,
                 error: dict | None = None, reference: str | None = None,
                 scheduler: str = "image", options: dict | None = None,
                 frame: int | None = None, progress: dict | None = None) -> dict:
    """Assemble a report dictionary (see DESIGN.md, "Reports").

    ``error`` (MSE, PSNR, relative MSE, max difference against ``reference``) sits beside the
    run time so a reader sees what accuracy the time bought. ``options`` are the run's
    switches beside the scheduler (nodes, cache, preload, ``simplified``...): with it they
    label the run in ``vastray plot``. ``frame`` is set for a frame of an animation.
    ``progress`` (``Progression.report``) adds ``stopped_by`` and the per-pass series
    ``passes`` (time, spp, error, variance estimate and confidence interval of each pass).
    """
    report = run_header(store, scheduler, options)
    if frame is not None:
        report["frame"] = frame
    report.update(settings=settings, seconds=seconds, counters=counters)
    if progress is not None:
        report.update(progress)
    if error is not None:
        report["error"] = dict(error, reference=reference)
        report["error_vs_time"] = [{"seconds": seconds.get("total"), **error}]
    return report


def run_label(report: dict) -> str:
    """A short name for the run a report describes: its scheduler and the options that change
    what or how it renders, e.g. ``"spec-ooc --spp 4 --cache 4 --no-preload"``."""
    options = report.get("options") or {}
    parts = [str(report.get("scheduler", "?"))]
    if (report.get("settings") or {}).get("spp") is not None:
        parts.append(f"--spp {report['settings']['spp']}")
    if options.get("nodes"):
        parts.append(f"--nodes {options['nodes']}")
    if options.get("cache") is not None:
        parts.append(f"--cache {options['cache']}")
    if options.get("history_depth") is not None:
        parts.append(f"--history-depth {options['history_depth']}")
    if options.get("preload") is False:
        parts.append("--no-preload")
    for name in ("assignment", "priority"):
        if options.get(name):
            parts.append(f"--{name} {options[name]}")
    if options.get("simplified"):
        parts.append(f"--simplified {options['simplified']}")
        if options["simplified"] == "portal":  # the portal settings a run changed
            from vastray.actors.job_options import JobOptions

            defaults = JobOptions(scheduler="temporal")
            for name in ("portal_threshold", "portal_resolution", "portal_interval",
                         "portal_memory"):
                if options.get(name) not in (None, getattr(defaults, name)):
                    parts.append(f"--{name.replace('_', '-')} {options[name]}")
    return " ".join(parts)


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
