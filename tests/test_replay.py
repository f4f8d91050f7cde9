"""The simulator's replay (``vastray.sim.crossings``, ``vastray.sim.replay``): one frame's
domain crossings recorded by a real trace, then every scheduler replayed over them. The
recording must be the render (its image the reference's, every ray's visits on its line), and
a replay must trace each ray exactly where a lossless schedule does, do what its scheduler
does (rounds or none, copies, moves), and cost what the real-code simulator says within a
stated band."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.errors import InputError
from vastray.scene.store import Store
from vastray.sim.cache import domain_sizes
from vastray.sim.costs import CostModel
from vastray.sim.crossings import RADIANCE, SHADOW, Crossings, record_crossings
from vastray.sim.replay import (
    REPLAY_SCHEDULERS,
    ActivationCosts,
    Network,
    NodeOwnCosts,
    Replay,
    fit_activation_costs,
    fit_node_own_costs,
)

from scenes import rm_store

SETTINGS = RenderSettings(width=40, height=32, spp=2, bounces=2, seed=5)
LOSSLESS_NON_SPECULATIVE = ("image", "domain", "dynamic", "async")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Store:
    return rm_store(tmp_path_factory.mktemp("replay") / "rm.store", 32, (4, 3, 2))


@pytest.fixture(scope="module")
def recorded(store):
    return record_crossings(store, SETTINGS, tile=500)


def replay_of(store, crossings: Crossings, activations=None, **options) -> Replay:
    """A replay of ``crossings`` on ``store`` with the default costs and (unless ``options``
    say) tiles of 600 paths."""
    return Replay(crossings, *domain_sizes(store), *store.domain_boxes(), CostModel(),
                  activations, **{"tile": 600, **options})


@pytest.fixture(scope="module")
def replay(store, recorded) -> Replay:
    return replay_of(store, recorded[0])


def test_the_recorded_frame_is_the_reference_render(store, recorded):
    crossings, film = recorded
    reference = render(store, SceneConfig(), SETTINGS, progress=False)
    np.testing.assert_array_equal(film.image(), reference.film.image())
    camera = crossings.parent < 0
    assert camera.sum() == SETTINGS.paths
    assert np.array_equal(np.sort(crossings.path[camera]), np.arange(SETTINGS.paths))
    assert crossings.n_paths == SETTINGS.paths and crossings.n_domains == len(store.domains)
    # every kind of segment is there: camera, continuation and shadow rays
    assert (crossings.kind == SHADOW).any()
    assert ((crossings.kind == RADIANCE) & (crossings.depth > 0)).any()


def test_every_visit_lies_on_its_rays_line(recorded):
    """A ray is traced only in domains its line crosses (its speculative copies' domains),
    each at most once, and the activations' ray counts add up to the visits."""
    c, _ = recorded
    assert c.visits.sum() == c.activation_rays.sum() > 0
    for seg in np.nonzero(c.visits)[0][:: max(1, len(c) // 2000)]:
        visited = c.visit_domain[c.visit_first[seg]:c.visit_first[seg + 1]]
        crossed = c.crossed_domain[c.crossed_first[seg]:c.crossed_first[seg + 1]]
        assert len(set(visited.tolist())) == len(visited)
        assert set(visited.tolist()) <= set(crossed.tolist())
    # a shadow ray spawned by a hit: its parent is a radiance segment of the same path
    shadow = np.nonzero(c.kind == SHADOW)[0]
    assert (c.kind[c.parent[shadow]] == RADIANCE).all()
    assert np.array_equal(c.path[c.parent[shadow]], c.path[shadow])


def test_a_recording_survives_its_file_and_a_bad_file_is_named(recorded, tmp_path):
    c, _ = recorded
    c.save(tmp_path / "frame.npz")
    back = Crossings.load(tmp_path / "frame.npz")
    for field in dataclasses.fields(Crossings):
        assert np.array_equal(getattr(back, field.name), getattr(c, field.name)), field.name
    (tmp_path / "bad.npz").write_bytes(b"not numpy")
    with pytest.raises(InputError, match="bad.npz"):
        Crossings.load(tmp_path / "bad.npz")


@pytest.mark.parametrize("scheduler", LOSSLESS_NON_SPECULATIVE)
@pytest.mark.parametrize("nodes", [1, 3, 8])
def test_a_lossless_schedule_traces_every_visit_once(replay, recorded, scheduler, nodes):
    c, _ = recorded
    result = replay.run(scheduler, nodes)
    assert result.counters["traced"] == c.visits.sum()
    assert result.seconds > 0
    if nodes == 1 or scheduler == "image":
        assert result.counters["messages"] == 0
    else:
        assert result.counters["messages"] > 0


@pytest.mark.parametrize("nodes", [1, 4])
def test_speculation_traces_copies(replay, recorded, nodes):
    """spec-insitu traces every copy on its line; spec-ooc at least every visit and fewer
    than every copy of every segment (copies after a committed hit are dropped)."""
    c, _ = recorded
    assert replay.run("spec-insitu", nodes).counters["traced"] == c.copies.sum()
    traced = replay.run("spec-ooc", nodes).counters["traced"]
    assert c.visits.sum() <= traced <= c.copies.sum()


def test_what_each_scheduler_synchronises_on(replay):
    """domain and dynamic end rounds with all-reductions, more of them on more nodes; async
    has none but its two termination waves; spec-insitu one per iteration (the buffers: how
    many batches come is fixed by its routes); sort-first nodes never synchronise."""
    assert replay.run("domain", 8).counters["rounds"] > replay.run("domain", 1).counters["rounds"]
    assert replay.run("dynamic", 4).counters["rounds"] > 2
    assert replay.run("async", 8).counters["rounds"] == 2
    insitu = replay.run("spec-insitu", 4).counters["rounds"]
    assert insitu >= SETTINGS.bounces + 1
    assert replay.run("image", 8).counters["rounds"] == 0


def test_dynamic_takes_the_next_tile_in_while_the_last_ones_rays_thin_out(store, recorded,
                                                                          monkeypatch):
    """As the nodes' ``DynamicFrame``: a round whose rays waiting were under a tile's paths
    takes the next tile in at its end, so fewer all-reductions find only a tile's stragglers;
    one tile at a time (``MAX_TILES`` 1) is the schedule before it.

    The activations cost what ``fit_activation_costs`` finds for this store (fixed here: the
    fit on a recording's measured CPU times moves from run to run, and on 8 nodes the two
    schedules' seconds are within 0.3 % of each other, so a fit's noise decided the
    comparison: CI once saw 0.34065 against 0.34042 s)."""
    from vastray.actors import dynamic_frame

    typical = ActivationCosts(fixed_s=1.5e-3, fixed_shadow_s=3.5e-4, radiance_s=3.5e-5,
                              shadow_s=2e-6, decision_s=3e-5)
    replay = replay_of(store, recorded[0], typical)
    monkeypatch.setattr(dynamic_frame, "MAX_TILES", 1)
    alone = {n: replay.run("dynamic", n) for n in (1, 4, 8)}
    monkeypatch.setattr(dynamic_frame, "MAX_TILES", 2)
    pipelined = {n: replay.run("dynamic", n) for n in (1, 4, 8)}
    for n in (4, 8):
        assert pipelined[n].counters["rounds"] < alone[n].counters["rounds"], n
        assert pipelined[n].seconds < alone[n].seconds, n
    for n in (1, 4, 8):  # the same rays traced, whatever the order
        assert pipelined[n].counters["activations"] > 0
        assert pipelined[n].counters["traced"] == alone[n].counters["traced"], n


@pytest.mark.parametrize("nodes", [5, 8])
def test_an_all_reduction_costs_its_butterfly_steps_and_the_tree_twice_its_height(store,
                                                                                recorded,
                                                                                nodes):
    """Each all-reduction costs its critical path's message steps: log2 C on the butterfly
    (two more where P is no power of two), 2 ceil(log2 P) on the first design's tree; the
    termination waves of ``async`` stay on the tree."""
    butterfly = replay_of(store, recorded[0], network=Network(latency_s=1e-3))
    tree = replay_of(store, recorded[0], network=Network(latency_s=1e-3), reduction="tree")
    step = butterfly._step_s(64.0)
    assert butterfly._allreduce_s(nodes) == pytest.approx(
        {5: 4, 8: 3}[nodes] * step, rel=1e-12)
    assert tree._allreduce_s(nodes) == pytest.approx(2 * 3 * step, rel=1e-12)
    for scheduler in ("domain", "dynamic", "spec-insitu"):
        fast, slow = butterfly.run(scheduler, nodes), tree.run(scheduler, nodes)
        assert fast.counters["rounds"] == slow.counters["rounds"] > 0
        assert fast.breakdown["reduction"] < slow.breakdown["reduction"], scheduler
        assert fast.seconds < slow.seconds, scheduler
    assert butterfly.run("async", nodes).seconds == tree.run("async", nodes).seconds
    with pytest.raises(ValueError, match="reduction must be one of butterfly, tree"):
        replay_of(store, recorded[0], reduction="ring")


def test_a_long_all_reduction_costs_its_halving_and_doubling(store, recorded):
    """From ``SCATTER_MIN_BYTES`` an all-reduction scatters, as the tree-reduce actor does:
    2 log2 C steps of halves, quarters, ... of the array instead of log2 C whole ones (two
    whole fold steps more where P is no power of two); on 1,024 nodes a t-buffer of 32 MB
    costs a fraction of its whole-array steps."""
    from vastray.transport.tree import SCATTER_MIN_BYTES

    replay = replay_of(store, recorded[0], network=Network(latency_s=1e-3, bandwidth=1e9))
    long = float(SCATTER_MIN_BYTES)
    for nodes, core_steps in ((8, 3), (12, 3)):
        halves = sum(replay._step_s(long / 2 ** (s + 1)) for s in range(core_steps))
        folds = 2 * replay._step_s(long) if nodes == 12 else 0.0
        assert replay._allreduce_s(nodes, long) == pytest.approx(2 * halves + folds, rel=1e-12)
    assert replay._allreduce_s(8, long - 1) == pytest.approx(3 * replay._step_s(long - 1))
    t_buffer = 8.0 * 4096 * 1024
    assert replay._allreduce_s(1024, t_buffer) < 0.4 * 10 * replay._step_s(t_buffer)


def test_spec_insitu_reduces_the_paths_in_flight_not_the_whole_tile(store, recorded):
    """As the nodes' ``_reduce_buffers``: the first iteration's buffers cover the tile, the
    next ones the paths whose last iteration hit something; what the replay charges for
    them lies between one whole-tile reduction an iteration and the first one alone."""
    c = recorded[0]
    replay = replay_of(store, c, tile=c.n_paths,
                       network=Network(latency_s=1e-4, bandwidth=1e8))
    result = replay.run("spec-insitu", 4)
    iterations = result.counters["rounds"]  # each: the buffers' all-reduction
    shadow = c.kind != RADIANCE
    slots = int(np.bincount(c.parent[shadow & (c.parent >= 0)]).max())
    whole = replay._allreduce_s(4, c.n_paths * (8.0 + slots / 8.0))
    reduced = result.breakdown["reduction"]
    assert iterations >= 3
    assert whole + (iterations - 1) * replay._allreduce_s(4, 0.0) < reduced
    assert reduced < 0.95 * iterations * whole


def test_a_slower_network_costs_the_schedules_that_move_rays(store, recorded):
    fast = replay_of(store, recorded[0])
    slow = replay_of(store, recorded[0], network=Network(latency_s=5e-3, bandwidth=1e6))
    for scheduler in ("domain", "async", "spec-insitu", "dynamic"):
        assert slow.run(scheduler, 4).seconds > fast.run(scheduler, 4).seconds, scheduler
    assert slow.run("image", 4).seconds == fast.run("image", 4).seconds


def test_measured_loads_replace_the_constants_read_then_build(store, recorded):
    """``loads``: each domain's read and build as measured (the real-code simulator's
    ``Domains.load_seconds``) is what a load costs; the storage floor lengthens the read."""
    n = len(store.domains)
    read, build = np.full(n, 0.01), np.arange(n) * 1e-3
    once = replay_of(store, recorded[0], loads=(read, build))
    twice = replay_of(store, recorded[0], loads=(2 * read, 2 * build))
    assert np.allclose(once.load_s, read + build)
    a, b = once.run("image", 1), twice.run("image", 1)
    assert a.counters["loads"] == b.counters["loads"] > 0
    assert b.breakdown["load"] == pytest.approx(2 * a.breakdown["load"], rel=1e-9)
    assert b.seconds > a.seconds
    nbytes = domain_sizes(store)[0]
    slow = replay_of(store, recorded[0], loads=(read, build),
                     storage_bandwidth=float(nbytes.max()))  # 1 s for the largest read
    assert np.allclose(slow.load_s, np.maximum(read, nbytes / nbytes.max()) + build)


def test_loads_follow_the_cache(replay):
    """A sort-first node with room for everything loads each domain once; a cache of one
    domain loads more."""
    roomy = replay.run("image", 1)
    assert roomy.counters["loads"] <= replay.n_domains
    assert replay.run("image", 1, cache=1).counters["loads"] > roomy.counters["loads"]


def test_the_activation_costs_are_fitted_to_the_recording(recorded):
    c, _ = recorded
    fitted = fit_activation_costs(c, CostModel())
    assert fitted.radiance_s >= 0 and fitted.shadow_s >= 0
    assert fitted.radiance_s + fitted.shadow_s > 0
    constants = ActivationCosts.of(CostModel())
    assert constants.seconds(2, 5) == pytest.approx(CostModel().trace_s(2, 3))


def test_a_sort_first_decision_cost_is_interpolated_by_the_node_s_tile():
    a = ActivationCosts(0.0, 0.0, 0.0, 0.0, decision_s=1e-5,
                        sort_first_decision_s={"spec-ooc": ((100, 1e-4), (10_000, 3e-4))})
    assert a.tile_decision_s("spec-ooc", 100) == pytest.approx(1e-4)
    assert a.tile_decision_s("spec-ooc", 1_000) == pytest.approx(2e-4)  # half way in log
    assert a.tile_decision_s("spec-ooc", 10) == pytest.approx(1e-4)  # the nearest beyond
    assert a.tile_decision_s("spec-ooc", 10**6) == pytest.approx(3e-4)
    assert a.tile_decision_s("image", 1_000) is None  # not measured: decision_s


def test_sort_first_nodes_pay_their_measured_decisions(store, recorded):
    """The product's loop on one virtual node decides for a CPU time per activation that is
    spec-ooc's more than image's (it filters, guesses and ranks); a replay charges each
    activation of a sort-first node that, and nothing changes for the others."""
    from vastray.render.driver import shading_inputs
    from vastray.sim.cache import Domains
    from vastray.sim.replay import sort_first_decisions

    domains = Domains(store, shading_inputs(store, SceneConfig(), SETTINGS.integrator)[1])
    try:
        measured = sort_first_decisions(store, SETTINGS, domains, None, (160, 640))
    finally:
        domains.close()
    assert set(measured) == {"image", "spec-ooc"}
    for points in measured.values():
        assert [paths for paths, _ in points] == [160, 640]
        assert all(0 < seconds < 0.05 for _, seconds in points)
    crossings = recorded[0]
    fitted = fit_activation_costs(crossings, CostModel())
    # a tile as large as the frame: each of the 2 nodes traces half of it in one tile
    plain = replay_of(store, crossings, fitted, tile=crossings.n_paths)
    charged = replay_of(store, crossings,
                        dataclasses.replace(fitted, sort_first_decision_s=measured),
                        tile=crossings.n_paths)
    for scheduler in ("image", "spec-ooc"):
        before, after = plain.run(scheduler, 2), charged.run(scheduler, 2)
        activations = after.counters["activations"]
        assert activations == before.counters["activations"] > 0
        tile = -(-crossings.n_paths // 2)
        extra = activations * (charged.activation.tile_decision_s(scheduler, tile)
                               - fitted.decision_s)
        # (the breakdown's trace is the mean over the 2 nodes)
        assert 2 * after.breakdown["trace"] == pytest.approx(
            2 * before.breakdown["trace"] + extra, rel=1e-6)
    # nor for the others, after a sort-first run on the same replay (`async`'s node
    # activations once paid the last sort-first schedule's decision)
    for scheduler in ("domain", "async"):
        assert charged.run(scheduler, 2).seconds == plain.run(scheduler, 2).seconds


@pytest.mark.parametrize("nodes", [1, 2])
def test_spec_ooc_activates_as_many_domains_as_the_real_loop(store, recorded, nodes):
    """A replayed spec-ooc node goes round by round, as ``SpeculativeSchedule``: every
    domain with rays at most once a round, cached first, then by front-to-back score. Picking
    the fullest domain at every step instead activated a domain again for every few rays
    that reached it: 13,659 activations against the real loop's 2,547 on one node of the
    1,439-domain store (a replayed frame 4.2 times the real-code simulator's)."""
    from vastray.actors.job_options import JobOptions
    from vastray.sim.simulate import simulate

    crossings = recorded[0]
    tile = crossings.n_paths
    replayed = replay_of(store, crossings, tile=tile).run("spec-ooc", nodes)
    simulated = simulate(store, JobOptions(scheduler="spec-ooc", max_samples_in_flight=tile),
                         nodes, CostModel(), SETTINGS, max_pass_spp=None)
    real = simulated.counters["activations"]
    assert 0.75 * real <= replayed.counters["activations"] <= 1.35 * real, (
        replayed.counters["activations"], real)


def test_a_spec_ooc_round_takes_each_domain_once_cached_first_then_by_score():
    from vastray.sim.replay import _Queues

    queues = _Queues(4)
    queues.push(np.array([0, 1, 1, 2, 3]), np.arange(5), np.array([1, 4, 4, 9, 2]))
    visited = np.zeros(4, bool)
    cached = np.array([False, False, False, True])
    order = []
    while (domain := queues.next_in_round(cached, visited)) is not None:
        order.append(domain)
        visited[domain] = True
        queues.pop(domain)
        if domain == 3:  # rays for a domain this round has passed wait for the next one
            queues.push(np.array([3]), np.array([9]), np.array([50]))
    assert order == [3, 2, 1, 0]
    assert queues.counts[3] == 1 and queues.next_in_round(cached, visited) is None
    visited[:] = False
    assert queues.next_in_round(cached, visited) == 3


@pytest.mark.parametrize("scheduler", REPLAY_SCHEDULERS)
def test_the_busiest_node_is_the_one_whose_busy_time_is_the_most(replay, scheduler):
    result = replay.run(scheduler, 4)
    kinds = ("trace", "load", "messages", "reduction", "own")
    busiest = result.busiest
    assert 0 <= busiest["rank"] < 4
    mean_busy = sum(result.breakdown[k] for k in kinds)
    assert sum(busiest[k] for k in kinds) >= mean_busy - 1e-12
    assert sum(busiest[k] for k in kinds) <= result.seconds + 1e-9


def test_the_replay_refuses_what_it_does_not_model(replay):
    with pytest.raises(ValueError, match="temporal"):
        replay.run("temporal", 2)
    with pytest.raises(ValueError, match="at least 1"):
        replay.run("domain", 0)
    assert set(REPLAY_SCHEDULERS) >= set(LOSSLESS_NON_SPECULATIVE)


def test_a_repeated_frame_is_the_same_work_over_more_paths(store, recorded, replay):
    c, _ = recorded
    twice = c.repeated(3)
    assert twice.n_paths == 3 * c.n_paths and len(twice) == 3 * len(c)
    assert np.array_equal(np.sort(twice.path[twice.parent < 0]), np.arange(twice.n_paths))
    assert np.array_equal(twice.visits, np.tile(c.visits, 3))
    seg = len(c) + int(np.nonzero(c.visits > 1)[0][0])
    original = seg - len(c)
    assert np.array_equal(twice.visit_domain[twice.visit_first[seg]:twice.visit_first[seg + 1]],
                          c.visit_domain[c.visit_first[original]:c.visit_first[original + 1]])
    spawned = np.nonzero(twice.parent >= 0)[0]
    assert np.array_equal(twice.path[twice.parent[spawned]], twice.path[spawned])
    more = replay_of(store, twice, replay.activation)
    assert more.run("async", 2).counters["traced"] == 3 * c.visits.sum()


def test_a_subset_keeps_every_stride_th_path_and_its_rays(recorded):
    c, _ = recorded
    third = c.subset(3)
    assert third.n_paths == -(-c.n_paths // 3)
    assert np.array_equal(np.sort(third.path[third.parent < 0]), np.arange(third.n_paths))
    kept = np.nonzero(c.path % 3 == 0)[0]
    assert np.array_equal(third.visits, c.visits[kept])
    assert np.array_equal(third.copies, c.copies[kept])
    spawned = np.nonzero(third.parent >= 0)[0]
    assert np.array_equal(third.path[third.parent[spawned]], third.path[spawned])


def test_sort_first_nodes_on_copies_of_the_same_paths_cost_the_same(store, recorded, replay):
    """A repeated frame's sort-first nodes with the same base paths are replayed once: the
    result must equal replaying every node."""
    c, _ = recorded
    twice = c.repeated(2)
    fast = replay_of(store, twice, replay.activation)
    plain = dataclasses.replace(twice)  # no ``period``: every node replayed
    slow = replay_of(store, plain, replay.activation)
    # tiles of 600 paths dealt round robin, then a band a node cut by cost
    for tile, scheduler in itertools.product((600, 65536), ("image", "spec-ooc")):
        fast.tile = slow.tile = tile
        a, b = fast.run(scheduler, 4), slow.run(scheduler, 4)
        assert a.seconds == b.seconds and a.counters == b.counters, scheduler
        assert np.allclose(list(a.breakdown.values()), list(b.breakdown.values()))


def test_the_replay_cuts_sort_first_bands_at_equal_estimated_cost(recorded, replay):
    """As the nodes (``image_cost``): a path weighs 1 + PER_DOMAIN x the domains its camera
    ray's line crosses; the bands' weights differ by a path's at most, their paths do not."""
    from vastray.schedule.image_cost import PER_DOMAIN
    from vastray.schedule.ownership import weighted_band_cuts

    c, _ = recorded
    camera = np.nonzero(c.parent < 0)[0]
    weight = np.ones(c.n_paths, np.int64)
    weight[c.path[camera]] += PER_DOMAIN * c.copies[camera]
    cuts = weighted_band_cuts(replay.band_weights(), c.n_paths, 3)
    band = [int(weight[a:b].sum()) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    assert max(band) - min(band) <= 2 * weight.max()
    assert len(set(np.diff(cuts).tolist())) > 1


# -- the nodes' own code -------------------------------------------------------------------
@pytest.mark.parametrize("scheduler", REPLAY_SCHEDULERS)
def test_a_node_s_frame_set_up_makes_the_frame_that_much_later(store, recorded, scheduler):
    plain = replay_of(store, recorded[0]).run(scheduler, 4)
    own = replay_of(store, recorded[0],
                    own={scheduler: NodeOwnCosts(per_node_s=0.5)}).run(scheduler, 4)
    assert own.seconds == pytest.approx(plain.seconds + 0.5, rel=1e-9)
    assert own.breakdown["own"] == pytest.approx(0.5)


@pytest.mark.parametrize("scheduler", ["domain", "dynamic", "async", "spec-insitu"])
def test_each_batch_s_own_code_is_charged_to_its_sender_and_its_receiver(store, recorded,
                                                                         scheduler):
    plain = replay_of(store, recorded[0]).run(scheduler, 4)
    costs = NodeOwnCosts(sent_s=1e-3, received_s=2e-3)
    own = replay_of(store, recorded[0], own={scheduler: costs}).run(scheduler, 4)
    batches = own.counters["messages"]
    assert batches > 0 and own.seconds > plain.seconds
    # every batch once on each side (the all-reductions' messages are not ray batches)
    assert own.breakdown["own"] * 4 == pytest.approx(3e-3 * batches, rel=1e-9)
    # large beside the frame: an asynchronous frame's order moves with any cost, and a
    # cost of 1 us a ray could leave it a little faster by that alone
    by_ray = replay_of(store, recorded[0], own={scheduler: NodeOwnCosts(
        ray_sent_s=1e-4, ray_received_s=1e-4)}).run(scheduler, 4)
    assert by_ray.seconds > plain.seconds and by_ray.breakdown["own"] > 0


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc", "domain", "async"])
def test_each_activation_s_own_code_is_charged(store, recorded, scheduler):
    plain = replay_of(store, recorded[0]).run(scheduler, 4)
    own = replay_of(store, recorded[0],
                    own={scheduler: NodeOwnCosts(activation_s=1e-3)}).run(scheduler, 4)
    assert own.breakdown["own"] * 4 == pytest.approx(1e-3 * own.counters["activations"])
    assert own.seconds > plain.seconds


def test_only_the_scheduler_replayed_pays_its_own_code(store, recorded):
    replay = replay_of(store, recorded[0], own={"async": NodeOwnCosts(per_node_s=1.0)})
    assert replay.run("domain", 4).breakdown["own"] == 0.0
    assert replay.run("async", 4).breakdown["own"] == 1.0


def test_the_nodes_own_code_is_fitted_on_the_simulator_running_it(store):
    """Fitted on the real-code simulator: none negative, and not all zero (a node's own code
    costs something)."""
    from vastray.actors.job_options import JobOptions
    from vastray.render.driver import shading_inputs
    from vastray.sim.cache import Domains

    domains = Domains(store, shading_inputs(store, SceneConfig(), SETTINGS.integrator)[1])
    try:
        fitted = fit_node_own_costs(store, SETTINGS, domains, (2, 4),
                                    lambda s, n, paths: JobOptions(scheduler=s),
                                    schedulers=["async", "domain"])
    finally:
        domains.close()
    assert set(fitted) == {"async", "domain"}
    for costs in fitted.values():
        values = dataclasses.astuple(costs)
        assert all(v >= 0 for v in values) and sum(values) > 0


def test_the_replay_s_default_tile_is_the_coordinator_s_for_each_node_count(
        store, recorded, monkeypatch):
    """Tile None: each run takes ``default_tile`` for its scheduler and node count (here
    scaled down: 600 paths, 150 a node), so 8 nodes run tiles of 1,200 paths, in fewer
    rounds than tiles of 600; 2 nodes keep 600."""
    from vastray.actors import job_options

    monkeypatch.setattr(job_options, "DEFAULT_NODE_TILE", 600)
    monkeypatch.setattr(job_options, "MIN_NODE_SHARE", 150)
    crossings = recorded[0]
    default = replay_of(store, crossings, tile=None)
    for nodes, tile in ((2, 600), (8, 1200)):
        ran = default.run("domain", nodes)
        fixed = replay_of(store, crossings, tile=tile).run("domain", nodes)
        assert (ran.seconds, ran.counters) == (fixed.seconds, fixed.counters)
    assert (default.run("domain", 8).counters["rounds"]
            < replay_of(store, crossings, tile=600).run("domain", 8).counters["rounds"])


def test_spec_insitu_relays_over_the_routes_and_can_replay_the_straight_sends(store, recorded):
    """The product's two hops: a batch per pair of ``relay.routes``, queue and hop, every
    iteration, and one all-reduction an iteration; straight (before session 52): a batch per
    pair with copies and the (P,) counts all-reduced first. Both trace every copy once."""
    from vastray.schedule.relay import routes

    c = recorded[0]
    replay = replay_of(store, c, tile=c.n_paths)
    replay.insitu_holders = "owner"
    relayed = replay.run("spec-insitu", 5)
    replay.insitu_routes = "straight"
    straight = replay.run("spec-insitu", 5)
    iterations = relayed.counters["rounds"]
    assert straight.counters["rounds"] == 2 * iterations
    first, second = routes(5)
    assert relayed.counters["messages"] == 2 * iterations * (len(first.source)
                                                             + len(second.source))
    assert straight.counters["messages"] <= 2 * iterations * 5 * 4
    assert relayed.counters["traced"] == straight.counters["traced"] == c.copies.sum()


def test_spec_insitu_with_holders_by_camera_crossings_traces_each_copy_once(store, recorded):
    """``insitu_holders="camera"`` (the product's): the most-crossed domains get more
    holders where the bytes allow; a copy is still traced once, as with one holder a
    domain, and a holder loads what it holds."""
    c = recorded[0]
    replay = replay_of(store, c, tile=c.n_paths)
    assert replay.insitu_holders == "camera"
    replay.insitu_holders = "owner"
    owned = replay.run("spec-insitu", 4)
    replay.insitu_holders = "camera"
    from vastray.schedule.ownership import Holders, insitu_owners

    owner = insitu_owners(*store.domain_boxes(), store.domain_triangles(), 4)
    holding = replay._insitu_holding(owner, 4)
    held = replay.run("spec-insitu", 4)
    assert held.counters["traced"] == owned.counters["traced"] == c.copies.sum()
    assert owned.counters["loads"] == c.n_domains
    assert held.counters["loads"] == holding.count.sum() >= c.n_domains
    # this store's crossings are even, so no domain reaches two shares: given holders, every
    # domain on its owner and the next node, each copy is still traced once, each holder
    # loads what it holds, and the traces spread over the nodes
    two = Holders(np.arange(0, 2 * c.n_domains + 1, 2),
                  np.stack([owner, (owner + 1) % 4], axis=1).ravel())
    replay.insitu_holders = two
    shared = replay.run("spec-insitu", 4)
    assert shared.counters["traced"] == c.copies.sum()
    assert shared.counters["loads"] == 2 * c.n_domains
    replay.insitu_holders = "everywhere"
    with pytest.raises(ValueError, match="owner or camera"):
        replay.run("spec-insitu", 4)
