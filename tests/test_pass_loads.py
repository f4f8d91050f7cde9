"""Progressive passes out of core cost no extra domain loads (issue 40).

Out of core, each pass that sweeps the domains again reloads what the cache lost: the CLI
renders in one pass where nothing reads the image between passes, nodes keep their cache
from pass to pass, and unpaced passes on nodes run on from one into the next in one sweep
of tiles (as one process does)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import vastray
from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.progressive import Progression, StopRules
from vastray.render.scene_config import SceneConfig, load_scene_config

from scenes import POINT_AND_SKY_TOML, bumpy_scene, rm_store, settings, write_store

W, H, SPP = 48, 32, 8
# MB/s: storage slow enough that loads take most of the time even beside busy processes (at
# 1 MB/s, with three busy loops beside it, the traces slowed until loads no longer dominated
# and the later passes stopped riding: 190-196 loads against 135)
LOADS_TAKE_THE_TIME = 0.5


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("passes") / "kd16", bumpy_scene(), kd=16)


@pytest.fixture(scope="module")
def toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("passes-scene") / "scene.toml"
    path.write_text(POINT_AND_SKY_TOML)
    return path


@pytest.fixture(scope="module")
def config(toml):
    return load_scene_config(toml)


def quarter(store) -> int:
    return max(1, len(store.domains) // 4)


def one_pass(store, config, scheduler: str, tile: int | None):
    st = settings(width=W, height=H, spp=SPP, integrator="pt", bounces=3)
    return render_out_of_core(store, config, st, JobOptions(
        scheduler=scheduler, cache=quarter(store), max_samples_in_flight=tile), progress=False)


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_the_cli_renders_out_of_core_in_one_pass_with_the_loads_of_one(store, config, toml,
                                                                        scheduler):
    tile = W * H * SPP // 3  # several tiles: a pass sweeping the whole image costs more
    one = one_pass(store, config, scheduler, tile)
    out = vastray.render(store, scene=toml, width=W, height=H, spp=SPP, seed=7,
                         integrator="pt", bounces=3, shadow_samples=4, scheduler=scheduler,
                         cache=quarter(store), max_samples_in_flight=tile, progress=False)
    assert len(out.report["passes"]) == 1
    assert out.report["counters"]["loads"] <= 1.1 * one.counters["loads"]
    np.testing.assert_allclose(out.image, one.film.image(), rtol=1e-6, atol=1e-7)
    # asked for its passes, the same render keeps them and pays for them
    kept = vastray.render(store, scene=toml, width=W, height=H, spp=SPP, seed=7,
                          integrator="pt", bounces=3, shadow_samples=4, scheduler=scheduler,
                          cache=quarter(store), max_samples_in_flight=tile, max_pass_spp=16,
                          progress=False)
    assert len(kept.report["passes"]) == 4  # 1, 1, 2, 4 spp
    assert kept.report["counters"]["loads"] > out.report["counters"]["loads"]
    # the same samples, summed in one pass instead of four
    np.testing.assert_allclose(out.image, kept.image, rtol=1e-6, atol=1e-7)


def test_in_core_renders_keep_their_passes(store, toml):
    out = vastray.render(store, scene=toml, width=W, height=H, spp=SPP, seed=7,
                         integrator="pt", bounces=3, shadow_samples=4, scheduler="spec-ooc", progress=False)
    assert len(out.report["passes"]) == 4


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_unpaced_passes_on_two_nodes_cost_the_loads_of_one_pass(store, config, toml,
                                                                 scheduler):
    st = settings(width=W, height=H, spp=SPP, integrator="pt", bounces=3)
    options = JobOptions(scheduler=scheduler, cache=quarter(store),
                         max_samples_in_flight=W * H * SPP // 2, threads=1)
    one = render_distributed(store.path, toml, st, 2, options)
    passes = render_distributed(store.path, toml, st, 2, options,
                                progression_of=lambda frame: Progression(W, H, StopRules(SPP)))
    assert len(passes.progress["passes"]) == 4
    assert passes.counters["loads"] <= 1.1 * one.counters["loads"]
    reference = render_out_of_core(store, config, st, options, progress=False,
                                   progression=Progression(W, H, StopRules(SPP)))
    np.testing.assert_array_equal(passes.film.image(), reference.film.image())


@pytest.fixture(scope="module")
def rm(tmp_path_factory):
    """rm 48^3 in 5x5x4 grid domains (52 with triangles): the image's top and bottom halves
    show different domains, as on a real store."""
    return rm_store(tmp_path_factory.mktemp("passes-rm") / "rm.store", 48, (5, 5, 4))


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_kept_passes_on_two_nodes_cost_the_loads_of_one_pass_with_the_nodes_tile(rm,
                                                                                   scheduler):
    """Passes kept (a checkpoint or --max-pass-spp wants them) but unpaced, on 2 nodes with
    the nodes' own tile, as `vastray render --nodes 2` runs them: each node sweeps its part of
    every pass, the same part of the image, so the sweep loads what one pass loads. When the
    sweep was cut as one frame, one node traced the first passes' whole images and the other
    the last's: 1.4-1.8x the loads here (``bench/ooc.py --quick``: 1.46-1.51x)."""
    w, h, spp = 32, 24, 8
    st = settings(width=w, height=h, spp=spp, integrator="ao", bounces=1)
    options = JobOptions(scheduler=scheduler, cache=-(-len(rm.domains) // 4), threads=1)
    one = render_distributed(rm.path, None, st, 2, options)
    passes = render_distributed(rm.path, None, st, 2, options,
                                progression_of=lambda frame: Progression(w, h, StopRules(spp)))
    assert len(passes.progress["passes"]) == 4
    assert passes.counters["loads"] <= 1.1 * one.counters["loads"], (
        passes.counters["loads"], one.counters["loads"])
    reference = render_out_of_core(rm, SceneConfig(), st, options, progress=False,
                                   progression=Progression(w, h, StopRules(spp)))
    np.testing.assert_array_equal(passes.film.image(), reference.film.image())

def test_a_node_keeps_its_cache_from_pass_to_pass(store, toml):
    """Paced passes (a rule may stop between them) are rendered one by one, but what a node
    holds stays: with every domain cached, each is loaded once for all the passes (a cache
    rebuilt per pass loaded them again in each)."""
    st = settings(width=W, height=H, spp=SPP, integrator="pt", bounces=3)
    options = JobOptions(scheduler="spec-ooc", threads=1)  # every domain fits
    result = render_distributed(
        store.path, toml, st, 2, options,
        progression_of=lambda frame: Progression(W, H, StopRules(SPP, time_limit=3600.0)))
    assert len(result.progress["passes"]) == 4
    assert result.counters["loads"] <= 2 * len(store.domains)  # at most once per node


@pytest.mark.parametrize("nodes", [None, 2])
def test_passes_measured_against_a_reference_end_apart(store, toml, nodes):
    """Issue 41: with a reference the error of each pass is wanted as it ends, so passes are
    rendered apart (a curve of error against time, not one point at the end of one sweep)."""
    st = settings(width=W, height=H, spp=SPP, integrator="pt", bounces=3)
    reference = np.full((H, W, 3), 0.2, np.float32)
    options = JobOptions(scheduler="spec-ooc", cache=quarter(store), threads=1)
    progression = Progression(W, H, StopRules(SPP), reference)
    if nodes is None:
        render_out_of_core(store, load_scene_config(toml), st, options, progress=False,
                           progression=progression)
    else:
        render_distributed(store.path, toml, st, nodes, options,
                           progression_of=lambda frame: progression)
    seconds = [p["seconds"] for p in progression.series]
    assert len(seconds) == 4 and seconds == sorted(seconds), seconds
    # out of core the next pass is traced ahead, on the current one's loads
    # (``SortFirstTiles.render_ahead``), on nodes too: the first pass still ends well before
    # the last (passes merged together at the end of one sweep end within a millisecond)
    assert seconds[3] - seconds[0] > 0.25 * seconds[3], seconds


def test_a_node_sweeps_passes_together_only_out_of_core_and_within_the_film_budget():
    from vastray.actors.node import SWEEP_FILM_BYTES, units_together
    from vastray.render.film import FILM_BYTES_PER_PIXEL

    units = [(None, 0, 1), (None, 1, 2), (None, 2, 4), (None, 4, 8)]
    out = JobOptions(scheduler="spec-ooc", cache=4)
    assert units_together(units, 0, out, False, 16, 100) == [0, 1, 2, 3]
    assert units_together(units, 1, out, False, 16, 100) == [1, 2, 3]
    assert units_together(units, 0, out, True, 16, 100) == [0]  # paced, or a reference
    assert units_together(units, 0, out, False, 4, 100) == [0]  # in core: the cache keeps all
    assert units_together(units, 0, JobOptions(scheduler="spec-ooc"), False, 16, 100) == [0]
    assert units_together(units, 0, JobOptions(scheduler="async", cache=4), False, 16,
                          100) == [0]  # rays move between nodes: pass by pass
    two = SWEEP_FILM_BYTES // (2 * FILM_BYTES_PER_PIXEL)  # pixels of which two films fit
    assert units_together(units, 0, out, False, 16, two) == [0, 1]
    assert units_together(units, 0, out, False, 16, 10 * two) == [0]
    frames = [(0, 0, 1), (0, 1, 2), (1, 0, 1), (1, 1, 2)]
    assert units_together(frames, 0, out, False, 16, 100) == [0, 1]  # one frame at a time


def test_ctrl_c_during_the_one_pass_says_nothing_was_kept(store, toml, tmp_path):
    """As a user runs it, without --quiet: Ctrl-C in the middle of the one pass exits 130,
    says that nothing finished can be kept and how to keep passes, and writes no image."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "one.exr"
    proc = subprocess.Popen(
        [sys.executable, "-m", "vastray", "render", str(store.path), "--scene", str(toml),
         "--width", str(W), "--height", str(H), "--spp", "65536", "--cache",
         str(quarter(store)), "--scheduler", "spec-ooc", "-o", str(out)],
        stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120
        seen = []
        while not any("passes: one of 65536 spp" in line for line in seen):
            line = proc.stderr.readline()
            assert line and time.monotonic() < deadline, "".join(seen)
            seen.append(line)
        time.sleep(1.0)  # into the pass
        assert proc.poll() is None, "".join(seen)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()  # its pipe closed here, not by a later test's collection
    assert proc.returncode == 130, err
    assert "interrupted during the one pass: nothing finished to keep" in err, err
    assert "--checkpoint-every" in err
    assert not out.exists()


def test_the_cli_says_it_renders_out_of_core_in_one_pass(store, toml, tmp_path, capsys):
    """As a user runs it, without --quiet: the plan's line and the summary line."""
    from vastray.cli import main

    out = tmp_path / "one.exr"
    assert main(["render", str(store.path), "--scene", str(toml), "--width", str(W),
                 "--height", str(H), "--spp", str(SPP), "--cache", str(quarter(store)),
                 "--scheduler", "spec-ooc", "-o", str(out), "--report",
                 str(tmp_path / "one.json")]) == 0
    err = capsys.readouterr().err
    assert f"passes: one of {SPP} spp (out of core" in err, err
    assert err.strip().splitlines()[-1].startswith(f"wrote {out}"), err
    assert out.is_file()


def test_the_cli_on_two_nodes_keeps_its_passes_at_the_loads_of_one(rm, tmp_path, capsys):
    """As a user runs it, without --quiet: `vastray render --nodes 2` out of core with its
    passes kept (--max-pass-spp) loads what its one pass loads, and gives the same image."""
    import json

    from vastray.cli import main
    from vastray.render.imageio import read_image

    common = [str(rm.path), "--width", "32", "--height", "24", "--spp", "8", "--integrator",
              "ao", "--cache", str(-(-len(rm.domains) // 4)), "--scheduler", "image",
              "--nodes", "2"]
    loads = {}
    for name, extra in (("one", []), ("kept", ["--max-pass-spp", "2"])):
        assert main(["render", *common, *extra, "-o", str(tmp_path / f"{name}.exr"),
                     "--report", str(tmp_path / f"{name}.json")]) == 0
        err = capsys.readouterr().err
        assert err.strip().splitlines()[-1].startswith(f"wrote {tmp_path / name}.exr"), err
        report = json.loads((tmp_path / f"{name}.json").read_text())
        loads[name] = report["counters"]["loads"]
        assert len(report["passes"]) == (1 if name == "one" else 5), report["passes"]
    assert loads["kept"] <= 1.1 * loads["one"], loads
    np.testing.assert_array_equal(read_image(tmp_path / "kept.exr"),
                                  read_image(tmp_path / "one.exr"))


def each_alone(options: JobOptions) -> JobOptions:
    """``options`` with each pass sweeping the domains alone (``--passes-alone``)."""
    return dataclasses.replace(options, trace_ahead=False)


def apart(rm, options, st, **rules):
    """``render_out_of_core`` of ``rm`` in passes apart (``StopRules(**rules)``) and its
    progression."""
    progression = Progression(st.width, st.height, StopRules(st.spp, **rules.get("stop", {})),
                              rules.get("reference"))
    return render_out_of_core(rm, SceneConfig(), st, options, progress=False,
                              progression=progression), progression


@pytest.mark.parametrize("scheduler,stop", [("image", {}), ("spec-ooc", {}),
                                            ("image", {"time_limit": 3600.0})],
                         ids=["image", "spec-ooc", "image-time-limit"])
def test_passes_apart_where_loads_take_the_time_are_traced_on_the_first_ones_loads(rm,
                                                                                   scheduler,
                                                                                   stop):
    """Passes apart (a reference's error curve; or a time limit, whose rule may still grant
    every pass) in one process out of core, loads most of the time (0.5 MB/s storage): while a
    pass's tile leads, the later passes' tiles trace their rays in the domains it activates.
    Each pass still ends on its own, its film merged before the next one's, and the films
    are bit for bit those of passes swept one after another (``--passes-alone``): 1.2-1.3x
    one pass's loads, against 2.9-3.2x (under the time limit, whose first pass has only the
    next one ride, 1.8-1.9x)."""
    w, h, spp = 32, 24, 8  # passes of 1, 1, 2, 4 spp, all within the tile
    st = settings(width=w, height=h, spp=spp, integrator="ao", bounces=1)
    options = JobOptions(scheduler=scheduler, cache=-(-len(rm.domains) // 4), threads=1,
                         load_bandwidth=LOADS_TAKE_THE_TIME)
    one = render_out_of_core(rm, SceneConfig(), st, options, progress=False)
    reference = np.full((h, w, 3), 0.2, np.float32)
    ahead, progression = apart(rm, options, st, reference=reference, stop=stop)
    alone, _ = apart(rm, each_alone(options), st, reference=reference, stop=stop)
    assert ahead.counters["ahead_queries"] > 0  # later passes rode along
    assert "ahead_queries" not in alone.counters
    seconds = [p["seconds"] for p in progression.series]
    assert len(seconds) == 4 and seconds == sorted(seconds), seconds
    loads = (one.counters["loads"], ahead.counters["loads"], alone.counters["loads"])
    assert loads[2] > 2.5 * loads[0], loads
    if stop:  # the first pass of a time limit has only the next one ride: 1.8-1.9x here
        assert loads[1] <= 0.85 * loads[2], loads
    else:
        assert loads[1] <= 1.5 * loads[0], loads
    np.testing.assert_array_equal(ahead.film.image(), alone.film.image())


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_passes_apart_where_traces_take_the_time_trace_the_next_one_ahead(rm, scheduler):
    """Where traces take most of the time (path tracing, loads from the page cache) only the
    next pass rides along, so that each pass's error still comes early: 2.5-2.9x one pass's
    loads, against 3.3-4.1x; the same films."""
    w, h, spp = 32, 24, 16
    st = settings(width=w, height=h, spp=spp, integrator="pt", bounces=3)
    options = JobOptions(scheduler=scheduler, cache=-(-len(rm.domains) // 4), threads=1)
    reference = np.full((h, w, 3), 0.2, np.float32)
    ahead, _ = apart(rm, options, st, reference=reference)
    alone, _ = apart(rm, each_alone(options), st, reference=reference)
    assert ahead.counters["ahead_queries"] > 0
    assert ahead.counters["loads"] <= 0.85 * alone.counters["loads"], (
        ahead.counters["loads"], alone.counters["loads"])
    np.testing.assert_array_equal(ahead.film.image(), alone.film.image())


@pytest.mark.parametrize("nodes,scheduler", [(None, "spec-ooc"), (2, "image")])
def test_a_pass_traced_ahead_is_given_up_where_the_error_target_stops(rm, nodes, scheduler):
    """The rule (on nodes, the coordinator's) stops after pass 1: the passes traced ahead
    are given up, and the image is that of passes 0 and 1 bit for bit (what a 2-spp render
    gives)."""
    w, h = 32, 24
    st = settings(width=w, height=h, spp=16, integrator="ao", bounces=1)
    options = JobOptions(scheduler=scheduler, cache=-(-len(rm.domains) // 4), threads=1)
    reference = render_out_of_core(rm, SceneConfig(), settings(
        width=w, height=h, spp=64, integrator="ao", bounces=1, seed=99), JobOptions(),
        progress=False).film.image()
    _, curve = apart(rm, options, st, reference=reference)
    errors = [p["rel_mse"] for p in curve.series]
    assert errors[1] < errors[0], errors
    stop = {"target_error": (errors[0] + errors[1]) / 2}
    if nodes is None:
        result, progression = apart(rm, options, st, reference=reference, stop=stop)
    else:
        result, progression = apart_on_nodes(rm, options, st, nodes, reference=reference,
                                             stop=stop)
    assert_stopped_as_a_shorter_render(rm, options, result, progression, "target-error", 2)


def assert_stopped_as_a_shorter_render(rm, options: JobOptions, result, progression,
                                       rule: str, spp: int) -> None:
    """``rule`` stopped the AO render of ``rm`` after ``spp`` samples a pixel, the passes
    traced ahead given up, and its image is that of a ``spp``-sample render bit for bit."""
    w, h = progression.width, progression.height
    assert progression.stopped_by == rule
    assert progression.series[-1]["spp"] == spp, progression.series
    assert result.counters["given_up_paths"] > 0
    shorter = render_out_of_core(rm, SceneConfig(), settings(width=w, height=h, spp=spp,
                                                             integrator="ao", bounces=1),
                                 options, progress=False,
                                 progression=Progression(w, h, StopRules(spp)))
    np.testing.assert_array_equal(result.film.image(), shorter.film.image())


def apart_on_nodes(rm, options, st, nodes: int = 2, **rules):
    """``render_distributed`` of ``rm`` on ``nodes`` nodes in passes apart, as ``apart``."""
    progression = Progression(st.width, st.height, StopRules(st.spp, **rules.get("stop", {})),
                              rules.get("reference"))
    result = render_distributed(rm.path, None, st, nodes, options,
                                progression_of=lambda frame: progression)
    return result, progression


@pytest.mark.parametrize("stop", [{}, {"time_limit": 3600.0}], ids=["reference", "time-limit"])
def test_passes_apart_on_two_nodes_are_traced_on_the_first_ones_loads(rm, stop):
    """As in one process, on each of 2 nodes: each pass is reduced over the nodes as it ends
    while the node's render thread traces the later ones ahead (under a time limit, those
    the coordinator's rule may still grant, by the clock each grant brings); the films are
    those of one process bit for bit."""
    w, h, spp = 32, 24, 8
    st = settings(width=w, height=h, spp=spp, integrator="ao", bounces=1)
    options = JobOptions(scheduler="spec-ooc", cache=-(-len(rm.domains) // 4), threads=1,
                         load_bandwidth=LOADS_TAKE_THE_TIME)
    reference = np.full((h, w, 3), 0.2, np.float32)
    one = render_distributed(rm.path, None, st, 2, options)
    ahead, progression = apart_on_nodes(rm, options, st, reference=reference, stop=stop)
    alone, _ = apart_on_nodes(rm, each_alone(options), st, reference=reference, stop=stop)
    assert ahead.counters["ahead_queries"] > 0
    assert len(progression.series) == 4
    loads = (one.counters["loads"], ahead.counters["loads"], alone.counters["loads"])
    assert loads[2] > 2 * loads[0], loads
    if stop:  # the first pass of a time limit has only the next one ride: 1.8-1.9x here
        assert loads[1] <= 0.85 * loads[2], loads
    else:
        assert loads[1] <= 1.5 * loads[0], loads
    in_one_process, _ = apart(rm, options, st, reference=reference)
    np.testing.assert_array_equal(ahead.film.image(), in_one_process.film.image())
    np.testing.assert_array_equal(alone.film.image(), in_one_process.film.image())


def test_the_cli_says_it_traces_passes_ahead_out_of_core(rm, tmp_path, capsys):
    """As a user runs it, without --quiet: `vastray render --reference` out of core traces
    the next passes ahead (the report's ``ahead_queries``), with a time limit too, at fewer
    loads than with --passes-alone, and says which it does."""
    import json

    from vastray.cli import main
    from vastray.render.imageio import write_exr

    reference = tmp_path / "ref.exr"
    write_exr(reference, np.full((24, 32, 3), 0.2, np.float32))
    common = [str(rm.path), "--width", "32", "--height", "24", "--spp", "8", "--integrator",
              "pt", "--cache", str(-(-len(rm.domains) // 4)), "--scheduler", "spec-ooc",
              "--reference", str(reference)]
    reports = {}
    for name, extra, said in (
            ("ahead", [], "the next passes traced on the current one's domain loads (each "
                          "pass's image still merged as it ends)"),
            ("timed", ["--time-limit", "3600"], "the next passes traced on the current one's "
             "domain loads (each pass's image still merged as it ends; only passes "
             "--time-limit's rule may still grant)"),
            ("alone", ["--passes-alone"], "each sweeping the domains alone (--passes-alone)")):
        out = tmp_path / f"{name}.exr"
        assert main(["render", *common, *extra, "-o", str(out), "--report",
                     str(tmp_path / f"{name}.json")]) == 0
        err = capsys.readouterr().err
        assert f"passes: apart, out of core, {said}" in err, err
        assert err.strip().splitlines()[-1].startswith(f"wrote {out}"), err
        reports[name] = json.loads((tmp_path / f"{name}.json").read_text())
        assert len(reports[name]["passes"]) == 4
    for name in ("ahead", "timed"):
        assert reports[name]["counters"]["ahead_queries"] > 0
        assert reports[name]["counters"]["loads"] < reports["alone"]["counters"]["loads"]
    assert reports["alone"]["options"]["trace_ahead"] is False


def test_a_time_limit_gives_up_the_passes_its_rule_stops_before(rm):
    """Under a time limit the next pass rides from the start (the rule cannot yet tell), and
    is given up where the rule stops before it: here after pass 0 (0.7-0.8 s of loads at
    1 MB/s; pass 1 predicted to end past the 1 s limit). The image is pass 0's bit for bit."""
    w, h = 32, 24
    st = settings(width=w, height=h, spp=16, integrator="ao", bounces=1)
    options = JobOptions(scheduler="spec-ooc", cache=-(-len(rm.domains) // 4), threads=1,
                         load_bandwidth=1.0)
    result, progression = apart(rm, options, st, stop={"time_limit": 1.0})
    assert_stopped_as_a_shorter_render(rm, options, result, progression, "time-limit", 1)


def test_a_pass_rides_only_while_the_rule_may_grant_it(rm, monkeypatch):
    """``render_ahead`` starts a tile of pass k only while ``Progression.may_grant(k)``
    says the rules may still grant it: with a rule that grants nothing two passes ahead, no
    tile of pass k starts before pass k - 1 leads. The film is the same."""
    from vastray.actors import sort_first

    w, h = 32, 24
    st = settings(width=w, height=h, spp=8, integrator="ao", bounces=1)
    options = JobOptions(scheduler="spec-ooc", cache=-(-len(rm.domains) // 4), threads=1,
                         load_bandwidth=1.0)
    progression = Progression(w, h, StopRules(8, time_limit=3600.0))
    monkeypatch.setattr(progression, "may_grant",
                        lambda index, **time_rule:
                        index <= progression.snapshot.passes_done + 1)
    started = []  # (pass of the tile, pass under way) at each tile's start
    real = sort_first.SortFirstTiles._started

    def recording(tiles, ctx):
        first = int(ctx.sample.min())
        index = next(k for k, (a, b) in enumerate(progression.passes) if a <= first < b)
        started.append((index, progression.snapshot.passes_done))
        return real(tiles, ctx)

    monkeypatch.setattr(sort_first.SortFirstTiles, "_started", recording)
    result = render_out_of_core(rm, SceneConfig(), st, options, progress=False,
                                progression=progression)
    assert result.counters["ahead_queries"] > 0
    assert any(index == done + 1 for index, done in started), started  # the next one rode
    assert all(index <= done + 1 for index, done in started), started
    alone, _ = apart(rm, each_alone(options), st)
    np.testing.assert_array_equal(result.film.image(), alone.film.image())


@pytest.mark.parametrize("bound", ["films", "tile"])
def test_passes_are_traced_ahead_only_within_the_tile_and_while_their_films_fit(rm, monkeypatch,
                                                                                bound):
    """Tiles ride only within the tile's paths (a pass of one tile leaves no room beside
    it), and a pass traced ahead holds a film of its own until it is merged: with no room
    for one (``AHEAD_FILM_BYTES`` 0, as a 4K image's 2 GB film has against 256 MiB), no
    other pass's tile starts. Either way the render loads what passes alone load."""
    from vastray.actors import sort_first

    w, h = 32, 24
    st = settings(width=w, height=h, spp=8, integrator="ao", bounces=1)
    # no preloading: a preload's timing may add or spare a load, so only then are two renders'
    # loads the same count
    options = JobOptions(scheduler="spec-ooc", cache=-(-len(rm.domains) // 4), threads=1,
                         max_samples_in_flight=w * h if bound == "tile" else None,
                         preload=False)
    reference = np.full((h, w, 3), 0.2, np.float32)
    if bound == "films":
        monkeypatch.setattr(sort_first, "AHEAD_FILM_BYTES", 0)
    ahead, _ = apart(rm, options, st, reference=reference)
    alone, _ = apart(rm, each_alone(options), st, reference=reference)
    assert ahead.counters["ahead_queries"] == 0
    assert ahead.counters["loads"] == alone.counters["loads"]
    np.testing.assert_array_equal(ahead.film.image(), alone.film.image())


def test_an_animation_on_two_nodes_traces_each_frames_passes_ahead(store, tmp_path, capsys):
    """As a user runs it, without --quiet: `vastray render --frames 2 --nodes 2` out of core
    with an error target renders each frame's passes traced ahead, frame after frame (the
    coordinator's grant after a frame's last pass is the next frame's first), and gives one
    process's frames bit for bit (the rule stops each where one process does)."""
    import json

    from vastray.cli import main
    from vastray.render.imageio import read_image

    toml = tmp_path / "orbit.toml"
    toml.write_text(POINT_AND_SKY_TOML.replace(
        "look_at = [0.0, -0.5, 0.0]\n", "look_at = [0.0, -0.5, 0.0]\n[camera.orbit]\n"
        "degrees_per_frame = 40\n", 1))
    common = [str(store.path), "--scene", str(toml), "--frames", "2", "--width", str(W),
              "--height", str(H), "--spp", "16", "--integrator", "pt", "--bounces", "2",
              "--cache", str(quarter(store)), "--scheduler", "image", "--target-error", "0.02"]
    for name, extra in (("one", []), ("nodes", ["--nodes", "2"])):
        assert main(["render", *common, *extra, "-o", str(tmp_path / f"{name}.exr"),
                     "--report", str(tmp_path / f"{name}.json")]) == 0
        err = capsys.readouterr().err
        assert "wrote" in err.strip().splitlines()[-1], err
    for frame in (0, 1):
        np.testing.assert_array_equal(read_image(tmp_path / f"nodes_{frame:04d}.exr"),
                                      read_image(tmp_path / f"one_{frame:04d}.exr"))
    for frame in (0, 1):  # the rule stopped each frame early, its passes traced ahead dropped
        report = json.loads((tmp_path / f"nodes_{frame:04d}.json").read_text())
        assert report["stopped_by"] == "target-error", report["stopped_by"]
        assert report["counters"]["ahead_queries"] > 0, report["counters"]
        assert report["counters"]["given_up_paths"] > 0, report["counters"]
