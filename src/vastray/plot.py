"""``vastray plot``: error against time of several runs, from their reports, as a PNG.

Each report is a single render's (``vastray render --report`` with ``--reference``) or an
animation's summary (``--frames N --report``): every frame with an error is one point (seconds
of that frame, MSE against its lossless reference), and each run is one labelled series, its
scheduler and options, with a larger marker at its mean. matplotlib is an optional extra
(``pip install vastray[plot]``), imported only here.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

from vastray.render.imageio import atomic_path
from vastray.report import run_label
from vastray.scene.errors import InputError

log = logging.getLogger(__name__)

PLOT_EPILOG = """\
example:
  vastray render rm.store -o ref.exr --scene orbit.toml --frames 8 --spp 64
  vastray render rm.store -o a.exr --scene orbit.toml --frames 8 --spp 4 \\
      --reference ref.exr --report a.json              # ref.exr: ref_0000.exr ...
  vastray render rm.store -o b.exr --scene orbit.toml --frames 8 --spp 16 \\
      --cache 25% --scheduler spec-ooc --reference ref.exr --report b.json
  vastray plot a.json b.json -o error_vs_time.png

Reports of single renders made with --reference work too (one point each). A run whose MSE is
0 (a lossless run against its own reference) is drawn on the plot's floor.
"""


@dataclass
class Series:
    """One run's points: seconds per frame and MSE against the reference, by frame."""

    label: str
    seconds: list[float]
    mse: list[float]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plot", help="plot error vs time per frame of several runs (PNG)",
        description="Plot the MSE against the time per frame of several runs, read from\n"
                    "their JSON reports (single renders or --frames summaries, made with\n"
                    "--reference), one labelled series per run: its scheduler and options.\n"
                    "Needs matplotlib: pip install vastray[plot].",
        epilog=PLOT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reports", nargs="+", metavar="REPORT.json",
                   help="reports of `vastray render --report`")
    p.add_argument("-o", "--output", required=True, help="PNG file to write")
    p.add_argument("--title", default="error vs time per frame", help="the plot's title")
    p.set_defaults(func=run_plot)


def load_series(path: str | Path) -> Series:
    """The points of one report (a summary's frames, or a single render).

    Raises
    ------
    InputError
        When the file is not a vastray report or holds no error (made without --reference).
    """
    path = Path(path)
    try:
        report = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "report not found") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"not a JSON report ({exc})") from None
    if not isinstance(report, dict) or "scheduler" not in report:
        raise InputError(path, "not a vastray render report (no scheduler)")
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


def plot_error_vs_time(series: list[Series], output: str | Path,
                       title: str = "error vs time per frame") -> None:
    """Write the plot of ``series`` as a PNG: seconds per frame on x, MSE (log) on y."""
    try:
        import matplotlib
    except ImportError:
        raise InputError(None, "plotting needs matplotlib: pip install vastray[plot]") from None
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    positive = [m for s in series for m in s.mse if m > 0]
    floor = min(positive) / 10.0 if positive else 1e-12
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    try:
        for s in series:
            lossless = all(m == 0 for m in s.mse)
            mse = [max(m, floor) for m in s.mse]
            label = s.label + (" (MSE 0, drawn on the floor)" if lossless else "")
            (points,) = ax.plot(s.seconds, mse, "o", alpha=0.5, markersize=4)
            mean_t, mean_mse = sum(s.seconds) / len(s.seconds), max(sum(s.mse) / len(s.mse), floor)
            ax.plot([mean_t], [mean_mse], "v" if lossless else "D", markersize=9,
                    color=points.get_color(), markeredgecolor="black", label=label)
        ax.set_yscale("log")
        ax.set_xlabel("seconds per frame")
        ax.set_ylabel("MSE against the lossless render")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
        fig.tight_layout()
        with atomic_path(output) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)


def run_plot(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.suffix.lower() != ".png":
        raise InputError(output, "-o needs a file name ending in .png")
    if output.is_dir():
        raise InputError(output, "-o is a folder; give a file name such as "
                                 f"{output / 'error_vs_time.png'}")
    series = [load_series(path) for path in args.reports]
    labels = [s.label for s in series]
    for s, path in zip(series, args.reports, strict=True):
        if labels.count(s.label) > 1:  # same scheduler and options: tell the runs apart
            s.label += f" ({Path(path).stem})"
    plot_error_vs_time(series, output, args.title)
    print(f"wrote {output} ({len(series)} run{'s' if len(series) > 1 else ''}, "
          f"{sum(len(s.mse) for s in series)} points)", file=sys.stderr)
    return 0
