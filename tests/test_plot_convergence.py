"""``vastray plot`` convergence mode (issue 22): relMSE per pass against time, the
time-to-error table and efficiency, from reports with a ``passes`` list."""

from __future__ import annotations

import itertools
import json
import math

import pytest

from vastray.cli import main
from vastray.convergence import (
    Curve,
    convergence_series,
    efficiency,
    markdown_table,
    table_rows,
    time_to_error,
)
from vastray.scene.errors import InputError


def one_pass(index, seconds, spp, rel_mse=None, estimated=None):
    return {"pass": index, "seconds": seconds, "spp": spp,
            "mse": None if rel_mse is None else rel_mse / 10, "rel_mse": rel_mse,
            "rel_mse_global": None, "psnr_db": None, "variance_of_mean": None,
            "estimated_rel_mse": estimated, "mean_radiance": 0.2, "ci95": None}


def render_report(passes, scheduler="image", spp=4, **options):
    return {"scheduler": scheduler, "options": options, "settings": {"spp": spp},
            "stopped_by": "spp", "passes": passes,
            "seconds": {"total": passes[-1]["seconds"] if passes else 0.0}}


def write(tmp_path, name, doc):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return str(path)


# --- the arithmetic, against hand-computed numbers ---------------------------------------

def test_time_to_error_interpolates_in_log_log_between_the_bracketing_passes():
    seconds, rel = [1.0, 2.0, 4.0], [0.4, 0.2, 0.05]
    # 0.1 lies between (2 s, 0.2) and (4 s, 0.05): slope ln2/ln(1/4) = -1/2 in log-log,
    # so t = 2 * (0.1/0.2)^(-1/2) = 2 * sqrt(2)
    assert time_to_error(seconds, rel, 0.1) == pytest.approx(2 * math.sqrt(2))
    assert time_to_error(seconds, rel, 0.2) == pytest.approx(2.0)  # reached exactly at a pass
    assert time_to_error(seconds, rel, 0.5) == 1.0  # the first pass is already below
    assert time_to_error(seconds, rel, 0.01) is None  # never reached
    # an exact 1/t run (relMSE = 1/t) crosses 0.3 at t = 1/0.3
    assert time_to_error([1.0, 10.0], [1.0, 0.1], 0.3) == pytest.approx(1 / 0.3)


def test_time_to_error_takes_the_first_crossing_and_a_zero_error_as_it_is():
    # 0.5 -> 0.05 (crossing 0.1) then back up to 0.2: the first crossing counts,
    # t = 2^(ln(0.1/0.5)/ln(0.05/0.5)) = 2^(log10 5)
    assert time_to_error([1.0, 2.0, 3.0], [0.5, 0.05, 0.2], 0.1) == \
        pytest.approx(2 ** math.log10(5))
    # an error of 0 has no logarithm: the time of the pass that reached it
    assert time_to_error([1.0, 2.0], [0.5, 0.0], 0.1) == 2.0


def test_efficiency_is_one_over_error_times_seconds():
    assert efficiency(4.0, 0.05) == pytest.approx(5.0)
    assert efficiency(2.0, 0.0) == math.inf
    with pytest.raises(ValueError, match="seconds > 0"):
        efficiency(0.0, 0.1)


def test_the_table_has_a_row_per_run_in_markdown():
    curves = [Curve("image --spp 4", [1.0, 2.0, 4.0], [0.4, 0.2, 0.05]),
              Curve("async --spp 4 --nodes 2", [1.0, 2.0], [0.3, 0.2], estimated=True),
              Curve("image --spp 4 --cache 2", [0.5, 1.0], [0.0, 0.0])]
    rows = table_rows(curves)
    assert rows[0].to_threshold == [pytest.approx(2 * math.sqrt(2)), None, None]
    assert rows[0].efficiency == pytest.approx(5.0)
    table = markdown_table(rows).splitlines()
    assert "log-log interpolation" in table[0]
    assert table[2] == ("| run | s to ≤1e-1 | s to ≤1e-2 | s to ≤1e-3 | final relMSE "
                        "| 1/(relMSE·t) (1/s) |")
    assert table[4] == "| image --spp 4 | 2.83 | — | — | 0.05 | 5 |"
    assert table[5] == "| async --spp 4 --nodes 2 (estimated) | — | — | — | 0.2 | 2.5 |"
    assert table[6] == "| image --spp 4 --cache 2 | 0.5 | 0.5 | 0.5 | 0 | ∞ (relMSE 0) |"


# --- reading a report ----------------------------------------------------------------

def test_convergence_series_uses_rel_mse_and_skips_null_passes():
    report = render_report([one_pass(0, 0.0, 0, 0.9), one_pass(1, 0.5, 1, 0.8),
                            one_pass(2, 1.0, 2, None, 0.3), one_pass(3, None, 3, 0.25),
                            one_pass(4, 2.0, 4, 0.2, 0.25)], nodes=2, cache=4)
    curve = convergence_series(report)
    assert (curve.seconds, curve.rel_mse, curve.estimated) == ([0.5, 2.0], [0.8, 0.2], False)
    assert curve.label == "image --spp 4 --nodes 2 --cache 4"


def test_convergence_series_without_a_reference_uses_the_estimate():
    report = render_report([one_pass(0, 0.5, 1), one_pass(1, 1.0, 2, None, 0.3),
                            one_pass(2, 2.0, 4, None, 0.15)])
    curve = convergence_series(report)
    assert (curve.seconds, curve.rel_mse, curve.estimated) == ([1.0, 2.0], [0.3, 0.15], True)


@pytest.mark.parametrize("doc, message", [
    ({"scheduler": "image", "frames": []}, "animation summary (per-frame reports): plot it "
                                           "with --mode frames"),
    ({"scheduler": "image", "seconds": {"total": 1.0}}, "has no passes list"),
    (render_report([one_pass(0, 0.5, 1)]), "none of its 1 passes has an error: render with "
                                           "--reference"),
])
def test_convergence_series_refuses_what_it_cannot_draw(doc, message):
    with pytest.raises(InputError, match="^r.json: ") as info:
        convergence_series(doc, "r.json")
    assert message in str(info.value)


# --- the CLI, end to end -------------------------------------------------------------

def runs(tmp_path, count):
    """``count`` synthetic reports: 1/t-like runs with long labels, one without a reference
    and one lossless."""
    paths = []
    for i in range(count):
        speed = 0.02 * (i + 1)
        passes = [one_pass(k, 0.1 + speed * s, s, None if i == 2 else 1.0 / (s * (i + 1)),
                           None if s == 1 else 0.9 / (s * (i + 1)))
                  for k, s in enumerate([1, 2, 4, 8, 16, 32])]
        if i == 5:
            passes = [dict(p, rel_mse=0.0) for p in passes]
        options = {"nodes": 4, "cache": 25, "simplified": "portal",
                   "assignment": "spatial", "priority": "queue"} if i % 2 else {"cache": i}
        paths.append(write(tmp_path, f"run{i}.json",
                           render_report(passes, ["image", "temporal"][i % 2], 32, **options)))
    return paths


def png_size(path):
    from PIL import Image

    with Image.open(path) as image:
        return image.size


def test_plot_draws_convergence_and_prints_the_table(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="vastray[plot] (matplotlib) is not installed")
    paths, out = runs(tmp_path, 3), tmp_path / "c.png"
    assert main(["plot", *paths, "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "wrote" in captured.err and "convergence: 3 runs, 17 points" in captured.err
    lines = captured.out.splitlines()
    assert lines[2].startswith("| run | s to ≤1e-1")
    # run0: relMSE 1/spp at 0.1 + 0.02 spp seconds: 0.125 at 0.26 s, 0.0625 at 0.42 s, so
    # 0.1 at 0.26 * (0.42/0.26)^(ln 0.8 / ln 0.5) = 0.303 s; 1/(0.03125 * 0.74 s) = 43.2/s
    assert lines[4] == "| image --spp 32 --cache 0 | 0.303 | — | — | 0.0312 | 43.2 |"
    assert "(estimated)" in lines[6]  # run2 has no reference
    assert len(lines) == 7
    one = tmp_path / "one.png"
    assert main(["plot", paths[0], "-o", str(one)]) == 0
    # the table grows under the plot, a row per run
    (width, height), (width_one, height_one) = png_size(out), png_size(one)
    assert height > height_one and width == width_one
    # the same run twice: its file names tell the rows apart
    twin = write(tmp_path, "twin.json", json.loads((tmp_path / "run0.json").read_text()))
    capsys.readouterr()
    assert main(["plot", paths[0], twin, "-o", str(one)]) == 0
    rows = capsys.readouterr().out.splitlines()[4:]
    assert [r.split(" | ")[0] for r in rows] == ["| image --spp 32 --cache 0 (run0)",
                                                 "| image --spp 32 --cache 0 (twin)"]


@pytest.mark.parametrize("count", [1, 3, 6])
def test_convergence_figure_text_does_not_overlap(tmp_path, count):
    pytest.importorskip("matplotlib", reason="vastray[plot] (matplotlib) is not installed")
    from matplotlib import pyplot as plt
    from matplotlib.text import Text

    from vastray.plot import convergence_figure, load_report

    curves = [convergence_series(load_report(p), p) for p in runs(tmp_path, count)]
    fig = convergence_figure(curves)
    try:
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        plot_sub, table_sub = fig.subfigs
        ax = plot_sub.axes[0]
        legend = ax.get_legend().get_window_extent(renderer)
        axes = ax.get_tightbbox(renderer, bbox_extra_artists=[])  # ticks, labels, title
        table = table_sub.axes[0].tables[0].get_window_extent(renderer)
        table_ax = table_sub.axes[0]
        assert table_ax.get_title(loc="left").startswith("Seconds to reach relMSE")
        (caption,) = [t.get_window_extent(renderer) for t in table_ax.get_children()
                      if isinstance(t, Text) and t.get_text() == table_ax.get_title(loc="left")]
        page = fig.bbox
        for box in (legend, axes, table, caption):
            assert page.x0 - 1 <= box.x0 and box.x1 <= page.x1 + 1, box
            assert page.y0 - 1 <= box.y0 and box.y1 <= page.y1 + 1, box
        assert legend.x0 >= ax.get_window_extent(renderer).x1  # right of the axes
        assert table.y1 <= caption.y0 < caption.y1 < min(axes.y0, legend.y0)  # under the plot
        frame = ax.get_window_extent(renderer)
        for axis, lo, hi in ((ax.xaxis, 0, 2), (ax.yaxis, 1, 3)):  # tick labels apart
            extents = [t.get_window_extent(renderer).extents for t in axis.get_ticklabels(
                which="both") if t.get_visible() and t.get_text()]
            boxes = sorted((e[lo], e[hi]) for e in extents  # those drawn: beside the frame
                           if frame.extents[lo] - 1 <= (e[lo] + e[hi]) / 2
                           <= frame.extents[hi] + 1)
            assert len(boxes) >= 2
            assert all(a[1] <= b[0] for a, b in itertools.pairwise(boxes)), boxes
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert labels[-1] == "1/t (reference slope)" and len(labels) == count + 1
        if count == 6:
            assert "(estimated, no reference)" in labels[2]
            assert " ".join(labels[5].split()).endswith("(relMSE 0, drawn on the floor)")
            assert max(len(line) for t in labels for line in t.split("\n")) <= 34
    finally:
        plt.close(fig)


def test_slope_line_runs_through_the_curves():
    from vastray.plot import slope_anchor

    # relMSE·t is 2, 2 and 8 at the positive points: the constant is their geometric mean
    assert slope_anchor([Curve("a", [1.0, 2.0], [2.0, 1.0]), Curve("b", [4.0], [2.0]),
                         Curve("c", [1.0], [0.0])]) == pytest.approx(32 ** (1 / 3))
    assert slope_anchor([Curve("c", [1.0], [0.0])]) is None


def test_mode_follows_the_reports_and_can_be_forced(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="vastray[plot] (matplotlib) is not installed")
    single = render_report([one_pass(0, 0.5, 1, 0.4), one_pass(1, 1.0, 2, 0.2)])
    single["error"] = {"mse": 0.02, "rel_mse": 0.2}
    single_path = write(tmp_path, "single.json", single)
    summary_path = write(tmp_path, "anim.json", {
        "scheduler": "temporal", "options": {}, "settings": {"spp": 2},
        "frames": [{"frame": 0, "seconds": {"total": 1.0}, "error": {"mse": 0.01}}]})
    out = tmp_path / "p.png"
    # a summary among the reports: frames, a single render as one point
    assert main(["plot", single_path, summary_path, "-o", str(out)]) == 0
    assert "(frames: 2 runs, 2 points)" in capsys.readouterr().err
    assert main(["plot", single_path, "-o", str(out), "--mode", "frames"]) == 0
    captured = capsys.readouterr()
    assert "(frames: 1 run, 1 point)" in captured.err and captured.out == ""
    out.unlink()
    assert main(["plot", single_path, summary_path, "-o", str(out), "--mode",
                 "convergence"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"vastray plot: error: {summary_path}: is an animation summary (per-frame "
                   "reports): plot it with --mode frames")
    assert not out.exists()


def test_reports_that_cannot_be_drawn_say_what_to_run_again(tmp_path, capsys):
    no_error = write(tmp_path, "noref.json", render_report([one_pass(0, 0.4, 1)]))
    old = write(tmp_path, "old.json", {"scheduler": "image", "seconds": {"total": 1.0},
                                       "error": {"mse": 0.1}})
    out = tmp_path / "x.png"
    for path, expect in ((no_error, "render with --reference, or with --spp 2 or more"),
                         (old, "has no passes list")):
        assert main(["plot", path, "-o", str(out), "--mode", "convergence"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"vastray plot: error: {path}: ") and expect in err, err
        assert len(err.splitlines()) == 1
    assert not out.exists()
    assert main(["plot", no_error, "-o", str(out)]) == 2  # convergence, the default for it
    assert "none of its 1 passes has an error" in capsys.readouterr().err
    # a report from before renders ran in passes still plots as one point (frames mode)
    pytest.importorskip("matplotlib", reason="vastray[plot] (matplotlib) is not installed")
    assert main(["plot", old, "-o", str(out)]) == 0
    assert "(frames: 1 run, 1 point)" in capsys.readouterr().err
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("case", ["options_a_string", "frames_not_reports", "negative_error",
                                  "missing_folder"])
def test_a_hand_edited_report_or_a_missing_folder_is_one_line_not_a_traceback(tmp_path, capsys,
                                                                               case):
    """Reports edited by hand once ended ``vastray plot`` in tracebacks (an AttributeError in
    the run's label, a TypeError in an animation summary's frames) or were drawn with a
    negative error; ``-o`` in a missing folder created it."""
    good = render_report([one_pass(0, 0.5, 1, 0.4), one_pass(1, 1.0, 2, 0.2)])
    doc = {"options_a_string": {**good, "options": "x"},
           "frames_not_reports": {"scheduler": "image", "frames": [1, 2]},
           "negative_error": render_report([one_pass(0, 0.5, 1, -1.0)]),
           "missing_folder": good}[case]
    path = write(tmp_path, "r.json", doc)
    out = tmp_path / ("missing" if case == "missing_folder" else ".") / "p.png"
    assert main(["plot", path, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray plot: error: ") and len(err.splitlines()) == 1, err
    says = {"missing_folder": "-o's folder", "negative_error": "negative rel_mse"}.get(
        case, "is not a report as vastray writes it")
    assert says in err
    assert not out.exists() and not (tmp_path / "missing").exists()
