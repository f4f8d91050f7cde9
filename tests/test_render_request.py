"""``RenderRequest`` (src/vastray/request.py): the one typed, checked value of a render that
the command line parses into and the Python API builds without any command line; the
options' defaults and refusals are its own, so both give the same request and the same
refusal."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest

import vastray
from vastray.api import render_request
from vastray.cli import build_parser, main
from vastray.request import OPTIONS, STORE_DEFAULTS, RenderRequest
from vastray.scene.errors import InputError

from scenes import bumpy_scene, write_store

SMALL = {"width": 32, "height": 24, "spp": 2}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("request") / "s.store", bumpy_scene(),
                       grid=(2, 2, 1))


def cli_request(*argv: str) -> RenderRequest:
    """The request ``vastray render ARGV`` parses into."""
    return RenderRequest.from_namespace(build_parser().parse_args(["render", *map(str, argv)]))


def api_request(store=None, **kwargs) -> RenderRequest:
    """The request ``vastray.render(store, **kwargs)`` builds."""
    return render_request(store, kwargs)[0]


def test_the_api_renders_without_building_any_argparse_object(store, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("vastray.render built an argparse object")

    monkeypatch.setattr(argparse.ArgumentParser, "__init__", refuse)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", refuse)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", refuse)
    monkeypatch.setattr(argparse.Namespace, "__init__", refuse)
    out = vastray.render(store.path, cache=2, progress=False, **SMALL)
    assert out.image.shape == (24, 32, 3)
    assert out.report["scheduler"] == "spec-ooc"


def test_the_cli_and_the_api_build_equal_requests_for_the_same_options(store):
    cli = cli_request(store.path, "-o", "x.exr", "--width", "32", "--height", "24", "--spp",
                      "2", "--cache", "25%", "--scheduler", "spec-ooc", "--history-depth", "2",
                      "--load-bandwidth", "200,100", "--memory-limit", "700M", "--color-range",
                      "0", "1.5", "--no-preload", "--eviction", "demand", "--time-limit", "3",
                      "--quiet")
    api = api_request(store.path, width=32, height=24, spp=2, cache="25%",
                      scheduler="spec-ooc", history_depth=2, load_bandwidth=[200, 100],
                      memory_limit="700M", color_range=(0, 1.5), no_preload=True,
                      eviction="demand", time_limit=3, progress=False)
    assert dataclasses.replace(cli, output=None) == api
    assert api.memory_limit == 700 * 2**20 and api.load_bandwidth == [200.0, 100.0]
    assert cli.argv is None and cli.camera is None  # main() adds the typed arguments
    # and with nothing given, both are the request's own defaults
    assert dataclasses.replace(cli_request("-o", "x.exr"), output=None) == api_request() \
        == RenderRequest(quiet=False)


def test_every_option_of_the_command_line_is_a_field_with_the_parsers_default():
    parser = build_parser().subcommands.choices["render"]
    dests = {action.dest: action for action in parser._actions if action.dest != "help"}
    assert set(dests) == set(OPTIONS)
    for name, action in dests.items():
        assert action.default == RenderRequest.field_default(name), name


@pytest.mark.parametrize(("argv", "kwargs", "message"), [
    (["--ao-distance", "0.1"], {"ao_distance": 0.1},
     "--ao-distance is the ambient-occlusion ray length: it applies to --integrator ao only"),
    (["--node-timeout", "5"], {"node_timeout": 5},
     "--node-timeout applies to node processes: give --nodes N with it, or drop it"),
    (["--integrator", "ao", "--bounces", "2"], {"integrator": "ao", "bounces": 2},
     "--bounces counts path-tracing bounces: --integrator ao traces one hit per path (use "
     "--integrator pt, or drop --bounces)"),
    (["--cache", "2", "--scheduler", "reference", "--history-depth", "1"],
     {"cache": 2, "scheduler": "reference", "history_depth": 1},
     "--history-depth applies to the out-of-core schedulers; this render is the in-core "
     "reference (every domain fits in --cache): give --scheduler image or spec-ooc with a "
     "smaller --cache, or drop it"),
])
def test_a_refused_option_gets_the_same_refusal_from_the_cli_and_the_api(
        store, tmp_path, capsys, argv, kwargs, message):
    assert main(["render", str(store.path), "-o", str(tmp_path / "o.exr"), *argv,
                 "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == f"vastray render: error: {message}"
    with pytest.raises(InputError) as caught:
        vastray.render(store.path, progress=False, **SMALL, **kwargs)
    assert str(caught.value) == message
    assert not list(tmp_path.iterdir())


def test_a_bad_value_is_refused_by_the_options_own_converter_from_both(store, tmp_path,
                                                                       capsys):
    with pytest.raises(SystemExit) as exit:  # argparse's refusal
        main(["render", str(store.path), "-o", str(tmp_path / "o.exr"), "--spp", "0"])
    assert exit.value.code == 2
    assert "argument --spp: must be at least 1, got 0" in capsys.readouterr().err
    with pytest.raises(InputError, match="^spp=0: must be at least 1, got 0$"):
        vastray.render(store.path, spp=0)
    with pytest.raises(InputError, match="^spp=0: must be at least 1, got 0$"):
        RenderRequest(spp=0)  # made directly, the request checks itself
    with pytest.raises(InputError, match="^scheduler='fast': choose from auto, reference"):
        RenderRequest(scheduler="fast")
    with pytest.raises(InputError, match="^quiet must be True or False, got 1$"):
        RenderRequest(quiet=1)


def test_resolved_fills_in_the_store_or_built_in_defaults_and_names_what_was_given():
    given = RenderRequest(store="s.store", output="o.exr", spp=16)
    full = given.resolved()
    assert (full.width, full.height, full.spp, full.bounces) == (
        STORE_DEFAULTS["width"], STORE_DEFAULTS["height"], 16, STORE_DEFAULTS["bounces"])
    assert full.exposure == 1.0 and full.node_timeout == 120.0
    assert full.given == {"store", "output", "spp"}
    assert full.resolved() is full
    assert RenderRequest().resolved().width == 640  # the built-in scene's
    # a request with defaults filled in is not refused for them (--node-timeout without
    # --nodes), and the one it came from is unchanged
    assert given.node_timeout is None and dataclasses.replace(full, seed=3).seed == 3


def test_a_reference_array_and_a_camera_travel_in_the_request(store):
    reference = np.zeros((24, 32, 3), np.float32)
    request = api_request(store.path, reference=reference, camera={"fov": 20}, **SMALL)
    assert request.reference is not None and request.reference.shape == (24, 32, 3)
    assert request.camera == {"fov": 20}
