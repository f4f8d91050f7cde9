"""Out-of-core schedules (image baseline, SpRay spec-ooc) reproduce the reference image."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.actors.render_setup import RenderSetup
from vastray.cli import main
from vastray.render.driver import path_context, render
from vastray.render.integrators import camera_rays
from vastray.render.lights import AmbientLight, PointLight, QuadLight
from vastray.render.scene_config import SceneConfig
from vastray.scene.cache import DomainCache
from vastray.scene.generate import generate
from vastray.scene.partition import partition_kd
from vastray.scene.readers import read_mesh
from vastray.scene.store import Store, StoreWriter
from vastray.schedule.spec_ooc import SpeculationRules, SpeculativeSchedule, traversal_order
from vastray.schedule.traversal import traversal_score

from scenes import bumpy_scene, camera_config, settings, write_store

LIGHTS = [PointLight(np.array([2.0, 3.0, 1.0]), np.full(3, 12.0)),
          QuadLight(np.array([-1.0, 3.0, -1.0]), np.array([0.0, 0.0, 0.8]),
                    np.array([0.8, 0.0, 0.0]), np.full(3, 4.0)),
          AmbientLight(np.full(3, 0.2))]


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("ooc") / "kd27", bumpy_scene(), kd=27)


@pytest.fixture(scope="module")
def config():
    return camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0], lights=LIGHTS)


def assert_same(image, reference, what):
    np.testing.assert_allclose(image, reference, rtol=1e-6, atol=1e-6, err_msg=what)


@pytest.mark.parametrize("integrator", ["ao", "pt"])
@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_schedules_match_reference_for_any_cache_and_tile(bumpy, config, integrator, scheduler):
    st = settings(width=40, height=30, spp=2, integrator=integrator, bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    for cache, in_flight, eviction in [(None, None, "lru"), (7, None, "lru"), (1, 700, "lru"),
                                       (4, None, "demand")]:
        result = render_out_of_core(bumpy, config, st,
                                    options=JobOptions(scheduler=scheduler, cache=cache,
                                                       max_samples_in_flight=in_flight,
                                                       eviction=eviction), progress=False)
        assert_same(result.film.image(), reference,
                    f"{scheduler} cache={cache} tile={in_flight} eviction={eviction}")
        assert result.film.depth.tolist() == render(bumpy, config, st, progress=False
                                                    ).film.depth.tolist()


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_builds_ahead_leave_the_image_and_the_capacity_alone(bumpy, config, scheduler):
    """Out of core a cache may keep a slot for the next domain to load, built while the
    schedule names no preload (``JobOptions.build_ahead``, for both schedules). The image is
    the reference bit for bit and no more domains are built at once than the cache holds."""
    st = settings(width=40, height=30, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    for build_ahead in (True, False):
        result = render_out_of_core(bumpy, config, st, options=JobOptions(
            scheduler=scheduler, cache=4, build_ahead=build_ahead), progress=False)
        c = result.counters
        assert_same(result.film.image(), reference, f"{scheduler} build_ahead={build_ahead}")
        assert c["peak_resident_domains"] <= 4
        assert c["builds_ahead_used"] <= c["builds_ahead"] and c["builds_ahead_used"] <= c["loads"]
        if not build_ahead:
            assert c["builds_ahead"] == 0
        # (neither schedule builds ahead here: spec-ooc serves the victim before its preloaded
        # domain, so it names a preload at every step, as the baseline nearly always does;
        # tests/test_preloader.py builds ahead by hand)


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_a_cache_holding_every_domain_reads_the_next_load_ahead(bumpy, config, scheduler,
                                                                 tmp_path, capsys):
    """In core the preloader is one domain ahead, as out of core: the files of the load after
    it are read ahead on the reader thread (session 70: before, the preloader read and then
    built each domain and the render waited for every read). Each domain is still loaded
    once, nothing is evicted, and the image is the reference bit for bit; the CLI's render,
    without --quiet, says so in its summary and report."""
    st = settings(width=40, height=30, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    n = len(bumpy.domains)
    result = render_out_of_core(bumpy, config, st, options=JobOptions(
        scheduler=scheduler, cache=n), progress=False)
    c = result.counters
    assert_same(result.film.image(), reference, f"{scheduler} in core")
    assert c["evictions"] == 0 and c["loads"] == c["distinct_domains_loaded"]
    assert 0 < c["reads_ahead_used"] <= c["reads_ahead"]
    out, report = tmp_path / "in-core.exr", tmp_path / "in-core.json"
    assert main(["render", str(bumpy.path), "-o", str(out), "--width", "24", "--height", "18",
                 "--spp", "1", "--scheduler", scheduler, "--report", str(report)]) == 0
    err = capsys.readouterr().err
    assert f"wrote {out}" in err and "domain loads" in err, err
    counters = json.loads(report.read_text())["counters"]
    assert counters["evictions"] == 0 and counters["reads_ahead_used"] > 0


@pytest.mark.parametrize("history_depth", [0, 1, 2, 3])
def test_spec_ooc_any_history_depth_matches_reference(bumpy, config, history_depth):
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    result = render_out_of_core(bumpy, config, st,
                                options=JobOptions(scheduler="spec-ooc", cache=5,
                                                   history_depth=history_depth), progress=False)
    assert_same(result.film.image(), reference, f"H={history_depth}")
    windows = result.counters["windows"]
    assert windows == -(-4 // (1 + min(history_depth, 3)))  # ceil(vertices / window)


def test_speculation_loads_fewer_domains_and_reports_its_waste(bumpy, config):
    st = settings(width=48, height=36, spp=2, integrator="pt", bounces=3)
    base = render_out_of_core(bumpy, config, st, options=JobOptions(scheduler="image", cache=7),
                              progress=False).counters
    spec = render_out_of_core(bumpy, config, st, options=JobOptions(scheduler="spec-ooc", cache=7),
                              progress=False).counters
    assert spec["loads"] * 1.5 < base["loads"]
    assert spec["speculative_rays"] > 0 and 0 < spec["wasted_rays"] < spec["speculative_rays"]
    assert spec["filtered_rays"] > 0
    for counters in (base, spec):
        for key in ("loads", "cache_hits", "load_s", "rays_in_flight_peak", "preloads"):
            assert key in counters


@pytest.mark.parametrize("integrator", ["ao", "pt"])
@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_every_switch_combination_matches_reference(bumpy, config, integrator, scheduler):
    # Residency and preloading change the order domains are visited in, never the image.
    st = settings(width=24, height=18, spp=2, integrator=integrator, bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    for resident_first in (False, True):
        for preload in (False, True):
            result = render_out_of_core(bumpy, config, st,
                                        options=JobOptions(scheduler=scheduler, cache=4,
                                                           resident_first=resident_first,
                                                           preload=preload), progress=False)
            assert_same(result.film.image(), reference,
                        f"{scheduler} resident_first={resident_first} preload={preload}")


@pytest.mark.parametrize("resident_first", [False, True])
def test_spec_ooc_filters_before_it_loads(bumpy, config, resident_first):
    # Listing 2, lines 15-19: a domain whose rays are all stale, beaten or blocked is skipped,
    # not loaded. With sequential loading every load traces at least one ray.
    st = settings(width=48, height=36, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    result = render_out_of_core(bumpy, config, st,
                                options=JobOptions(scheduler="spec-ooc", cache=7,
                                                   resident_first=resident_first, preload=False),
                                progress=False)
    c = result.counters
    assert_same(result.film.image(), reference, f"resident_first={resident_first}")
    assert c["skipped_domains"] > 0
    assert c["untraced_loads"] == 0
    assert c["domains_traced"] == 27 <= c["loads"]


def test_resident_first_saves_baseline_loads(bumpy, config):
    # The baseline gets the rule spec-ooc has: serve what is in memory before loading more.
    st = settings(width=48, height=36, spp=2, integrator="pt", bounces=3)
    loads = {rule: render_out_of_core(bumpy, config, st,
                                      options=JobOptions(scheduler="image", cache=7,
                                                         resident_first=rule, preload=False),
                                      progress=False).counters["loads"]
             for rule in (False, True)}
    assert loads[True] < loads[False]


def test_traversal_order_follows_the_score():
    # Score[i] = sum_j (M - j) Counter[i][j], M = 3: 3, 3, 4, 8; ties go to the lower id.
    counter = np.array([[0, 0, 3],
                        [1, 0, 0],
                        [0, 2, 0],
                        [2, 1, 0]])
    score = traversal_score(counter)
    assert score.tolist() == [3, 3, 4, 8]
    assert traversal_order(score) == [3, 2, 0, 1]
    assert traversal_order(score, frozenset({1, 2})) == [2, 1, 3, 0]
    assert traversal_order(np.zeros(3, np.int64)) == [0, 1, 2]


def test_traversal_order_ranks_the_rest_of_a_round():
    # rescore: only the domains still to visit are ranked, by the scores of now.
    counter = np.array([[0, 0, 3],
                        [1, 0, 0],
                        [0, 2, 0],
                        [2, 1, 0]])
    assert traversal_order(traversal_score(counter), domains=[0, 1, 2]) == [2, 0, 1]
    counter[1, 0] = 5  # rays queued for domain 1 during the round
    assert traversal_order(traversal_score(counter), domains=[0, 1, 2]) == [1, 2, 0]
    assert traversal_order(traversal_score(counter), frozenset({0}), [0, 1, 2]) == [0, 1, 2]


@pytest.mark.parametrize("scale", [1, 10**9, 10**13])  # the last: past the packed key
def test_traversal_order_is_resident_then_score_then_id(scale):
    rng = np.random.default_rng(scale % 97)
    for _ in range(50):
        n = int(rng.integers(1, 600))
        score = rng.integers(-40, 40, n) * scale
        resident = frozenset(rng.choice(n, int(rng.integers(0, n + 1)), replace=False).tolist())
        domains = sorted(rng.choice(n, int(rng.integers(0, n + 1)), replace=False).tolist())
        expected = sorted(domains, key=lambda d: (d not in resident, -int(score[d]), d))
        assert traversal_order(score, resident, domains) == expected


def _started(store, config, st, **options) -> tuple[RenderSetup, SpeculativeSchedule]:
    """The render set-up of ``st`` and a spec-ooc schedule of its one tile, camera rays in."""
    setup = RenderSetup.of(store, config, st)
    ctx = path_context(setup.shading, st, 0, setup.total_paths, setup.ao_distance)
    policy = SpeculativeSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range,
                                 **options)
    policy.start(camera_rays(setup.camera, ctx))
    return setup, policy


def _drive(store, config, st, cache_capacity, parting=True, **options):
    """Run spec-ooc over one tile by hand (sequential loads), the domain it serves before
    the cache evicts it marked parting as the runtime marks it (``parting=False``: not).
    Returns (evicted with rays that would still be traced, process calls, film radiance,
    most loads of one domain in one round)."""
    setup, policy = _started(store, config, st, **options)
    cache = DomainCache(store, cache_capacity, setup.keep)
    unserved = calls = 0
    loads: dict[tuple[int, int], int] = {}  # (round, domain) -> loads
    while (domain := policy.next_domain(cache.resident_set(), victim=cache.victim)) is not None:
        going = cache.victim()
        if domain not in cache:
            key = (policy.counters["rounds"], domain)
            loads[key] = loads.get(key, 0) + 1
            if going is not None and policy._would_trace(going):
                unserved += 1
        if parting and domain == policy.parting:
            assert domain == going  # only the cache's victim is served as parting
            cache.parting(domain)
        policy.process(domain, cache.get(domain))
        calls += 1
    return unserved, calls, policy.result.radiance, max(loads.values())


def _would_trace_by_predicates(policy, domain: int) -> bool:
    """``_would_trace`` as the filter's own predicates answer it over every queued chunk."""
    for chunk in policy.radiance.peek(domain):
        level = chunk["depth"].astype(np.int64) - policy.window_start
        if policy._radiance_predicate(chunk, level)[1].any():
            return True
    return any(policy._shadow_predicate(chunk)[1].any() for chunk in policy.shadow.peek(domain))


def test_the_compiled_would_trace_answers_as_the_filter_predicates(bumpy, config):
    # likely_next's test, compiled, against the predicates next_domain filters by: at every
    # step of a tile, for every domain (both answers occur, or the check proves nothing)
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    setup, policy = _started(bumpy, config, st)
    cache = DomainCache(bumpy, 5, setup.keep)
    answers = set()
    while (domain := policy.next_domain(cache.resident_set(), victim=cache.victim)) is not None:
        for d in range(len(bumpy.domains)):
            if d != domain:  # the chosen domain's rays are staged, not queued
                expected = _would_trace_by_predicates(policy, d)
                assert policy._would_trace(d) == expected, d
                answers.add(expected)
        policy.process(domain, cache.get(domain))
    assert answers == {True, False}


def test_spec_ooc_serves_a_resident_domain_before_it_is_evicted(bumpy, config):
    # serve_before_evict: rays that reached a resident domain are traced before a load evicts
    # it (never a reload for them), in fewer batches than serving each arrival at once.
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    lazy, lazy_calls, lazy_radiance, lazy_reloads = _drive(bumpy, config, st, 5)
    eager, eager_calls, eager_radiance, _ = _drive(bumpy, config, st, 5,
                                                   serve_before_evict=False)
    paper, _, _, _ = _drive(bumpy, config, st, 5, resident_first=False)
    assert lazy == 0 and eager == 0
    assert lazy_reloads == 1  # no domain is loaded twice in one round
    assert paper > 0  # the paper's order evicts domains with rays left (the check can fail)
    assert lazy_calls < eager_calls
    np.testing.assert_allclose(lazy_radiance, eager_radiance, rtol=1e-6, atol=1e-6)


def test_a_domain_served_before_its_eviction_stays_the_victim(bumpy, config):
    # Served before it goes, the victim keeps its place in the eviction order; counted as
    # used, the next resident domain became the victim and was served in turn, through every
    # resident domain with rays before each load: more activations, the same picture, and
    # still no domain evicted with rays to trace.
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    kept, kept_calls, kept_radiance, _ = _drive(bumpy, config, st, 3)
    used, used_calls, used_radiance, _ = _drive(bumpy, config, st, 3, parting=False)
    assert kept == 0 and used == 0
    assert kept_calls < used_calls, (kept_calls, used_calls)
    np.testing.assert_allclose(kept_radiance, used_radiance, rtol=1e-6, atol=1e-6)


def test_spec_ooc_serves_the_victim_before_a_preloaded_domain(bumpy, config):
    # The round's next domain is resident because a preload brought it (or is bringing it)
    # and nothing has taken it yet: before it, the schedule serves the domain the cache
    # evicts next (a resident one with rays), so the preloader may evict that one for the
    # load after while the new domain is traced, with no serve pending.
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    setup, policy = _started(bumpy, config, st)
    cache = DomainCache(bumpy, 3, setup.keep)
    checked = 0
    while (domain := policy.next_domain(cache.resident_set(), victim=cache.victim)) is not None:
        policy.process(domain, cache.get(domain))
        going = cache.victim()
        upcoming = policy._schedule[0] if policy._schedule else None
        if (checked or going is None or upcoming is None or upcoming in cache
                or not policy._would_trace(going) or not policy._would_trace(upcoming)):
            continue
        # as if ``upcoming`` had been preloaded into the slot ``going`` still holds
        served = policy.next_domain(cache.resident_set() | {upcoming}, victim=cache.victim,
                                    preloaded=frozenset({upcoming}))
        assert served == going == policy.parting
        assert policy.counters["served_before_preloaded"] == 1
        cache.parting(served)
        policy.process(served, cache.get(served))
        checked += 1
    assert checked == 1  # the state occurred (the check can fail)
    assert policy.counters["served_before_evict"] > 0


def test_spec_ooc_serves_victims_before_preloaded_domains_whatever_the_load_speed(bumpy, config):
    # The runtime hands the schedule its preloaded domains: the victim is served before them,
    # the image is the reference's, and, since a preloaded domain counts whether its load has
    # ended or not, the loads are the same with storage slow enough that every preload is
    # still running when the next domain is chosen.
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()

    def run(bandwidth):
        return render_out_of_core(bumpy, config, st,
                                  JobOptions(scheduler="spec-ooc", cache=5, preload=True,
                                             load_bandwidth=bandwidth), progress=False)

    fast = run(None)
    assert_same(fast.film.image(), reference, "fast loads")
    assert fast.counters["served_before_preloaded"] > 0 and fast.counters["preloads"] > 0
    slow = run(max(d.nbytes for d in bumpy.domains) / 0.03 / 1e6)  # 30 ms a load
    assert_same(slow.film.image(), reference, "slow loads")
    for key in ("loads", "served_before_preloaded", "served_before_evict", "activations"):
        assert slow.counters[key] == fast.counters[key], key


@pytest.mark.parametrize("options", [SpeculationRules(serve_before_evict=False),
                                     SpeculationRules(rescore=False),
                                     SpeculationRules(serve_before_evict=False, rescore=False)])
def test_spec_ooc_switches_match_reference(bumpy, config, options):
    st = settings(width=24, height=18, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    result = render_out_of_core(bumpy, config, st, options=JobOptions(scheduler="spec-ooc", cache=4),
                                ablation=options, progress=False)
    assert_same(result.film.image(), reference, str(options))


def test_spec_ooc_first_round_follows_the_score(bumpy, config):
    # In the paper's order (no resident rule) the first round visits domains in descending
    # score of the camera rays' Counter; skipped domains only leave gaps.
    st = settings(width=24, height=18, spp=1, integrator="pt", bounces=2)
    setup, policy = _started(bumpy, config, st, resident_first=False)
    expected = traversal_order(policy.score.copy())
    cache = DomainCache(bumpy, len(bumpy.domains), setup.keep)
    visited = []
    while (domain := policy.next_domain()) is not None and policy.counters["rounds"] == 1:
        visited.append(domain)
        policy.process(domain, cache.get(domain))
    assert len(visited) > 3 and visited[0] == expected[0]
    assert visited == sorted(visited, key=expected.index)


def test_spec_ooc_demand_ranks_domains_by_their_place_in_the_round(bumpy, config):
    # eviction by demand: the round's schedule is the future Belady's rule looks at, so the
    # domains left in it rank above the rest, the sooner the higher; no rays, no demand
    st = settings(width=24, height=18, spp=1, integrator="pt", bounces=2)
    setup, policy = _started(bumpy, config, st)
    assert policy.next_domain() is not None
    demand, left = policy.demand(), list(policy._schedule)
    assert len(left) >= 2
    assert (np.diff(demand[left]) < 0).all()  # sooner, higher
    queued = policy.radiance.counts() + policy.shadow.counts()
    rest = [d for d in range(len(demand)) if d not in left]
    assert all(demand[d] == (1.0 if queued[d] else 0.0) for d in rest)
    assert min(demand[left]) > 1.0


def test_samples_in_flight_bound_peak_rays(bumpy, config):
    # SpRay's memory explosion (sections 5.1.2, 6) must not happen: with a tile of 500 paths
    # the peak number of queued rays does not grow with the samples per pixel.
    def peak(spp, tile):
        st = settings(width=24, height=18, spp=spp, integrator="pt", bounces=3)
        # No preloading: which domains are resident when the next is chosen would then depend
        # on thread timing (a loaded machine), and with it the domain order and the peak.
        return render_out_of_core(bumpy, config, st,
                                  options=JobOptions(scheduler="spec-ooc", cache=7,
                                                     max_samples_in_flight=tile, preload=False,
                                                     threads=1),
                                  progress=False).counters["rays_in_flight_peak"]

    bounded = [peak(spp, 500) for spp in (2, 8)]
    unbounded = peak(8, None)
    # 4x the paths, not 4x the peak. The peak is a max over tiles (2 tiles at 2 spp, 7 at
    # 8 spp) and depends on the domain order: over render seeds 1-7 the ratio ranges 1.4-2.1.
    assert bounded[1] <= 2.5 * bounded[0]
    # Deterministic (one thread, no preloading): 16,479 rays against 46,330 unbounded.
    assert bounded[1] * 2 < unbounded


def test_generated_rm_scene(tmp_path):
    generate("rm", tmp_path / "rm", 40, grid=(3, 3, 2), seed=1)
    store = Store(tmp_path / "rm")
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=2, shadow_samples=2)
    reference = render(store, SceneConfig(), st, progress=False).film.image()
    for scheduler in ("image", "spec-ooc"):
        result = render_out_of_core(store, SceneConfig(), st,
                                    options=JobOptions(scheduler=scheduler, cache=4), progress=False)
        assert_same(result.film.image(), reference, scheduler)


@pytest.mark.shared_data
def test_real_mesh_bunny(shared_data, tmp_path):
    mesh = read_mesh(shared_data / "meshes" / "stanford_bunny.ply")
    with StoreWriter(tmp_path / "bunny") as writer:
        for dom in partition_kd(mesh, 8).domains:
            writer.add_domain(dom)
    store = Store(tmp_path / "bunny")
    for integrator in ("ao", "pt"):
        st = settings(width=32, height=32, spp=2, integrator=integrator, bounces=2,
                      shadow_samples=2)
        reference = render(store, SceneConfig(), st, progress=False).film.image()
        assert reference.max() > 0
        for scheduler in ("image", "spec-ooc"):
            result = render_out_of_core(store, SceneConfig(), st,
                                        options=JobOptions(scheduler=scheduler, cache=2), progress=False)
            assert_same(result.film.image(), reference, f"{scheduler} {integrator}")


def test_cli_cache_percentage_and_report(bumpy, tmp_path, capsys):
    # without --quiet, as a user runs it: the out-of-core summary line is printed too
    out, report = tmp_path / "o.exr", tmp_path / "r.json"
    small = ["--width", "24", "--height", "18", "--spp", "1", "--shadow-samples", "2"]
    assert main(["render", str(bumpy.path), "-o", str(out), "--cache", "25%", *small,
                 "--report", str(report)]) == 0
    err = capsys.readouterr().err
    assert f"wrote {out}" in err and "domain loads" in err, err
    doc = json.loads(report.read_text())
    assert doc["scheduler"] == "spec-ooc"  # auto picks speculation when domains do not fit
    assert doc["counters"]["cache_capacity"] == 7  # ceil(25% of 27)
    assert doc["counters"]["max_samples_in_flight"] == 24 * 18
    for key in ("load", "render", "schedule", "total"):
        assert doc["seconds"][key] >= 0
    image = tmp_path / "image.exr"  # the baseline schedule's summary as well
    assert main(["render", str(bumpy.path), "-o", str(image), "--cache", "25%", *small,
                 "--scheduler", "image"]) == 0
    err = capsys.readouterr().err
    assert f"wrote {image}" in err and "domain loads" in err, err
    with pytest.raises(SystemExit):
        main(["render", str(bumpy.path), "-o", str(tmp_path / "x.exr"), "--cache", "150%"])
    assert not (tmp_path / "x.exr").exists()


def test_the_compiled_history_match_is_numpys_comparison():
    """``_matches`` (one compiled pass) against the numpy expression it replaced: equal
    histories, a differing t or domain at each depth, NaN (never equal), and every bound from
    below 0 to beyond the window."""
    from vastray.schedule.spec_ooc import _matches

    rng = np.random.default_rng(11)
    n_paths, window, n = 40, 4, 2000
    hbuf_t = rng.choice([0.5, 1.0, 2.0, np.inf, np.nan], (n_paths, window)).astype(np.float32)
    hbuf_d = rng.integers(0, 3, (n_paths, window)).astype(np.int32)
    path = rng.integers(0, n_paths, n)
    hist_t, hist_d = hbuf_t[path].copy(), hbuf_d[path].copy()
    row, col = rng.integers(0, n, n // 2), rng.integers(0, window, n // 2)
    hist_t[row[::2], col[::2]] = 3.0  # a different t
    hist_d[row[1::2], col[1::2]] += 1  # a different domain
    upto = rng.integers(-1, window + 2, n)
    used = np.arange(window)[None, :] < upto[:, None]
    same = (hist_t == hbuf_t[path]) & (hist_d == hbuf_d[path])
    expected = np.all(same | ~used, axis=1)
    out = np.empty(n, np.bool_)
    _matches(path, hist_t, hist_d, hbuf_t, hbuf_d, upto.astype(np.int64), out)
    assert expected.any() and not expected.all()
    assert (out == expected).all()


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_load_bandwidth_throttles_every_load_of_the_out_of_core_schedules(bumpy, config,
                                                                          scheduler):
    """--load-bandwidth reaches the domain cache of image and spec-ooc (it was dropped on the
    way once): each load is held to its size over the bandwidth, so the time spent waiting is
    at least the bytes loaded over the bandwidth, less the real reads (a lower bound: a busy
    machine only makes the reads longer, and the waits then shorter, never the sum). Same
    image."""
    st = settings(width=24, height=18, spp=1, integrator="pt", bounces=1)
    free = render_out_of_core(bumpy, config, st, JobOptions(scheduler=scheduler, cache=4),
                              progress=False)
    per_load = max(d.nbytes for d in bumpy.domains)
    megabytes_per_s = per_load / 0.02 / 1e6  # the largest domain takes 20 ms
    slowed = render_out_of_core(bumpy, config, st,
                                JobOptions(scheduler=scheduler, cache=4,
                                           load_bandwidth=megabytes_per_s), progress=False)
    c = slowed.counters
    floor = c["bytes_loaded"] / (megabytes_per_s * 1e6)
    assert c["loads"] == free.counters["loads"] > 0
    assert c["load_bandwidth_mb_s"] == pytest.approx(megabytes_per_s)
    assert free.counters["load_bandwidth_mb_s"] is None
    assert free.counters["load_throttle_s"] == 0
    assert c["read_s"] >= floor - 1e-3  # read_s: each read and its wait
    assert c["load_throttle_s"] >= 0.5 * floor  # a 50 KB read takes far less than 10 ms
    assert slowed.seconds["total"] >= floor * 0.9
    np.testing.assert_array_equal(slowed.film.image(), free.film.image())


def test_the_report_times_the_schedules_decisions_apart_from_tracing(bumpy, config):
    # spec-ooc filters a domain's queues when it picks it: that work is the schedule's, timed
    # for both schedules the same way (seconds.schedule), beside the tracing (seconds.render).
    st = settings(width=24, height=18, spp=2, integrator="pt", bounces=3)
    for scheduler in ("image", "spec-ooc"):
        seconds = render_out_of_core(bumpy, config, st, options=JobOptions(
            scheduler=scheduler, cache=4), progress=False).seconds
        assert seconds["schedule"] > 0 and seconds["render"] > 0, scheduler
        assert seconds["schedule"] + seconds["render"] + seconds["load_wait"] <= seconds["total"]
