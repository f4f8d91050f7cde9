"""``vastray plot``: error against time of several runs, from their reports, as a PNG.

Two modes. ``convergence`` (single renders' reports, the default for them): each run's
per-pass relMSE against the seconds since it started, on log-log axes with a 1/t reference
slope, and a time-to-error table under the plot and on stdout (``vastray.convergence``).
``frames`` (animation summaries, the default for them): every frame with an error is one point
(seconds of that frame, MSE against its lossless reference), each run one labelled series, its
scheduler and options, with a larger marker at its mean. matplotlib is an optional extra
(``pip install vastray[plot]``), imported only here.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

from vastray.convergence import (
    TABLE_CAPTION,
    TABLE_HEADER,
    THRESHOLDS,
    Curve,
    convergence_series,
    markdown_table,
    table_cells,
    table_rows,
)
from vastray.render.imageio import atomic_path
from vastray.report import run_label
from vastray.scene.errors import InputError

log = logging.getLogger(__name__)

PLOT_EPILOG = """\
examples:
  # convergence: relMSE per pass against time, log-log, and the time-to-error table
  vastray render rm.store -o ref.exr --spp 256
  vastray render rm.store -o a.exr --spp 64 --reference ref.exr --report a.json
  vastray render rm.store -o b.exr --spp 64 --nodes 2 --scheduler async \\
      --reference ref.exr --report b.json
  vastray plot a.json b.json -o convergence.png > time_to_error.md

  # frames: error against seconds per frame of animations (--frames N summaries)
  vastray render rm.store -o oref.exr --scene orbit.toml --frames 8 --spp 64
  vastray render rm.store -o c.exr --scene orbit.toml --frames 8 --spp 4 \\
      --cache 25% --scheduler spec-ooc --reference oref.exr --report c.json
  vastray plot c.json -o error_vs_time.png

The mode follows the reports: single renders give --mode convergence, animation
summaries (or reports from before renders ran in passes) --mode frames. Without
--reference a run's curve is the film's own estimate (labelled "estimated, no
reference"; needs --spp 2 or more). The table (seconds to relMSE 1e-1, 1e-2, 1e-3 and
1/(relMSE·t) at the last pass) is printed on stdout as Markdown. An error of 0 (a
lossless run against its own reference) is drawn on the floor.
"""


@dataclass
class Series:
    """One run's points: seconds per frame and MSE against the reference, by frame."""

    label: str
    seconds: list[float]
    mse: list[float]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plot", help="plot error vs time of several runs: convergence per pass, or per frame (PNG)",
        description="Plot the error against time of several runs, read from their JSON reports\n"
                    "(`vastray render --report`), one labelled series per run: its scheduler and\n"
                    "options. Single renders: relMSE per pass against seconds (log-log, with a\n"
                    "1/t slope) and a time-to-error table, also printed on stdout as Markdown.\n"
                    "Animation summaries (--frames): MSE per frame against seconds per frame.\n"
                    "Needs matplotlib: pip install vastray[plot].",
        epilog=PLOT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reports", nargs="+", metavar="REPORT.json",
                   help="reports of `vastray render --report`")
    p.add_argument("-o", "--output", required=True, help="PNG file to write")
    p.add_argument("--mode", choices=MODES, default=None,
                   help="convergence: relMSE per pass against time; frames: error per frame "
                        "against seconds per frame (default: convergence when every report is "
                        "a single render with passes, else frames)")
    p.add_argument("--title", default=None, help="the plot's title")
    p.set_defaults(func=run_plot)


MODES = ("convergence", "frames")


def load_report(path: str | Path) -> dict:
    """The JSON report at ``path``.

    Raises
    ------
    InputError
        When the file is missing, not JSON, or not a vastray render report.
    """
    path = Path(path)
    try:
        report = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "report not found") from None
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a report") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"not a JSON report ({exc})") from None
    if not isinstance(report, dict) or "scheduler" not in report:
        raise InputError(path, "not a vastray render report (no scheduler)")
    return report


def default_mode(reports: list[dict]) -> str:
    """``convergence`` when every report is a single render with passes, else ``frames``
    (an animation summary, or a report written before renders ran in passes)."""
    if all(isinstance(r.get("passes"), list) and not isinstance(r.get("frames"), list)
           for r in reports):
        return "convergence"
    return "frames"


def frame_series(report: dict, path: str | Path | None = None) -> Series:
    """The points of one report for ``--mode frames``: a summary's frames, or a single render
    as one point.

    Raises
    ------
    InputError
        When the report holds no error (made without --reference).
    """
    if isinstance(report.get("frames"), list):
        entries = [(e.get("seconds", {}).get("total"), e.get("error")) for e in report["frames"]]
    else:
        entries = [(report.get("seconds", {}).get("total"), report.get("error"))]
    points = [(float(t), float(e["mse"])) for t, e in entries
              if t is not None and e and e.get("mse") is not None]
    if not points:
        raise InputError(path, "holds no error against a reference; render with --reference "
                               "to measure one")
    return Series(run_label(report), [t for t, _ in points], [m for _, m in points])


def load_series(path: str | Path) -> Series:
    """The ``--mode frames`` points of the report at ``path`` (see ``frame_series``)."""
    return frame_series(load_report(path), path)


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise InputError(None, "plotting needs matplotlib: pip install vastray[plot]") from None
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    return plt


def _save(fig, output: str | Path) -> None:
    with atomic_path(output) as tmp:
        fig.savefig(tmp, format="png")


def _write(fig, output: str | Path) -> None:
    """Save ``fig`` as a PNG at ``output`` and close it."""
    try:
        _save(fig, output)
    finally:
        _pyplot().close(fig)


def plot_error_vs_time(series: list[Series], output: str | Path,
                       title: str = "error vs time per frame") -> None:
    """Write the plot of ``series`` as a PNG (see ``error_vs_time_figure``)."""
    _write(error_vs_time_figure(series, title), output)


def error_vs_time_figure(series: list[Series], title: str = "error vs time per frame"):
    """The frames plot of ``series``: seconds per frame on x, MSE (log) on y, each run's
    frames and a larger marker at its mean; the legend right of the axes, its labels wrapped,
    so that it covers neither the points nor the axis labels (inside the axes, long run labels
    ran over the y label).

    Returns
    -------
    matplotlib.figure.Figure
        The caller closes it.
    """
    plt = _pyplot()
    positive = [m for s in series for m in s.mse if m > 0]
    floor = min(positive) / 10.0 if positive else 1e-12
    fig, ax = plt.subplots(figsize=(10, 4.5), dpi=120, layout="constrained")
    try:
        for s in series:
            lossless = all(m == 0 for m in s.mse)
            mse = [max(m, floor) for m in s.mse]
            label = s.label + (" (MSE 0, drawn on the floor)" if lossless else "")
            (points,) = ax.plot(s.seconds, mse, "o", alpha=0.5, markersize=4)
            mean_t, mean_mse = sum(s.seconds) / len(s.seconds), max(sum(s.mse) / len(s.mse), floor)
            ax.plot([mean_t], [mean_mse], "v" if lossless else "D", markersize=9,
                    color=points.get_color(), markeredgecolor="black",
                    label=textwrap.fill(label, LEGEND_WRAP))
        ax.set_yscale("log")
        ax.set_xlabel("seconds per frame (s)")
        ax.set_ylabel("MSE against the lossless render")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0,
                  fontsize="small")
    except BaseException:
        plt.close(fig)
        raise
    return fig


LEGEND_WRAP = 34  # characters per legend line: long run labels wrap instead of widening it
TABLE_WRAP = 44


def curve_label(curve: Curve) -> str:
    """A curve's legend entry: its run, and how its error was measured when not plainly."""
    if curve.lossless:
        return curve.label + " (relMSE 0, drawn on the floor)"
    return curve.label + (" (estimated, no reference)" if curve.estimated else "")


def slope_anchor(curves: list[Curve]) -> float | None:
    """The constant c of the reference line relMSE = c/t: the geometric mean of relMSE·t over
    every positive point, so the line runs through the middle of the curves (None without
    one)."""
    logs = [math.log(t * e) for c in curves for t, e in zip(c.seconds, c.rel_mse, strict=True)
            if t > 0 and e > 0]
    return math.exp(sum(logs) / len(logs)) if logs else None


def plot_convergence(curves: list[Curve], output: str | Path,
                     title: str = "convergence: relMSE against time") -> None:
    """Write the convergence plot of ``curves`` as a PNG (see ``convergence_figure``)."""
    _write(convergence_figure(curves, title), output)


def convergence_figure(curves: list[Curve], title: str = "convergence: relMSE against time"):
    """The convergence plot of ``curves``: seconds (log) on x, relMSE (log) on y, a 1/t
    reference line, the legend right of the axes and the time-to-error table under them.

    Returns
    -------
    matplotlib.figure.Figure
        Two subfigures: the plot's, and the table's. The caller closes it.
    """
    plt = _pyplot()
    positive = [e for c in curves for e in c.rel_mse if e > 0]
    floor = min(positive) / 10.0 if positive else 1e-6
    cells = table_cells(table_rows(curves))
    wrapped = [textwrap.fill(row[0], TABLE_WRAP) for row in cells]
    table_lines = 1.6 + sum(label.count("\n") + 1 for label in wrapped)  # + header
    table_h = 0.55 + 0.2 * table_lines  # inches: caption, header and rows
    fig = plt.figure(figsize=(10, 4.6 + table_h), dpi=120, layout="constrained")
    try:
        top, bottom = fig.subfigures(2, 1, height_ratios=[4.6, table_h])
        ax = top.subplots()
        colours = []
        for c in curves:
            rel = [max(e, floor) for e in c.rel_mse]
            (line,) = ax.plot(c.seconds, rel, marker="o", markersize=4, linewidth=1.5,
                              linestyle="--" if c.estimated else "-",
                              label=textwrap.fill(curve_label(c), LEGEND_WRAP))
            colours.append(line.get_color())
        anchor = slope_anchor(curves)
        if anchor is not None:
            times = [t for c in curves for t in c.seconds if t > 0]
            lo, hi = min(times), max(times)
            if hi <= lo * 1.5:  # a single time: still show the slope over half a decade
                lo, hi = lo / 1.8, hi * 1.8
            ax.plot([lo, hi], [anchor / lo, anchor / hi], linestyle=(0, (6, 4)), color="0.55",
                    linewidth=1.2, label="1/t (reference slope)", zorder=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        low, high = ax.get_ylim()
        for h in THRESHOLDS:  # the table's thresholds, where the curves are
            if low < h < high:
                ax.axhline(h, color="0.8", linewidth=0.8, linestyle=":", zorder=0)
        _label_log_ticks(ax.xaxis)
        _label_log_ticks(ax.yaxis)
        ax.set_xlabel("wall-clock time since the render started (s)")
        ax.set_ylabel(_y_label(curves))
        ax.set_title(title)
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0,
                  fontsize="small")
        _draw_table(bottom, cells, wrapped, colours)
    except BaseException:
        plt.close(fig)
        raise
    return fig


def _y_label(curves: list[Curve]) -> str:
    estimated = [c.estimated for c in curves]
    if all(estimated):
        return "estimated relMSE (per pixel, from the film: no reference)"
    if any(estimated):
        return "relMSE (per pixel; dashed: estimated, no reference)"
    return "relMSE (per pixel, against the reference)"


def _label_log_ticks(axis) -> None:
    """Plain numbers (0.2, 1, 5) on a log ``axis``: the decades, every tick between them when
    it spans under one decade, 2 and 5 under two (matplotlib's own 3x10^-1 labels run into
    each other)."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    low, high = sorted(axis.get_view_interval())
    if low <= 0 or high / low > 100:
        axis.set_minor_formatter(NullFormatter())
        return
    shown = range(2, 10) if high / low <= 10 else (2, 5)

    def minor(v, _):
        mantissa = round(v / 10 ** math.floor(math.log10(v)), 6)
        return f"{v:g}" if mantissa in shown else ""

    axis.set_minor_formatter(FuncFormatter(minor))


def _draw_table(fig, cells: list[list[str]], wrapped: list[str], colours: list) -> None:
    """The time-to-error table in (sub)figure ``fig``: its caption, header and a row per run,
    each run's label in its curve's colour."""
    ax = fig.subplots()
    ax.axis("off")
    ax.set_title(textwrap.fill(TABLE_CAPTION[0].upper() + TABLE_CAPTION[1:] + ".", 150),
                 fontsize="small", loc="left")
    text = [[label, *row[1:]] for label, row in zip(wrapped, cells, strict=True)]
    header = [textwrap.fill(h, 14) for h in TABLE_HEADER]
    table = ax.table(cellText=text, colLabels=header, loc="upper center", cellLoc="right",
                     colLoc="center", colWidths=[0.38] + [0.124] * (len(header) - 1))
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    unit = 1.0 / (1.6 + sum(label.count("\n") + 1 for label in wrapped))
    for (r, col), cell in table.get_celld().items():
        lines = 1.6 if r == 0 else wrapped[r - 1].count("\n") + 1
        cell.set_height(unit * lines)
        cell.set_linewidth(0.5)
        if r == 0:
            cell.set_facecolor("0.92")
        elif col == 0:
            cell.get_text().set_horizontalalignment("left")
            cell.get_text().set_color(colours[r - 1])
            cell.PAD = 0.02


def _series(mode: str, report: dict, path: str) -> Series | Curve:
    """The series ``mode`` plots from ``report`` (read from ``path``).

    Raises
    ------
    InputError
        Naming ``path`` where a field is not what vastray writes (a report edited by hand).
    """
    try:
        return frame_series(report, path) if mode == "frames" else convergence_series(report, path)
    except (AttributeError, TypeError, KeyError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(path, f"is not a report as vastray writes it ({type(exc).__name__}: "
                               f"{exc}); was it edited?") from None


def run_plot(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.suffix.lower() != ".png":
        raise InputError(output, "-o needs a file name ending in .png")
    if output.is_dir():
        raise InputError(output, "-o is a folder; give a file name such as "
                                 f"{output / 'error_vs_time.png'}")
    if not output.absolute().parent.is_dir():  # never created: a typo would be
        raise InputError(output, f"-o's folder {output.parent} does not exist (create it "
                                 f"first, e.g. mkdir -p {output.parent})")
    reports = [load_report(path) for path in args.reports]
    mode = args.mode or default_mode(reports)
    series = [_series(mode, r, path) for r, path in zip(reports, args.reports, strict=True)]
    labels = [s.label for s in series]
    for s, path in zip(series, args.reports, strict=True):
        if labels.count(s.label) > 1:  # same scheduler and options: tell the runs apart
            s.label += f" ({Path(path).stem})"
    runs = f"{len(series)} run{'s' if len(series) > 1 else ''}"
    if mode == "frames":
        plot_error_vs_time(series, output, args.title or "error vs time per frame")
        points = sum(len(s.mse) for s in series)
    else:
        plot_convergence(series, output, args.title or "convergence: relMSE against time")
        print(markdown_table(table_rows(series)))
        points = sum(len(c.rel_mse) for c in series)
    print(f"wrote {output} ({mode}: {runs}, {points} point{'s' if points > 1 else ''})",
          file=sys.stderr)
    return 0
