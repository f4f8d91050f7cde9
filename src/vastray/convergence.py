"""Convergence of a progressive render, from its report's ``passes``: relMSE against time,
the seconds it took to reach an error, and its efficiency (no plotting here; see ``plot``).

A render's report lists one entry per finished pass (``seconds`` since the render started,
``rel_mse`` against ``--reference`` or, without one, ``estimated_rel_mse`` from the film
alone). A Monte Carlo estimate's error falls as 1/t, so 1/(relMSE·t) is roughly constant along a
run and compares runs: higher is better.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from vastray.report import run_label
from vastray.scene.errors import InputError

THRESHOLDS = (1e-1, 1e-2, 1e-3)
TABLE_CAPTION = ("seconds to reach relMSE ≤ 1e-1, 1e-2, 1e-3 (log-log interpolation between "
                 "the two passes that bracket it; — never reached); efficiency 1/(relMSE·t) "
                 "at the last pass, in 1/s")


@dataclass
class Curve:
    """One run's convergence: a point per pass with an error.

    Attributes
    ----------
    label : str
        The run's scheduler and options (``vastray.report.run_label``).
    seconds : list of float
        Wall seconds since the render started, at the end of each pass.
    rel_mse : list of float
        Per-pixel relMSE at each pass (0 for a render identical to its reference).
    estimated : bool
        True when ``rel_mse`` is the film's own estimate (the render had no reference).
    """

    label: str
    seconds: list[float]
    rel_mse: list[float]
    estimated: bool = False

    @property
    def lossless(self) -> bool:
        """Whether every point is exactly 0 (no point can go on a log axis)."""
        return all(e == 0 for e in self.rel_mse)


def time_to_error(seconds, rel_mse, threshold: float) -> float | None:
    """The seconds a run took to reach ``rel_mse <= threshold``.

    The first pass at or below ``threshold`` and the pass before it bracket the crossing;
    the time is interpolated linearly in log-log space between them (a 1/t run's error is a
    straight line there). When the first pass is already below, or an end of the bracket is 0
    (no logarithm), that pass's time is returned as it is.

    Parameters
    ----------
    seconds, rel_mse : sequence of float
        The passes, in order.
    threshold : float
        The error to reach (> 0).

    Returns
    -------
    float or None
        Seconds, or None when no pass reached ``threshold``.
    """
    for i, (t, e) in enumerate(zip(seconds, rel_mse, strict=True)):
        if e > threshold:
            continue
        if i == 0:
            return float(t)
        t0, e0 = seconds[i - 1], rel_mse[i - 1]
        if min(t0, t, e0, e) <= 0 or e0 == e:
            return float(t)
        slope = (math.log(t) - math.log(t0)) / (math.log(e) - math.log(e0))
        return math.exp(math.log(t0) + slope * (math.log(threshold) - math.log(e0)))
    return None


def efficiency(seconds: float, rel_mse: float) -> float:
    """1/(relMSE·t), in 1/s: constant along an ideal Monte Carlo run, higher is better;
    infinite for an error of 0."""
    if seconds <= 0:
        raise ValueError(f"efficiency needs seconds > 0, not {seconds}")
    return math.inf if rel_mse == 0 else 1.0 / (rel_mse * seconds)


def convergence_series(report: dict, path: str | Path | None = None) -> Curve:
    """The convergence curve of a single render's ``report``.

    Uses each pass's ``rel_mse`` when the report has a reference, else its
    ``estimated_rel_mse``; passes whose value is null, or whose time is null or 0 (no place
    on a log axis), are skipped.

    Raises
    ------
    InputError
        Naming ``path``, when the report cannot give a curve: an animation summary, no
        ``passes`` list, or no pass with an error.
    """
    if isinstance(report.get("frames"), list):
        raise InputError(path, "is an animation summary (per-frame reports): plot it with "
                               "--mode frames")
    passes = report.get("passes")
    if not isinstance(passes, list):
        raise InputError(path, "has no passes list (written before progressive rendering?); "
                               "render it again with --report, or plot it with --mode frames")
    passes = [p for p in passes
              if isinstance(p, dict) and _number(p.get("seconds")) and p["seconds"] > 0]
    estimated = not any(_number(p.get("rel_mse")) for p in passes)
    key = "estimated_rel_mse" if estimated else "rel_mse"
    points = [(float(p["seconds"]), float(p[key])) for p in passes if _number(p.get(key))]
    if any(error < 0 for _, error in points):
        raise InputError(path, f"holds a negative {key}, which vastray never writes; was it "
                               "edited?")
    if not points:
        raise InputError(path, f"none of its {len(passes)} passes has an error: render "
                               "with --reference, or with --spp 2 or more for the film's own "
                               "estimate" + (" (it has only one pass at 1 spp)"
                                             if len(passes) == 1 else ""))
    return Curve(run_label(report), [t for t, _ in points], [e for _, e in points], estimated)


def _number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


@dataclass
class Row:
    """One run's line of the time-to-error table."""

    label: str
    to_threshold: list[float | None]
    final_rel_mse: float
    final_seconds: float
    efficiency: float


def table_rows(curves: list[Curve]) -> list[Row]:
    """The time-to-error table: a row per curve (``THRESHOLDS``, then the last pass)."""
    rows = []
    for c in curves:
        t, e = c.seconds[-1], c.rel_mse[-1]
        label = c.label + (" (estimated)" if c.estimated else "")
        rows.append(Row(label, [time_to_error(c.seconds, c.rel_mse, h) for h in THRESHOLDS],
                        e, t, efficiency(t, e) if t > 0 else math.nan))
    return rows


def format_seconds(value: float | None) -> str:
    """``value`` seconds in a table cell: 3 significant digits, or — when never reached."""
    return "—" if value is None else f"{value:.3g}"


def _exponent(value: float) -> str:
    """``1e-2`` for 0.01 (a threshold as the table's header names it)."""
    return f"{value:.0e}".replace("e-0", "e-").replace("e+0", "e")


def format_efficiency(value: float) -> str:
    if math.isinf(value):
        return "∞ (relMSE 0)"
    return "—" if math.isnan(value) else f"{value:.3g}"


TABLE_HEADER = ["run", *(f"s to ≤{_exponent(h)}" for h in THRESHOLDS), "final relMSE",
                "1/(relMSE·t) (1/s)"]


def table_cells(rows: list[Row]) -> list[list[str]]:
    """The table's cells, a list per row, in the order of ``TABLE_HEADER``."""
    return [[r.label, *(format_seconds(s) for s in r.to_threshold), f"{r.final_rel_mse:.3g}",
             format_efficiency(r.efficiency)] for r in rows]


def markdown_table(rows: list[Row]) -> str:
    """The table as Markdown (for bench/README.md), its caption in italics above it."""
    lines = [f"_{TABLE_CAPTION[0].upper()}{TABLE_CAPTION[1:]}._", "",
             "| " + " | ".join(TABLE_HEADER) + " |",
             "|" + "|".join(["---"] + ["---:"] * (len(TABLE_HEADER) - 1)) + "|"]
    for cells in table_cells(rows):
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines)
