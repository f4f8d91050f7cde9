"""What a new user hit (issue 42, part 4), the small things: help text, sizes and their units,
output folders, the frames plot's legend, a fixed colour range. The CLI in subprocesses where
the point is what a user sees."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys

import numpy as np
import pytest

from vastray.cli import build_parser
from vastray.preflight import check_limit_fits_machine, gigabytes, parse_size, physical_memory
from vastray.render.imageio import read_image
from vastray.scene.errors import InputError

VASTRAY = [sys.executable, "-m", "vastray.cli"]
SMALL = ["--width", "32", "--height", "24", "--spp", "2"]


def _cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([*VASTRAY, *args], capture_output=True, text=True, timeout=timeout)


def _parsers(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """Every (command words, parser) of the command line, nested sub-commands included."""
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, (*prefix, name))


def test_no_help_shows_an_argparse_escape():
    # `vastray render --help` showed "95%%": an argument group's description is not
    # %-formatted, so its escape reached the user
    commands = list(_parsers(build_parser()))
    assert len(commands) > 10
    for words, parser in commands:
        assert "%%" not in parser.format_help(), f"vastray {' '.join(words)} --help shows %%"
    for words in (["render"], ["launch"], ["node"], []):
        run = _cli(*words, "--help", timeout=120)
        assert run.returncode == 0, run.stderr
        assert "%%" not in run.stdout, f"vastray {' '.join(words)} --help shows %%"


def test_the_top_help_names_every_output_of_render():
    # `vastray --help` said render writes "to OpenEXR" only
    run = _cli("--help", timeout=120)
    assert run.returncode == 0, run.stderr
    text = " ".join(run.stdout.split())
    line = text[text.index("render render"):text.index("launch render")]
    assert "OpenEXR" not in line
    for word in (".exr", ".png", "PNG preview", "JSON report"):
        assert word in line, line


def test_sizes_are_read_and_printed_in_the_same_binary_units():
    # limits were read in GiB (powers of 1024) but printed in GB
    for text, shown in [("700M", "700 MiB"), ("6G", "6 GiB"), ("1.5GiB", "1.5 GiB"),
                        ("64K", "64 KiB"), ("1T", "1 TiB"), ("2TB", "2 TiB")]:
        assert gigabytes(parse_size(text)) == shown
    for bad in ("inf", "nan", "-1G", "0", "1X", ""):
        with pytest.raises(ValueError, match="size"):
            parse_size(bad)


def test_a_render_prints_its_memory_limit_as_given(tmp_path):
    run = _cli("render", "-o", str(tmp_path / "a.exr"), *SMALL, "--memory-limit", "700M")
    assert run.returncode == 0, run.stderr
    line = run.stderr.strip().splitlines()[-1]
    assert re.search(r"peak RSS [\d.]+ [MG]iB of --memory-limit 700 MiB", line), line


def test_a_memory_limit_beyond_this_machine_is_refused_in_one_line(tmp_path):
    # `--memory-limit 1T` (a typo for 1G) was accepted silently
    physical = physical_memory()
    if physical is None:
        pytest.skip("this machine's memory cannot be read")
    too_big = f"{physical // 2**30 + 2}G"
    limits = [too_big] + (["1T"] if physical < 2**40 else [])
    for limit in limits:
        run = _cli("render", "-o", str(tmp_path / "a.exr"), *SMALL, "--memory-limit", limit)
        assert run.returncode == 2, run.stderr
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
        assert f"--memory-limit {gigabytes(parse_size(limit))} is more than this machine's" \
               in lines[0], lines[0]
        assert not (tmp_path / "a.exr").exists()
    with pytest.raises(InputError, match="more than this machine's 8 GiB"):
        check_limit_fits_machine(9 * 2**30, physical=8 * 2**30)
    check_limit_fits_machine(8 * 2**30, physical=8 * 2**30)


@pytest.mark.parametrize("option", ["-o", "--png", "--report"])
def test_a_missing_output_folder_is_refused_naming_it_not_created(tmp_path, option):
    # `-o new/dir/out.exr` created new/dir silently: a typo in a folder name went unseen
    missing = tmp_path / "new" / "dir"
    name = {"-o": "out.exr", "--png": "out.png", "--report": "out.json"}[option]
    outputs = {"-o": str(tmp_path / "a.exr"), option: str(missing / name)}
    run = _cli("render", *SMALL, *[word for pair in outputs.items() for word in pair],
               timeout=300)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert f"{option}'s folder {missing} does not exist" in lines[0], lines[0]
    assert f"mkdir -p {missing}" in lines[0], lines[0]
    assert not (tmp_path / "new").exists() and not (tmp_path / "a.exr").exists()
    missing.mkdir(parents=True)  # once it exists, the same command renders
    run = _cli("render", *SMALL, *[word for pair in outputs.items() for word in pair], "--quiet",
               timeout=300)
    assert run.returncode == 0, run.stderr
    assert (missing / name).is_file()


def _frames_plot_boxes(monkeypatch, tmp_path, plot_module, series):
    """The window extents of the frames plot's legend and of its axis labels, taken from
    the figure as it is saved."""
    boxes = {}

    def save(fig, output):
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        (ax,) = fig.axes
        boxes["legend"] = ax.get_legend().get_window_extent(renderer)
        boxes["xlabel"] = ax.xaxis.label.get_window_extent(renderer)
        boxes["ylabel"] = ax.yaxis.label.get_window_extent(renderer)
        boxes["axes"] = ax.get_window_extent(renderer)
        boxes["figure"] = fig.bbox

    monkeypatch.setattr(plot_module, "_save", save)
    plot_module.plot_error_vs_time(series, tmp_path / "frames.png")
    return boxes


@pytest.mark.parametrize("runs", [1, 3, 6])
def test_the_frames_plot_legend_covers_no_axis_label(monkeypatch, tmp_path, runs):
    # the legend of `vastray plot --mode frames` sat inside the axes: with a few runs' long
    # labels (scheduler and options) it ran over the axis label
    pytest.importorskip("matplotlib")
    from vastray import plot

    label = ("async, --nodes 2, --cache 25%, --eviction demand, --max-samples-in-flight "
             "65536, --batch-size 4096")
    series = [plot.Series(f"{label} ({k})", [0.5 + 0.1 * k, 0.6 + 0.1 * k, 0.7],
                          [1e-3 * (k + 1), 2e-3, 0.0]) for k in range(runs)]
    boxes = _frames_plot_boxes(monkeypatch, tmp_path, plot, series)
    legend = boxes["legend"]
    for name in ("xlabel", "ylabel"):
        assert not legend.overlaps(boxes[name]), f"the legend covers the {name}"
    assert not legend.overlaps(boxes["axes"]), "the legend covers the points"
    figure = boxes["figure"]
    assert figure.x0 <= legend.x0 and legend.x1 <= figure.x1 + 1, "the legend is cut off"


@pytest.fixture(scope="module")
def scalar_stores(tmp_path_factory):
    """Two stores of one geometry and one scalar field, but for a single vertex of the second
    set to 5: their ranges differ (0.2..0.8 against 0.2..5), their other vertices do not."""
    from vastray.scene.store import DomainArrays

    from scenes import bumpy_scene, write_store

    folder = tmp_path_factory.mktemp("scalars")
    mesh = bumpy_scene()
    x = mesh.vertices[:, 0].astype(np.float64)
    scalars = (0.2 + 0.6 * (x - x.min()) / np.ptp(x)).astype(np.float32)
    outlier = scalars.copy()
    outlier[0] = 5.0
    stores = []
    for name, values in (("a", scalars), ("b", outlier)):
        arrays = DomainArrays(mesh.vertices, mesh.indices, scalars=values)
        stores.append(str(write_store(folder / f"{name}.store", arrays, grid=(2, 1, 1)).path))
    return stores


def _render(store: str, out, *extra: str) -> np.ndarray:
    run = _cli("render", store, "-o", str(out), *COLOR_SMALL, *extra, timeout=600)
    assert run.returncode == 0, run.stderr
    return read_image(out)


#: Ambient occlusion: a surface's colour is its own scalar's, no light bounced off another.
COLOR_SMALL = ["--width", "48", "--height", "32", "--spp", "2", "--integrator", "ao",
               "--shadow-samples", "2"]


def test_a_fixed_color_range_colours_a_scalar_alike_whatever_the_data_range(
        scalar_stores, tmp_path):
    a, b = scalar_stores
    own_a, own_b = _render(a, tmp_path / "a.exr"), _render(b, tmp_path / "b.exr")
    fixed_a = _render(a, tmp_path / "fa.exr", "--color-range", "0", "1")
    fixed_b = _render(b, tmp_path / "fb.exr", "--color-range", "0", "1")
    surface = np.abs(own_a - own_a[0, 0]).sum(axis=2) > 1e-6  # not the background
    assert surface.mean() > 0.05

    def differing(x, y):
        return float((np.abs(x - y).sum(axis=2) > 1e-6)[surface].mean())

    # each store's own range: the outlier rescales the whole second image
    assert differing(own_a, own_b) > 0.5
    # one range for both: only pixels that see the outlier's triangles differ
    assert differing(fixed_a, fixed_b) < 0.05
    assert differing(own_a, fixed_a) > 0.5  # the range changed the colours


def test_a_fixed_color_range_reaches_the_nodes(scalar_stores, tmp_path):
    _, b = scalar_stores
    one = _render(b, tmp_path / "one.exr", "--color-range", "0", "1")
    for scheduler in ("image", "async"):
        nodes = _render(b, tmp_path / f"{scheduler}.exr", "--color-range", "0", "1",
                        "--nodes", "2", "--scheduler", scheduler)
        np.testing.assert_allclose(nodes, one, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("words", "named"), [
    (["2", "1"], "--color-range LO HI needs LO < HI, got 2 1"),
    (["1", "1"], "--color-range LO HI needs LO < HI, got 1 1"),
    (["0", "nan"], "must be a finite number"),
    (["-1", "inf"], "must be a finite number"),
    (["0", "x"], "expected a number"),
])
def test_a_bad_color_range_is_refused_in_one_line(scalar_stores, tmp_path, words, named):
    run = _cli("render", scalar_stores[0], "-o", str(tmp_path / "x.exr"), *COLOR_SMALL,
               "--color-range", *words, timeout=120)
    assert run.returncode == 2 and named in run.stderr, run.stderr
    assert "Traceback" not in run.stderr and not (tmp_path / "x.exr").exists()
    assert run.stderr.strip().splitlines()[0].count("--color-range") >= 1


def test_the_python_api_takes_a_color_range_as_a_pair(scalar_stores, tmp_path):
    import vastray
    from vastray.scene.errors import InputError

    _, b = scalar_stores
    cli = _render(b, tmp_path / "cli.exr", "--color-range", "0", "1")
    out = vastray.render(b, width=48, height=32, spp=2, integrator="ao", shadow_samples=2,
                         color_range=(0.0, 1.0), progress=False)
    np.testing.assert_array_equal(out.image, cli)
    with pytest.raises(InputError, match="color_range takes 2 values"):
        vastray.render(b, width=48, height=32, spp=2, color_range=1.0, progress=False)
