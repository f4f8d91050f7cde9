"""``vastray simulate`` (``vastray.sim``): the virtual clock, the virtual cluster and domain
cache, the cost model, simulated renders of every scheduler (their images bit for bit the
reference's, their time the cost model's), the command, and one check against real runs."""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import itertools
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions
from vastray.actors.node import frame_inputs
from vastray.render.driver import render, shading_inputs
from vastray.render.imageio import read_image
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.errors import InputError
from vastray.scene.generate import generate
from vastray.scene.store import Store
from vastray.schedule.registry import Runtime, running
from vastray.sim.cache import Domains, VirtualPreloader
from vastray.sim.clock import Deadlock, run_virtual
from vastray.sim.cluster import Cluster
from vastray.sim.cores import SharedCores
from vastray.sim.costs import CostModel
from vastray.sim.simulate import SIM_SCHEDULERS, node_options, simulate
from vastray.transport.codec import Message

from scenes import rm_store

#: A tiny render: two samples in one pass (the default passes are of 16 spp).
SETTINGS = RenderSettings(width=32, height=24, spp=2, bounces=1, shadow_samples=2, seed=3)
COSTS = CostModel()
#: Every cost 0: a test sets the ones it looks at.
ZERO = CostModel.free()
#: The trace costs (per query and per activation).
TRACE_COSTS = ("trace_ray_s", "shade_ray_s", "shadow_ray_s", "activation_s",
               "shadow_activation_s")
#: The schedulers that run sort-first tiles.
TILE_SCHEDULERS = running(Runtime.TILES)
#: The schedulers whose nodes run the node runtimes (the others run sort-first tiles).
NODE_SCHEDULERS = tuple(s for s in SIM_SCHEDULERS if s not in TILE_SCHEDULERS)


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Store:
    return rm_store(tmp_path_factory.mktemp("simulate") / "rm.store", 32, (3, 2, 2))


@pytest.fixture(scope="module")
def domains(store):
    """The store's domains built once for every simulation of ``SETTINGS`` here."""
    built = Domains(store, shading_inputs(store, SceneConfig(), SETTINGS.integrator)[1])
    yield built
    built.close()


@pytest.fixture(scope="module")
def reference(store) -> np.ndarray:
    return render(store, SceneConfig(), SETTINGS, progress=False).film.image()


def sim(store, domains, scheduler: str, nodes: int, costs: CostModel = COSTS,
        settings: RenderSettings = SETTINGS, max_pass_spp: int | None = 16, **options):
    return simulate(store, JobOptions(scheduler=scheduler, **options), nodes, costs, settings,
                    max_pass_spp=max_pass_spp, domains=domains)


# -- the virtual clock ----------------------------------------------------------------------
def test_run_virtual_returns_the_result_and_the_virtual_seconds_at_once():
    async def main():
        await asyncio.gather(*(asyncio.sleep(100.0) for _ in range(5)))
        middle = asyncio.get_running_loop().time()
        await asyncio.sleep(2.5)
        return "done", middle

    start = time.perf_counter()
    (result, middle), seconds = run_virtual(main())
    assert result == "done" and middle == 100.0 and seconds == 102.5
    assert time.perf_counter() - start < 5  # no real sleeping


def test_a_timeout_fires_in_virtual_time_not_as_a_deadlock():
    async def main():
        await asyncio.wait_for(asyncio.Queue().get(), 30.0)

    start = time.perf_counter()
    with pytest.raises(TimeoutError):
        run_virtual(main())
    assert time.perf_counter() - start < 5


def test_waiting_forever_is_a_deadlock_and_leaves_no_task_behind(caplog, recwarn):
    waiting = []

    async def main():
        waiting.append(asyncio.ensure_future(asyncio.Queue().get()))  # a second waiter
        await asyncio.sleep(5.0)
        await asyncio.Queue().get()

    with pytest.raises(Deadlock):
        run_virtual(main())
    assert waiting[0].cancelled()
    waiting.clear()
    gc.collect()
    assert not [r for r in caplog.records if "destroyed but it is pending" in r.getMessage()]
    assert not [w for w in recwarn if "never awaited" in str(w.message)]
    # the loop is closed and a fresh one works
    assert run_virtual(asyncio.sleep(1.0, result=7)) == (7, 1.0)


# -- the cost model -------------------------------------------------------------------------
def test_trace_seconds_are_the_activation_plus_the_queries():
    c = CostModel(trace_ray_s=1.0, shade_ray_s=2.0, shadow_ray_s=4.0, activation_s=100.0,
                  shadow_activation_s=1000.0)
    assert c.trace_s(3, 5) == 100 + 3 * 3 + 5 * 4
    assert c.trace_s(0, 5) == 1000 + 5 * 4  # a shadow-only activation's fixed cost
    assert c.trace_s(1, 0) == 100 + 3
    assert c.load_s(10, 3) == 10 * c.load_byte_s + 3 * c.build_triangle_s
    assert c.message_s(1000) == c.latency_s + 1000 * c.byte_s


def test_a_free_cost_model_charges_nothing():
    free = CostModel.free()
    numbers = {k: v for k, v in dataclasses.asdict(free).items() if isinstance(v, float)}
    assert numbers and all(v == 0.0 for v in numbers.values()), numbers
    assert free.cores is None and free.throughput == ()
    assert free.trace_s(3, 5) == 0.0 and free.load_s(10, 3) == 0.0 and free.message_s(99) == 0.0


def test_a_trace_is_charged_its_cpu_time_where_trace_scale_is_set_else_the_constants():
    c = CostModel(trace_ray_s=1.0, shade_ray_s=2.0, shadow_ray_s=4.0, activation_s=100.0)
    assert c.trace_charge(3, 5, cpu_seconds=0.25) == c.trace_s(3, 5)
    assert dataclasses.replace(c, trace_scale=2.0).trace_charge(3, 5, cpu_seconds=0.25) == 0.5


@pytest.mark.parametrize("scheduler", ["image", "domain", "async", "spec-insitu"])
def test_traces_charged_at_their_cpu_time_cost_what_the_simulator_spent_tracing(
        store, domains, scheduler, monkeypatch):
    """With every other cost 0, the simulated seconds are the CPU time the virtual node's
    traces took here: more than nothing and at most the simulation's own time. At trace_scale
    2 they are twice what the same clock readings cost at trace_scale 1: checked on a clock
    that ticks 1 ms per reading, since two real runs' CPU times differ by 2x on a busy
    machine (CI once saw 3.5x between two runs of the same work)."""
    once = sim(store, domains, scheduler, 1, dataclasses.replace(ZERO, trace_scale=1.0))
    assert 0.0 < once.seconds <= once.wall_s

    charged = charged_on_a_ticking_clock(monkeypatch, lambda scale: sim(
        store, domains, scheduler, 1, dataclasses.replace(ZERO, trace_scale=scale)).seconds)
    assert charged[1.0] > 0.0
    assert charged[2.0] == pytest.approx(2.0 * charged[1.0], rel=1e-9)


def charged_on_a_ticking_clock(monkeypatch, seconds_at) -> dict[float, float]:
    """``seconds_at(scale)`` for scales 1 and 2, each run with every CPU clock a simulation
    reads (``launch.cpu_time`` where each module imported it) ticking 1 ms a reading."""
    import vastray.actors.domain_loop
    import vastray.actors.dynamic_frame
    import vastray.actors.insitu
    import vastray.sim.crossings
    import vastray.sim.meter
    import vastray.sim.node

    charged = {}
    for scale in (1.0, 2.0):
        readings = itertools.count(1)
        for module in (vastray.actors.domain_loop, vastray.actors.insitu,
                       vastray.actors.dynamic_frame, vastray.sim.crossings, vastray.sim.node,
                       vastray.sim.meter):
            monkeypatch.setattr(module, "cpu_time", lambda r=readings: next(r) * 1e-3)
        charged[scale] = seconds_at(scale)
    return charged


@pytest.mark.parametrize("scheduler", SIM_SCHEDULERS)
def test_a_node_runtime_pays_the_hand_off_of_each_activation_and_a_sort_first_node_not(
        store, domains, scheduler, monkeypatch):
    """``offload_s`` is charged per activation the real node's loop hands to a worker thread
    (the domain-decomposition runtimes' larger ones, ``hands_off``), not for sort-first tiles
    (their own thread) nor in situ (traced on the event loop's thread)."""
    import vastray.actors.domain_loop as domain_loop

    costs = dataclasses.replace(ZERO, offload_s=0.01)
    result = sim(store, domains, scheduler, 1, costs, max_pass_spp=None)
    # this store's activations are small: a node traces them on its loop's thread
    assert result.seconds < 0.01 and "handed_off" not in result.counters
    # every one with a ray handed off (decided on the rays waiting before the trace, as the
    # real loop decides: after it they are gone, and the simulator once charged half the
    # hand-offs a real node made, 60 of 120)
    monkeypatch.setattr(domain_loop, "INLINE_RAYS", 0)
    result = sim(store, domains, scheduler, 1, costs, max_pass_spp=None)
    if scheduler in NODE_SCHEDULERS and scheduler != "spec-insitu":
        assert result.counters["handed_off"] == result.counters["activations"] > 0
        assert result.seconds == pytest.approx(0.01 * result.counters["activations"], rel=0.02)
    else:
        assert result.seconds < 0.01 and "handed_off" not in result.counters


@pytest.mark.parametrize("bad", [{"latency_s": -1e-6}, {"trace_ray_s": math.nan},
                                 {"byte_s": math.inf}, {"warmup_s": "1"}, {"cores": 0},
                                 {"cores": 1.5}])
def test_a_cost_model_refuses_negative_or_non_finite_values(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        CostModel(**bad)


def test_with_cores_and_warm_change_only_their_fields():
    c = CostModel(warmup_s=1.0, node_setup_s=2.0, tile_setup_s=3.0, latency_s=7e-4, cores=2,
                  machine={"hostname": "h", "calibration": {"quick": True}})
    assert c.with_cores(None).cores is None and c.with_cores(8).cores == 8
    assert dataclasses.replace(c.with_cores(8), cores=2) == c
    warm = c.warm()
    assert (warm.warmup_s, warm.node_setup_s, warm.tile_setup_s) == (0.0, 0.0, 0.0)
    assert dataclasses.replace(warm, warmup_s=1.0, node_setup_s=2.0, tile_setup_s=3.0) == c
    assert c.warmup_s == 1.0  # frozen: the original is untouched
    # a warm node's memory was touched by its earlier jobs; a fault still costs what it costs
    touching = CostModel(page_fault_s=3e-6, fresh_pages_per_path=0.25)
    assert touching.first_touch_s(4000) == pytest.approx(3e-3)
    assert touching.warm().first_touch_s(4000) == 0.0 and touching.warm().page_fault_s == 3e-6


def test_a_hand_made_model_round_trips_and_unknown_or_bad_fields_are_refused(tmp_path):
    path = tmp_path / "costs.json"
    model = CostModel(latency_s=3e-5, warmup_s=0.25, cores=None,
                      machine={"hostname": "x", "calibration": {"quick": False}})
    model.save(path)
    assert CostModel.load(path) == model
    data = json.loads(path.read_text())
    path.write_text(json.dumps({**data, "latency": 1e-4}))
    with pytest.raises(InputError, match="unknown cost fields") as err:
        CostModel.load(path)
    assert str(path) in str(err.value)
    for field, value in (("cores", 0), ("load_byte_s", float("nan"))):
        path.write_text(json.dumps({**data, field: value}))
        with pytest.raises(InputError, match=field):
            CostModel.load(path)


# -- the virtual cluster --------------------------------------------------------------------
def test_compute_overlaps_on_own_cores_and_shares_shared_ones():
    async def work(costs):
        cluster = Cluster(3, costs)
        await asyncio.gather(*(cluster.compute(rank, 1.0) for rank in range(3)))
        return cluster.compute_s

    compute_s, seconds = run_virtual(work(COSTS))
    assert seconds == 1.0 and list(compute_s) == [1.0, 1.0, 1.0, 0.0]
    # processor sharing: three jobs on two cores all run at 2/3 speed
    assert run_virtual(work(COSTS.with_cores(2)))[1] == pytest.approx(1.5)
    assert run_virtual(work(COSTS.with_cores(1)))[1] == pytest.approx(3.0)
    # a machine whose 2 cores give 1.5 cores' work with 2 or more busy processes
    slow = dataclasses.replace(COSTS, cores=2, throughput=(1.0, 1.5))
    assert run_virtual(work(slow))[1] == pytest.approx(2.0)


def test_a_job_wider_than_a_core_uses_the_cores_no_other_process_is_using():
    """An Embree build keeps more than one core busy: alone on the machine it runs at its
    width, up to the cores; beside another busy process on 2 cores it gets one core until
    that process is done; on one core, or beside another job of its own process, one core."""
    async def alone(cores, seconds, width):
        await SharedCores(cores).run(seconds, owner=0, width=width)

    assert run_virtual(alone(2, 1.8, 1.8))[1] == pytest.approx(1.0)
    assert run_virtual(alone(2, 3.0, 4.0))[1] == pytest.approx(1.5)  # at most the cores
    assert run_virtual(alone(1, 1.8, 1.8))[1] == pytest.approx(1.8)  # no spare core

    async def beside(second_owner):
        cores = SharedCores(2)
        loop = asyncio.get_running_loop()
        ends = {}

        async def job(name, seconds, owner, width=1.0):
            await cores.run(seconds, owner=owner, width=width)
            ends[name] = loop.time()

        await asyncio.gather(job("build", 1.8, 0, 1.8), job("trace", 0.5, second_owner))
        return ends

    ends = run_virtual(beside(1))[0]
    # a core each until the trace is done at 0.5 s; then the build's last 1.3 s at 1.8 cores
    assert ends["trace"] == pytest.approx(0.5)
    assert ends["build"] == pytest.approx(0.5 + 1.3 / 1.8)
    ends = run_virtual(beside(0))[0]  # the trace is the build's own process's: one core
    # between them until the trace is done at 1 s; then the build alone, 1.8 cores wide
    assert ends["trace"] == pytest.approx(1.0)
    assert ends["build"] == pytest.approx(1.0 + 1.3 / 1.8)

    async def narrow():
        await SharedCores(2).run(1.0, width=0.5)

    with pytest.raises(ValueError, match="width"):
        run_virtual(narrow())


def test_a_temporal_run_too_large_for_this_machine_is_refused_saying_why():
    from vastray.scene.errors import InputError
    from vastray.sim.simulate import _check_memory

    with pytest.raises(InputError, match=r"temporal on 1024 virtual nodes .* GiB"):
        _check_memory("temporal", 1024, 1439)
    _check_memory("temporal", 16, 1439)  # fits
    _check_memory("async", 1024, 1439)  # no (D, D) state


def test_a_run_whose_nodes_path_state_cannot_fit_is_refused_naming_the_tile():
    from vastray.actors.job_options import JobOptions
    from vastray.scene.errors import InputError
    from vastray.sim.simulate import _check_path_memory, node_options

    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    paths = 1 << 22
    # from 1,024 nodes the default tile is the cap, 4,194,304 paths, on each virtual node
    nodes = max(1024, int(memory // (64 * paths)) + 1)
    with pytest.raises(InputError, match=rf"domain on {nodes} virtual nodes with tiles of "
                                         r"4,194,304 paths .*--max-samples-in-flight"):
        _check_path_memory(node_options(JobOptions(scheduler="domain"), nodes), nodes, paths)
    _check_path_memory(node_options(JobOptions(scheduler="domain", max_samples_in_flight=4096),
                                    nodes), nodes, paths)  # a smaller tile fits
    _check_path_memory(node_options(JobOptions(scheduler="image"), nodes), nodes, paths)


def test_shared_cores_speed_jobs_up_as_others_finish():
    async def work():
        cores = SharedCores(1)
        short = asyncio.ensure_future(cores.run(1.0))
        long = asyncio.ensure_future(cores.run(3.0))
        await short
        at_short = asyncio.get_running_loop().time()
        await long
        return at_short

    at_short, seconds = run_virtual(work())
    # both at half speed until the short one is done (2 s), then the long one alone
    assert at_short == pytest.approx(2.0) and seconds == pytest.approx(4.0)
    with pytest.raises(ValueError, match="throughput"):
        CostModel(throughput=(1.0, -1.0))

def test_a_message_costs_its_receiver_too_and_arrives_in_order():
    costs = CostModel(latency_s=0.5, byte_s=0.0, receive_s=0.25)

    async def main():
        cluster = Cluster(2, costs)
        loop = asyncio.get_running_loop()

        async def sender():
            for n in range(3):
                await cluster.send(0, 1, Message("rays", {}, {"n": n}), 10)

        sending = asyncio.ensure_future(sender())
        box = cluster.mailboxes[1]["rays"]
        first = await box.get()
        at_first = loop.time()
        rest = [await box.get() for _ in range(2)]
        await sending
        return cluster, [first, *rest], at_first

    (cluster, got, at_first), seconds = run_virtual(main())
    assert [m.meta["n"] for m in got] == [0, 1, 2]
    # the first is in after its send and its receipt; the receiver takes them one at a
    # time while the sender sends the next (the last: 3 sends, then its receipt)
    assert at_first == pytest.approx(0.5 + 0.25)
    assert seconds == pytest.approx(3 * 0.5 + 0.25)
    assert cluster.compute_s[0] == pytest.approx(1.5)
    assert cluster.compute_s[1] == pytest.approx(3 * 0.25)


def test_a_node_process_computes_on_one_core_however_many_jobs_it_has():
    """Two cores: node 0's trace and its load (two jobs of one process, its GIL) take turns
    on one core, while node 1's trace has the other core to itself."""
    async def work():
        cores = SharedCores(2)
        loop = asyncio.get_running_loop()
        finished = {}

        async def job(name, seconds, owner):
            await cores.run(seconds, owner=owner)
            finished[name] = loop.time()

        await asyncio.gather(job("trace 0", 2.0, 0), job("load 0", 1.0, 0),
                             job("trace 1", 2.0, 1))
        return finished

    finished, seconds = run_virtual(work())
    # node 0's two jobs at half a core each until the load is done (2 s), then its trace alone
    assert finished["load 0"] == pytest.approx(2.0)
    assert finished["trace 0"] == pytest.approx(3.0)
    assert finished["trace 1"] == pytest.approx(2.0)
    assert seconds == pytest.approx(3.0)

    async def without_owners():
        cores = SharedCores(2)
        await asyncio.gather(cores.run(2.0), cores.run(1.0), cores.run(2.0))

    # three processes of their own on two cores: 2/3 of a core each until the short one is
    # done (1.5 s), then a core each for the 1 s left of the others
    assert run_virtual(without_owners())[1] == pytest.approx(1.5 + 1.0)



def test_a_message_costs_its_sender_and_lands_in_the_mailbox_of_its_kind():
    costs = CostModel(latency_s=0.5, byte_s=1e-3)

    async def main():
        cluster = Cluster(2, costs)
        await cluster.send(0, 1, Message("rays", {}, {"n": 1}), 1000)
        await cluster.send(1, cluster.coordinator, Message("status", {}, {"n": 2}), 10)
        box = cluster.mailboxes[1]["rays"]
        return cluster, box.get_nowait(), cluster.mailboxes[2]["status"].get_nowait()

    (cluster, rays, status), seconds = run_virtual(main())
    assert rays.meta == {"n": 1} and status.meta == {"n": 2}
    assert seconds == pytest.approx(costs.message_s(1000) + costs.message_s(10))
    assert cluster.compute_s[0] == pytest.approx(costs.message_s(1000))
    assert cluster.compute_s[1] == pytest.approx(costs.message_s(10))
    assert cluster.compute_s[2] == 0.0
    assert (cluster.messages, cluster.bytes) == (2, 1010)


def test_only_the_first_trace_of_a_node_pays_its_warm_up_and_set_up():
    costs = CostModel(warmup_s=10.0, node_setup_s=1.0, tile_setup_s=100.0)

    async def main():
        cluster = Cluster(2, costs)
        await cluster.trace(0, 0.5, runtime="node")
        await cluster.trace(0, 0.5, runtime="node")
        await cluster.trace(1, 0.5, runtime="tile")
        return cluster.compute_s

    compute_s, _ = run_virtual(main())
    assert list(compute_s) == [11.0 + 1.0, 110.5, 0.0]


def test_a_fresh_node_pays_the_first_touch_of_its_paths_once_at_its_first_trace():
    costs = CostModel(warmup_s=1.0)

    async def main():
        cluster = Cluster(2, costs, first_touch_s=0.25)
        await cluster.trace(0, 0.5, runtime="node")
        await cluster.trace(0, 0.5, runtime="node")
        return cluster.compute_s

    compute_s, _ = run_virtual(main())
    assert list(compute_s) == [1.25 + 0.5 + 0.5, 0.0, 0.0]  # node 1 never traced: nothing


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc", "domain", "async", "spec-insitu"])
def test_a_simulation_charges_each_node_the_first_touch_of_its_share_of_paths(
        store, domains, scheduler):
    # constants only (no CPU measured), so the two simulations differ by the charge alone
    touching = dataclasses.replace(COSTS, page_fault_s=1e-3, fresh_pages_per_path=0.5)
    tile = 100  # paths in flight, below a node's share of SETTINGS' 1,536 paths
    options = {"max_samples_in_flight": tile}
    fresh = sim(store, domains, scheduler, 2, touching, **options)
    untouched = sim(store, domains, scheduler, 2, COSTS, **options)
    # a sort-first node's own tile; a domain-decomposition job's, each node starting half
    held = tile if scheduler in TILE_SCHEDULERS else tile // 2
    assert fresh.compute_seconds[:2] == pytest.approx(
        untouched.compute_seconds[:2] + touching.first_touch_s(held))
    # without a tile (the default one holds more), a node holds its share of the pass's paths
    assert node_options(JobOptions(scheduler=scheduler), 2).max_samples_in_flight > SETTINGS.paths
    for passes, share in ((None, SETTINGS.paths // 2), (1, SETTINGS.paths // 4)):  # 1 spp a pass
        whole = sim(store, domains, scheduler, 2, touching, max_pass_spp=passes)
        bare = sim(store, domains, scheduler, 2, COSTS, max_pass_spp=passes)
        assert whole.compute_seconds[:2] == pytest.approx(
            bare.compute_seconds[:2] + touching.first_touch_s(share))


# -- the virtual domain cache ---------------------------------------------------------------
def _preloader(domains, capacity: int, costs: CostModel, **kw):
    cluster = Cluster(1, costs)
    return cluster, VirtualPreloader(cluster, 0, domains, capacity, **kw)


LOADS = CostModel(load_byte_s=1e-6, build_triangle_s=1e-4)


def test_a_load_charges_its_cost_and_a_resident_domain_costs_nothing(domains):
    async def main():
        cluster, preloader = _preloader(domains, 2, LOADS)
        start = cluster.now()
        bvh = await preloader.get(3)
        loaded = cluster.now()
        again = await preloader.get(3)
        return preloader, bvh, again, loaded - start, cluster.now() - loaded

    preloader, bvh, again, load_s, hit_s = run_virtual(main())[0]
    expected = LOADS.load_s(int(domains.nbytes[3]), int(domains.triangles[3]))
    assert expected > 0 and load_s == pytest.approx(expected, rel=1e-12)
    assert hit_s == 0.0 and again is bvh is domains.get(3)
    stats = preloader.stats()
    assert stats["loads"] == 1 and stats["bytes_loaded"] == domains.nbytes[3]
    assert stats["load_wait_s"] == pytest.approx(expected, abs=1e-4)
    assert preloader.load_count(3) == 1 and preloader.resident() == {3}


def test_a_read_ahead_charges_the_read_while_the_node_works_and_the_load_only_builds(domains):
    async def main():
        cluster, preloader = _preloader(domains, 1, LOADS)
        await preloader.get(2)
        preloader.read_ahead(3)  # the cache is full: no slot taken, nothing evicted
        assert preloader.resident() == {2}
        await asyncio.sleep(1.0)  # the node idles long enough for the read
        start = cluster.now()
        await preloader.get(3)
        return preloader, cluster.now() - start

    preloader, load_s = run_virtual(main())[0]
    build = LOADS.build_s(int(domains.triangles[3]))
    read = LOADS.read_s(int(domains.nbytes[3]))
    assert read > 0 and load_s == pytest.approx(build, rel=1e-9)
    stats = preloader.stats()
    assert stats["reads_ahead"] == stats["reads_ahead_used"] == 1 and stats["loads"] == 2


def test_a_build_ahead_charges_its_load_while_the_node_works_and_evicts_when_taken(domains):
    async def main():
        cluster, preloader = _preloader(domains, 3, LOADS, build_ahead=True)
        assert preloader.builds_ahead
        await preloader.get(0)
        await preloader.get(1)
        assert preloader.resident() == {0, 1}  # full: one slot kept for the build ahead
        preloader.build_ahead(3)
        await asyncio.sleep(5.0)  # the node idles long enough for the read and the build
        assert preloader.resident() == {0, 1}  # nothing evicted for it yet
        start = cluster.now()
        await preloader.get(3)
        return preloader, cluster.now() - start

    preloader, wait_s = run_virtual(main())[0]
    assert wait_s == pytest.approx(0.0, abs=1e-9)  # its whole load ran ahead
    assert preloader.resident() == {1, 3}  # taken: the least recently used evicted then
    stats = preloader.stats()
    assert stats["builds_ahead"] == stats["builds_ahead_used"] == 1 and stats["loads"] == 3
    assert stats["peak_resident_domains"] <= 3


def test_a_full_cache_evicts_the_least_recently_used_domain(domains):
    async def main():
        cluster, preloader = _preloader(domains, 2, LOADS, preload=False)
        for d in (0, 1, 0, 2):  # 1 is the least recently used when 2 comes
            await preloader.get(d)
        resident = preloader.resident()
        start = cluster.now()
        await preloader.get(1)  # loaded again
        return resident, cluster.now() - start, preloader

    resident, reload_s, preloader = run_virtual(main())[0]
    assert resident == {0, 2}
    assert reload_s == pytest.approx(LOADS.load_s(int(domains.nbytes[1]),
                                                  int(domains.triangles[1])))
    assert preloader.load_count(1) == 2 and preloader.resident() == {2, 1}


def test_a_cache_of_one_reloads_every_switch_and_never_preloads(domains):
    async def main():
        cluster, preloader = _preloader(domains, 1, LOADS)
        for d in (0, 1, 0):
            await preloader.get(d)
            preloader.preload(5)  # no room for a preload beside the domain in use
        return cluster.now(), preloader

    seconds, preloader = run_virtual(main())[0]
    cost = [LOADS.load_s(int(domains.nbytes[d]), int(domains.triangles[d])) for d in (0, 1)]
    assert seconds == pytest.approx(2 * cost[0] + cost[1])
    assert preloader.loads_per_domain() == {0: 2, 1: 1} and preloader.resident() == {0}
    assert preloader.stats()["preloads"] == 0


@pytest.mark.parametrize("cores", [None, 1])
def test_a_preload_takes_the_core_s_time_beside_compute(domains, cores):
    """A node's one core (``cores`` None: a core per node; 1: the machine's one core): the
    preload's read (from the page cache: the loader thread's CPU) and its build share the
    core with the node's trace, so both end when the core has done all three."""
    costs = dataclasses.replace(LOADS, cores=cores)
    load_s = costs.load_s(int(domains.nbytes[4]), int(domains.triangles[4]))
    assert 0 < costs.load_s(0, int(domains.triangles[4])) < load_s
    work_s = 2 * load_s

    async def main():
        cluster, preloader = _preloader(domains, 3, costs)
        preloader.preload(4)
        await cluster.compute(0, work_s)  # the node traces while domain 4 loads
        await preloader.get(4)
        return cluster.now(), preloader

    seconds, preloader = run_virtual(main())[0]
    assert seconds == pytest.approx(work_s + load_s)
    assert preloader.stats()["preloads"] == 1 and preloader.load_count(4) == 1


def test_a_get_joins_a_preload_in_flight(domains):
    async def main():
        cluster, preloader = _preloader(domains, 3, LOADS)
        preloader.preload(6)
        preloader.preload(6)  # already loading: nothing more
        await preloader.get(6)
        return cluster.now(), preloader

    seconds, preloader = run_virtual(main())[0]
    assert seconds == pytest.approx(LOADS.load_s(int(domains.nbytes[6]),
                                                 int(domains.triangles[6])))
    assert preloader.load_count(6) == 1


def test_an_emulated_storage_bandwidth_lengthens_a_load_without_holding_the_core(domains):
    load_s = LOADS.load_s(int(domains.nbytes[2]), int(domains.triangles[2]))
    bandwidth = domains.nbytes[2] / (10 * load_s)  # its read lasts ten times the load's cost

    async def main():
        cluster, preloader = _preloader(domains, 2, LOADS, bandwidth=float(bandwidth))
        await preloader.get(2)
        return cluster.now(), cluster.compute_s[0], preloader

    seconds, core_s, preloader = run_virtual(main())[0]
    # the read and the build take the node's core; the rest of the read is a wait (as
    # ``DomainCache.load``: the read lasts the bytes over the bandwidth, then the build)
    read_s = LOADS.read_s(int(domains.nbytes[2]))
    build_s = LOADS.build_s(int(domains.triangles[2]))
    assert seconds == pytest.approx(10 * load_s + build_s) and core_s == pytest.approx(load_s)
    assert preloader.stats()["load_throttle_s"] == pytest.approx(10 * load_s - read_s,
                                                                 abs=1e-4)


def test_a_load_is_charged_the_cpu_time_it_takes_here_where_load_scale_is_set(domains):
    """``load_scale``: a load costs the CPU seconds this process takes to read and build
    that domain at the node cache's qualities (``Domains.load_cpu_s``: a cache of 2 of the
    store's 12 domains builds Embree's LOW scene quality), times the scale, not the
    constants."""
    costs = dataclasses.replace(LOADS, load_scale=2.0)

    async def main():
        cluster, preloader = _preloader(domains, 2, costs, preload=False)
        await preloader.get(5)
        return cluster.now(), preloader.cache

    seconds, cache = run_virtual(main())[0]
    read_s, build_s = domains.load_cpu_s(5, cache.build_quality, cache.mesh_quality)
    assert cache.build_quality is not None and read_s > 0 and build_s > 0
    assert seconds == pytest.approx(2.0 * (read_s + build_s), rel=1e-12)


@pytest.mark.parametrize("cores", [None, 2])
def test_a_lone_node_s_build_uses_the_spare_core_as_embree_s_threads_do(domains, cores,
                                                                        monkeypatch):
    """A load's build is charged its CPU seconds at the width it kept busy here
    (``Domains.build_width``, measured as the load is timed: here set to 1.7, since this
    test's small domains build on about one core): a node alone on a 2-core machine builds
    that much faster; a node with a core of its own (``cores`` None) does not."""
    from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW

    costs = dataclasses.replace(LOADS, load_scale=1.0, cores=cores)
    qualities = (RTC_BUILD_QUALITY_LOW, None)  # a cache of 2 of the 12 domains builds these
    read_s, build_s = domains.load_cpu_s(5, *qualities)
    assert 1.0 <= domains.build_width(5, *qualities) <= os.cpu_count()
    monkeypatch.setitem(domains._load_cpu, (5, *qualities), (read_s, build_s, 1.7))

    async def main():
        cluster, preloader = _preloader(domains, 2, costs, preload=False)
        await preloader.get(5)
        return cluster.now(), preloader.cache

    seconds, cache = run_virtual(main())[0]
    assert (cache.build_quality, cache.mesh_quality) == qualities
    expected = read_s + (build_s / 1.7 if cores == 2 else build_s)
    assert seconds == pytest.approx(expected, rel=1e-9)


def test_a_domain_s_load_is_timed_once_and_kept_where_its_qualities_are_the_kept_ones(
        store, monkeypatch):
    from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW
    from vastray.sim import cache as sim_cache

    fresh = Domains(store, shading_inputs(store, SceneConfig(), SETTINGS.integrator)[1])
    try:
        seconds = fresh.load_cpu_s(7)  # the kept domains' qualities: the build is kept
        assert min(seconds) > 0 and 7 in fresh._real
        kept = fresh.get(7)
        low = fresh.load_cpu_s(8, RTC_BUILD_QUALITY_LOW)  # another quality: timed, dropped
        assert min(low) > 0 and 8 not in fresh._real

        def no_build(*args, **kwargs):
            raise AssertionError("a domain's load was timed twice")

        monkeypatch.setattr(sim_cache, "DomainBVH", no_build)
        assert fresh.load_cpu_s(7) == seconds
        assert fresh.load_cpu_s(8, RTC_BUILD_QUALITY_LOW) == low
        assert fresh.get(7) is kept
    finally:
        fresh.close()


@pytest.mark.parametrize("capacity", [12, 2])
def test_the_simulator_s_own_load_is_not_charged_as_the_node_s_code(store, capacity):
    """The simulator times a domain's load as a node's step asks for it: those CPU seconds
    are the load's charge, not the node's own code as well (``NodeMeter``). Nor is the
    build it keeps for every node, made apart where the node's cache builds another quality
    (2 of 12 domains: Embree's LOW scene quality)."""
    from vastray.sim.meter import start_node_task

    fresh = Domains(store, shading_inputs(store, SceneConfig(), SETTINGS.integrator)[1])
    costs = dataclasses.replace(ZERO, load_scale=1.0, node_cpu_scale=1.0)

    async def main():
        cluster, preloader = _preloader(fresh, capacity, costs, preload=False)
        asyncio.get_running_loop().set_task_factory(cluster.meter.task_factory)
        await start_node_task(asyncio.get_running_loop(), 0, preloader.get(9))
        return cluster.meter.measured[0]

    try:
        own_s = run_virtual(main())[0]
        load_s = sum(fresh.load_cpu_s(9))
        assert load_s > 0 and own_s < 0.5 * load_s
    finally:
        fresh.close()


# -- simulated renders: the image is the reference's whatever the schedule ------------------
@pytest.mark.parametrize("scheduler", SIM_SCHEDULERS)
def test_every_schedule_on_any_node_count_renders_the_reference_image(store, domains,
                                                                       reference, scheduler):
    for nodes in (1, 2, 3):
        result = sim(store, domains, scheduler, nodes)
        assert np.array_equal(result.film.image(), reference), (scheduler, nodes)
        assert result.nodes == nodes and result.scheduler == scheduler
        assert result.compute_seconds.shape == (nodes + 1,) and result.seconds > 0
    # in passes of one sample, and (sort-first) in tiles small enough for every node
    tile = 200 if scheduler in TILE_SCHEDULERS else None
    result = sim(store, domains, scheduler, 3, max_pass_spp=1, max_samples_in_flight=tile)
    assert np.array_equal(result.film.image(), reference), scheduler
    assert len(result.unit_seconds) == SETTINGS.spp
    # out of core on every node: two domains in memory, four nodes
    result = sim(store, domains, scheduler, 4, cache=2, max_samples_in_flight=tile)
    assert np.array_equal(result.film.image(), reference), scheduler


@pytest.mark.parametrize("scheduler", ["spec-insitu", "dynamic", "domain"])
def test_scattered_all_reductions_give_the_reference_image(store, domains, reference,
                                                           scheduler, monkeypatch):
    """Every all-reduction scattered (halving, then doubling: the tree-reduce actor's way
    for long arrays, such as spec-insitu's t-buffers of large tiles) on 4 and 6 virtual
    nodes of the nodes' own code: the reference image (the scattered path taken)."""
    from vastray.actors.tree_reduce import TreeReduceActor
    from vastray.transport import tree

    scattered = []
    original = TreeReduceActor._scattered

    async def counted(self, *args):
        scattered.append(self.rank)
        return await original(self, *args)

    monkeypatch.setattr(TreeReduceActor, "_scattered", counted)
    monkeypatch.setattr(tree, "SCATTER_MIN_BYTES", 0)
    for nodes in (4, 6):
        scattered.clear()
        result = sim(store, domains, scheduler, nodes)
        np.testing.assert_array_equal(result.film.image(), reference)
        assert set(scattered) == set(range(4))  # the core ranks; 4 and 5 fold in


@pytest.mark.parametrize("scheduler", ["async", "domain", "spec-insitu", "image"])
def test_ambient_occlusion_is_the_reference_image_too(store, scheduler):
    settings = dataclasses.replace(SETTINGS, integrator="ao", spp=1)
    ao_domains = Domains(store, shading_inputs(store, SceneConfig(), "ao")[1])
    try:
        result = sim(store, ao_domains, scheduler, 2, settings=settings)
    finally:
        ao_domains.close()
    expected = render(store, SceneConfig(), settings, progress=False).film.image()
    assert np.array_equal(result.film.image(), expected)


def test_simulate_refuses_an_unknown_scheduler_or_no_node(store, domains):
    with pytest.raises(ValueError, match="bogus"):
        sim(store, domains, "bogus", 2)
    with pytest.raises(ValueError, match="at least 1 node"):
        sim(store, domains, "async", 0)


# -- what the schedulers do in the simulator ------------------------------------------------
@pytest.mark.parametrize("scheduler", ["domain", "dynamic"])
def test_rounds_end_over_the_tree_without_the_coordinator(store, domains, scheduler):
    result = sim(store, domains, scheduler, 3)
    assert result.counters["rounds"] > 0
    assert result.counters["batches_sent"] > 0 and result.counters["rays_sent"] > 0
    assert result.counters["batches_sent"] == result.counters["batches_received"]
    assert result.counters["global_barriers"] >= result.counters["rounds"] // 3
    assert result.compute_seconds[-1] == 0  # the coordinator took no part in a round
    # delivering the batches and taking the rounds' rays are counted (and charged)
    assert result.counters["bookkeeping_cpu_s"] > 0


def test_spec_insitu_speculates_and_counts_its_iterations(store, domains):
    result = sim(store, domains, "spec-insitu", 2)
    assert result.counters["speculative_rays"] > 0
    assert result.counters["iterations"] > 0
    assert result.counters["wasted_rays"] <= result.counters["speculative_rays"]
    assert result.counters["bookkeeping_cpu_s"] > 0  # the exchange's copying, charged


def test_async_sends_ray_batches_only_between_nodes(store, domains):
    one, two = sim(store, domains, "async", 1), sim(store, domains, "async", 2)
    assert one.counters.get("batches_sent", 0) == 0 and one.counters.get("rays_sent", 0) == 0
    assert two.counters["batches_sent"] > 0 and two.counters["rays_sent"] > 0
    assert two.counters["rays_sent"] == two.counters["rays_received"]
    assert two.messages > one.messages and two.bytes > one.bytes
    assert all(two.compute_seconds[:-1] > 0)


def test_sort_first_tiles_give_every_node_work_and_a_speed_up(store, domains):
    # the default tile (65,536 paths) holds this whole frame; each node still gets a band
    split = sim(store, domains, "image", 2, max_pass_spp=None)
    alone = sim(store, domains, "image", 1, max_pass_spp=None)
    assert all(split.compute_seconds[:-1] > 0.3 * split.compute_seconds[:-1].max())
    assert split.seconds < alone.seconds


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_sort_first_blocks_spread_over_the_image_give_the_reference(store, domains, reference,
                                                                   scheduler, monkeypatch):
    """``bench/replay_variants.py``'s alternative to a band a node: 4 blocks a node spread
    over the image, so a node's tiles are not runs of paths (``paths_context`` and
    ``PassSpans.context`` over scattered ids). The nodes' own code, one pass and a frame's
    passes swept out of core: the reference image either way."""
    from vastray.schedule import ownership

    monkeypatch.setattr(ownership, "BLOCKS_PER_NODE", 4)
    monkeypatch.setattr(ownership, "MIN_BLOCK_PATHS", 16)
    one_pass = sim(store, domains, scheduler, 3, max_pass_spp=None)
    np.testing.assert_array_equal(one_pass.film.image(), reference)
    swept = sim(store, domains, scheduler, 3, max_pass_spp=1, cache=2)
    np.testing.assert_array_equal(swept.film.image(), reference)
    assert swept.unit_seconds[1:] == [0.0] * (SETTINGS.spp - 1)  # the passes in one sweep


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_sort_first_bands_cut_by_cost_give_the_reference(store, domains, reference, scheduler,
                                                         monkeypatch):
    """Bands cut at equal estimated cost (``schedule.image_cost``) rather than equal paths
    (the product's for ``image``; ``spec-ooc``'s in ``bench/replay_variants.py``): the nodes'
    own code, one pass and a frame's passes swept out of core, the reference image either
    way."""
    from vastray.actors.render_setup import RenderSetup
    from vastray.schedule import image_cost

    monkeypatch.setattr(image_cost, "CUT_BY_COST", frozenset({scheduler}))
    from vastray.schedule.image_cost import SweepWeights, pixel_weights
    from vastray.schedule.ownership import weighted_band_cuts

    setup = RenderSetup.of(store, SceneConfig(), SETTINGS)
    weights = pixel_weights(setup.camera, setup.geometry, SETTINGS.width, SETTINGS.height)
    cuts = weighted_band_cuts(SweepWeights(weights, np.array([SETTINGS.spp])), SETTINGS.paths, 3)
    assert len(np.unique(np.diff(cuts))) > 1  # this frame's bands are not equal ones
    one_pass = sim(store, domains, scheduler, 3, max_pass_spp=None)
    np.testing.assert_array_equal(one_pass.film.image(), reference)
    swept = sim(store, domains, scheduler, 3, max_pass_spp=1, cache=2)
    np.testing.assert_array_equal(swept.film.image(), reference)


def test_a_sort_first_node_keeps_its_cache_and_sweeps_passes_out_of_core(store, domains):
    # in core, as a node's NodeState: what the first pass loaded the second finds resident
    passes = sim(store, domains, "image", 1, max_pass_spp=1)
    assert 0 < passes.counters["loads"] <= len(store.domains)
    assert all(s > 0 for s in passes.unit_seconds)  # each pass rendered apart
    # out of core, as actors.node.units_together: the frame's passes in one sweep of tiles
    swept = sim(store, domains, "image", 3, max_pass_spp=1, cache=2, max_samples_in_flight=200)
    assert swept.unit_seconds[0] > 0 and swept.unit_seconds[1:] == [0.0] * (SETTINGS.spp - 1)


@pytest.mark.parametrize("scheduler", ["image", "async", "domain"])
def test_unit_reduction_and_busy_seconds_fit_together(store, domains, scheduler):
    one = sim(store, domains, scheduler, 1, max_pass_spp=None)
    assert one.seconds == pytest.approx(one.unit_seconds[0]) and one.reduce_seconds == 0.0
    two = sim(store, domains, scheduler, 2, max_pass_spp=1)
    assert len(two.unit_seconds) == SETTINGS.spp and all(s > 0 for s in two.unit_seconds)
    assert two.seconds <= sum(two.unit_seconds) + 1e-12
    assert two.reduce_seconds > 0  # the film went up the tree
    report = two.as_dict()
    assert report["nodes"] == 2 and report["scheduler"] == scheduler
    json.dumps(report, allow_nan=False)


# -- the cost model drives the simulated time -----------------------------------------------
#: Schedulers whose batches and activations depend on when rays arrive (no rounds): their work
#: on several nodes changes with the costs' timing, not only their time.
ARRIVAL_ORDER = ("async", "temporal")


@pytest.mark.parametrize("scheduler", SIM_SCHEDULERS)
def test_dearer_traces_make_a_slower_render(store, domains, scheduler):
    base1, base2 = sim(store, domains, scheduler, 1), sim(store, domains, scheduler, 2)
    for name in TRACE_COSTS:
        dearer = dataclasses.replace(COSTS, **{name: 2 * getattr(COSTS, name)})
        assert sim(store, domains, scheduler, 1, dearer).seconds > base1.seconds, name
        if scheduler in ARRIVAL_ORDER:  # on 2 nodes their very work depends on timing
            continue
        # on 2 nodes a dynamic schedule may reorder its work; the work itself grows
        assert (sim(store, domains, scheduler, 2, dearer).compute_seconds.sum()
                > base2.compute_seconds.sum()), name


@pytest.mark.parametrize("scheduler", [s for s in NODE_SCHEDULERS if s != "spec-insitu"])
def test_with_only_activations_costing_one_node_takes_one_second_per_activation(
        store, domains, scheduler):
    costs = dataclasses.replace(ZERO, activation_s=1.0, shadow_activation_s=1.0)
    result = sim(store, domains, scheduler, 1, costs)
    assert result.seconds == result.counters["activations"] > 0


@pytest.mark.parametrize("scheduler", ["async", "domain", "image", "spec-insitu"])
def test_sharing_one_core_among_four_nodes_is_slower(store, domains, scheduler):
    options = {"max_samples_in_flight": 200} if scheduler in TILE_SCHEDULERS else {}
    own = sim(store, domains, scheduler, 4, COSTS.with_cores(None), **options)
    shared = sim(store, domains, scheduler, 4, COSTS.with_cores(1), **options)
    assert shared.seconds > own.seconds


@pytest.mark.parametrize("scheduler", SIM_SCHEDULERS)
def test_a_fresh_node_pays_its_warm_up_once_and_a_warm_one_not(store, domains, scheduler):
    cold_costs = dataclasses.replace(COSTS, warmup_s=1.0)
    cold = sim(store, domains, scheduler, 1, cold_costs, max_pass_spp=1)  # two passes
    warm = sim(store, domains, scheduler, 1, cold_costs.warm(), max_pass_spp=1)
    assert 0.9 * cold_costs.warmup_s <= cold.seconds - warm.seconds < 1.5 * cold_costs.warmup_s


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc", "async", "domain", "spec-insitu"])
def test_each_runtime_pays_its_own_set_up(store, domains, scheduler):
    base = sim(store, domains, scheduler, 1).seconds
    paid = {name: sim(store, domains, scheduler, 1,
                      dataclasses.replace(COSTS, **{name: 1.0})).seconds - base
            for name in ("node_setup_s", "tile_setup_s", "insitu_setup_s")}
    own = ("tile_setup_s" if scheduler in TILE_SCHEDULERS
           else "insitu_setup_s" if scheduler == "spec-insitu" else "node_setup_s")
    for name, seconds in paid.items():
        assert seconds == pytest.approx(1.0 if name == own else 0.0, abs=0.1), name


@pytest.mark.parametrize("scheduler", ["image", "async", "domain"])
def test_slow_loads_make_a_small_cache_slower(store, domains, scheduler):
    costs = dataclasses.replace(COSTS, load_byte_s=1e-5)
    small = sim(store, domains, scheduler, 2, costs, cache=1)
    default = sim(store, domains, scheduler, 2, costs)
    assert small.counters["loads"] > default.counters["loads"]
    assert small.seconds > default.seconds


def test_latency_slows_what_sends_messages_only(store, domains):
    slow = dataclasses.replace(COSTS, latency_s=0.05)
    delta = slow.latency_s - COSTS.latency_s
    # one node: async's only messages are its reports to the coordinator
    fast1, slow1 = sim(store, domains, "async", 1), sim(store, domains, "async", 1, slow)
    assert fast1.counters.get("batches_sent", 0) == 0
    assert 0 <= slow1.seconds - fast1.seconds <= fast1.messages * delta + 1e-9
    # two nodes exchange ray batches: every hop pays
    fast2, slow2 = sim(store, domains, "async", 2), sim(store, domains, "async", 2, slow)
    assert slow2.seconds - fast2.seconds > slow1.seconds - fast1.seconds
    assert slow2.seconds - fast2.seconds > 10 * delta
    # one node that sends nothing does not notice
    for scheduler in ("image", "spec-insitu"):
        fast, late = (sim(store, domains, scheduler, 1, c) for c in (COSTS, slow))
        assert fast.messages == 0 and late.seconds == fast.seconds, scheduler
    # sort-first nodes send only their films, after the busy time
    fast, late = (sim(store, domains, "image", 2, c) for c in (COSTS, slow))
    assert late.seconds == pytest.approx(fast.seconds)
    assert late.reduce_seconds >= fast.reduce_seconds + delta


# -- the command ----------------------------------------------------------------------------
def vastray(*args, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run the installed CLI as a user would: ``python -m vastray.cli`` in ``cwd``."""
    return subprocess.run([sys.executable, "-m", "vastray.cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def _reject(name):
    raise AssertionError(f"report holds {name}: not strict JSON")


SMALL = ["--width", "32", "--height", "24", "--spp", "1", "--bounces", "1",
         "--shadow-samples", "2"]


def test_cli_prints_a_line_per_run_and_writes_the_image_and_the_report(store, tmp_path):
    COSTS.save(tmp_path / "costs.json")
    out = vastray("simulate", store.path, "--nodes", "1,2", "--scheduler", "async,domain",
                  *SMALL, "--costs", "costs.json", "-o", "sim.exr", "--report", "sim.json",
                  cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stdout.splitlines() if "simulated" in line]
    assert len(lines) == 4, out.stdout
    for line, (scheduler, nodes) in zip(lines, [("async", 1), ("async", 2), ("domain", 1),
                                                ("domain", 2)], strict=True):
        assert "speed-up" in line and scheduler in line and f"{nodes} nodes" in line, line
    settings = RenderSettings(width=32, height=24, spp=1, bounces=1, shadow_samples=2)
    expected = render(store, SceneConfig(), settings, progress=False).film.image()
    np.testing.assert_allclose(read_image(tmp_path / "sim.exr"), expected, rtol=0, atol=1e-6)
    report = json.loads((tmp_path / "sim.json").read_text(), parse_constant=_reject)
    runs = report["runs"]
    assert [(r["scheduler"], r["nodes"]) for r in runs] == [("async", 1), ("async", 2),
                                                            ("domain", 1), ("domain", 2)]
    assert all(r["seconds"] > 0 for r in runs)
    assert report["costs"]["latency_s"] == COSTS.latency_s


def test_cli_sort_first_runs_print_their_lines_and_report_their_activations(store, tmp_path):
    """Without --quiet, as a user runs it: the sort-first schedulers' lines and summary, and
    their nodes' activations in the report (the simulator reports them as a real sort-first
    node does since session 29)."""
    COSTS.save(tmp_path / "costs.json")
    out = vastray("simulate", store.path, "--nodes", "2", "--scheduler", "image,spec-ooc",
                  *SMALL, "--costs", "costs.json", "--report", "sim.json", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stdout.splitlines() if "simulated" in line]
    assert len(lines) == 2, out.stdout
    for line, scheduler in zip(lines, ("image", "spec-ooc"), strict=True):
        assert "speed-up" in line and scheduler in line and "2 nodes" in line, line
    runs = json.loads((tmp_path / "sim.json").read_text(), parse_constant=_reject)["runs"]
    assert [r["scheduler"] for r in runs] == ["image", "spec-ooc"]
    assert all(r["counters"]["activations"] > 0 and r["seconds"] > 0 for r in runs)


def test_cli_refuses_nodes_whose_path_state_cannot_fit_saying_what_to_set(store, tmp_path):
    """Without --quiet, as a user runs it: 100,000 virtual ``domain`` nodes, each keeping
    every path of a 4,194,304-path tile, are refused before any run, exit 2, naming the tile
    and the option to set; no report is written."""
    COSTS.save(tmp_path / "costs.json")
    out = vastray("simulate", store.path, "--nodes", "100000", "--scheduler", "domain",
                  "--width", "512", "--height", "512", "--spp", "64", "--costs", "costs.json",
                  "--report", "sim.json", cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert "domain on 100000 virtual nodes with tiles of 4,194,304 paths" in out.stderr
    assert "--max-samples-in-flight" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "sim.json").exists()


def test_cli_warm_and_cores_options_reach_the_costs(store, tmp_path):
    dataclasses.replace(COSTS, warmup_s=1.0, cores=3).save(tmp_path / "costs.json")
    runs = {}
    for name, extra in (("cold", []), ("warm", ["--warm"]), ("shared", ["--cores", "1"]),
                        ("calibrated", ["--cores", "calibrated"])):
        out = vastray("simulate", store.path, "--nodes", "2", "--scheduler", "async", *SMALL,
                      "--report", f"{name}.json", "--quiet", *extra, cwd=tmp_path)
        assert out.returncode == 0 and not out.stdout, out.stderr
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
    seconds = {name: run["runs"][0]["seconds"] for name, run in runs.items()}
    assert seconds["cold"] - seconds["warm"] >= 0.9
    assert runs["warm"]["costs"]["warmup_s"] == 0.0 and runs["cold"]["costs"]["cores"] is None
    assert runs["shared"]["costs"]["cores"] == 1 and seconds["shared"] > seconds["cold"]
    assert runs["calibrated"]["costs"]["cores"] == 3  # the calibrated machine's
    bad = vastray("simulate", store.path, "--cores", "0", cwd=tmp_path)
    assert bad.returncode == 2 and "'calibrated'" in bad.stderr


def test_cli_names_a_missing_costs_file_and_how_to_make_one(store, tmp_path):
    out = vastray("simulate", store.path, "--nodes", "1", *SMALL, "--costs", "absent.json",
                  cwd=tmp_path)
    assert out.returncode != 0
    assert "absent.json" in out.stderr and "vastray calibrate" in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize("args, problem", [(["--nodes", "0"], "--nodes"),
                                           (["--nodes", "two"], "--nodes"),
                                           (["--scheduler", "bogus"], "bogus")])
def test_cli_bad_arguments_are_usage_errors(store, tmp_path, args, problem):
    out = vastray("simulate", store.path, *args, cwd=tmp_path)
    assert out.returncode == 2
    assert problem in out.stderr and "Traceback" not in out.stderr


def test_cli_help_says_to_calibrate_first(tmp_path):
    out = vastray("simulate", "--help", cwd=tmp_path)
    assert out.returncode == 0 and "vastray calibrate" in out.stdout


# -- defects found once, fixed: animations, cache capacity and hits, message order --------
def test_an_animation_s_image_is_its_last_frame(store, domains):
    settings = dataclasses.replace(SETTINGS, spp=1)
    result = simulate(store, JobOptions(scheduler="async"), 2, COSTS, settings, frames=2,
                      domains=domains)
    frame_settings, frame_config = frame_inputs(settings, SceneConfig(), store, 1)
    last = render(store, frame_config, frame_settings, progress=False).film.image()
    assert np.array_equal(result.film.image(), last)


def test_a_preload_during_a_load_never_overfills_the_cache(domains):
    async def main():
        _, preloader = _preloader(domains, 2, LOADS)
        loading = asyncio.ensure_future(preloader.get(0))
        await asyncio.sleep(0)  # the load of 0 is under way
        preloader.preload(1)
        preloader.preload(2)
        await loading
        await asyncio.sleep(10.0)
        return preloader.cache.resident()

    assert len(run_virtual(main())[0]) <= 2


def test_a_load_is_not_a_cache_hit(domains):
    async def main():
        _, preloader = _preloader(domains, 2, LOADS)
        await preloader.get(0)
        return preloader.stats()

    assert run_virtual(main())[0]["cache_hits"] == 0


def test_messages_between_two_endpoints_arrive_in_order():
    async def main():
        cluster = Cluster(2, COSTS)
        await asyncio.gather(cluster.send(0, 1, Message("rays", {}, {"n": 1}), 10_000_000),
                             cluster.send(0, 1, Message("rays", {}, {"n": 2}), 10))
        box = cluster.mailboxes[1]["rays"]
        return [box.get_nowait().meta["n"] for _ in range(box.qsize())]

    assert run_virtual(main())[0] == [1, 2]


# -- against real runs ----------------------------------------------------------------------
@pytest.mark.slow
def test_validation_simulated_seconds_are_within_a_quarter_of_real_runs(tmp_path):
    from vastray.actors.coordinator import render_distributed
    from vastray.sim.calibrate import MachineProbe, calibrate
    from vastray.sim.steal import Contention

    path = tmp_path / "rm.store"
    generate("rm", path, 64, grid=(3, 3, 2))
    store = Store(path)
    calibrated = calibrate(path, quick=True)
    probe = MachineProbe(path)
    settings = RenderSettings(width=96, height=72, spp=4, bounces=1)
    errors = {}
    for scheduler in ("async", "domain"):
        # what a message and a hand-off cost and what busy processes get of the cores move
        # with the machine's moment, and the host's steal with it: each round measures them
        # beside one real run and charges them to one simulation, as bench/simulate.py does,
        # and the simulation is judged against the run of its own round; the median of the 7
        # rounds' errors is the test's. Neither side's fastest alone: the simulations' traces
        # are timed in this process at the moment too, so they spread as far as the runs (CI
        # once saw async's simulations at 0.36-0.49 s beside runs at 0.48-0.56 s: the fastest
        # of each, -25.7 %, set a quiet moment's simulation against a busier one's run), and a
        # host busy in some rounds only (CI once saw async runs at 0.51-0.58 s and 0.75-0.78 s
        # in one test, 10-14 % stolen) moves the medians of unpaired runs (-26 % there)
        reals, simulations, lost, throughputs_of_2 = [], [], [], []
        for _ in range(7):
            costs = probe.now(calibrated)
            throughputs_of_2.append(round(costs.throughput[1], 2))
            with Contention() as seen:
                reals.append(render_distributed(
                    path, None, settings, 2, options=JobOptions(scheduler=scheduler, threads=1),
                    timeout=300).seconds["busy_max"])
            simulations.append(simulate(store, JobOptions(scheduler=scheduler), 2,
                                        seen.charged(costs.with_cores(costs.cores)), settings,
                                        max_pass_spp=None).seconds)
            lost.append((seen.share, seen.others))
        rounds = list(zip(reals, simulations, lost, strict=True))
        paired = statistics.median(simulated / real - 1 for real, simulated, _ in rounds)
        shown = [(round(real, 3), round(simulated, 3), f"{simulated / real - 1:+.0%}",
                  f"{stolen:.0%}", f"{others:.2f}")
                 for real, simulated, (stolen, others) in rounds]
        # what a failure is read against: the set-up each node is charged (measured once, by
        # the calibration: a difference of real and simulated renders), the probe's
        # throughput of 2 processes and the others it saw
        errors[scheduler] = (f"rounds (real s, simulated s, error, stolen, others running) "
                             f"{shown}, "
                             f"median error {paired:+.1%} (the fastest of each: "
                             f"{min(simulations) / min(reals) - 1:+.1%}); set-up charged "
                             f"{(calibrated.warmup_s + calibrated.node_setup_s) * 1e3:.1f} ms "
                             f"a node, throughput of 2 {throughputs_of_2}, probe's others "
                             f"{[round(o, 2) for o in probe.others]}", paired)
        print(scheduler, errors[scheduler][0])
    probe.close()
    # a real run shares this machine's cores with whatever else runs (os.getloadavg)
    assert all(abs(e) <= 0.25 for _, e in errors.values()), (errors, os.getloadavg())


@pytest.mark.parametrize("scheduler", SIM_SCHEDULERS)
def test_the_schedules_decisions_cost_the_cpu_time_they_take(store, domains, scheduler):
    """``CostModel.decision_scale`` charges what the real schedule code takes to decide
    (``next_domain`` and spec-ooc's filtering, ``likely_next``, the dynamic rounds' plans,
    spec-insitu's speculative copies and their resolution) to the virtual node: with every
    other cost 0, a render costs nothing without it and something with it."""
    free = sim(store, domains, scheduler, 2, ZERO)
    charged = sim(store, domains, scheduler, 2, dataclasses.replace(ZERO, decision_scale=1e3))
    assert free.compute_seconds.sum() == 0
    assert charged.compute_seconds[:-1].sum() > 0 and charged.seconds > 0


def test_a_replaced_build_ahead_runs_on_charged_and_is_no_load(domains):
    async def main():
        cluster, preloader = _preloader(domains, 3, LOADS, build_ahead=True)
        await preloader.get(0)
        preloader.build_ahead(2)
        preloader.build_ahead(3)  # replaces 2's, which runs to its end on the node's core
        start = cluster.now()
        await preloader.get(3)  # waits for both builds on the one preloading thread
        return preloader, cluster.now() - start

    preloader, wait_s = run_virtual(main())[0]
    both = sum(LOADS.load_s(int(domains.nbytes[d]), int(domains.triangles[d])) for d in (2, 3))
    assert wait_s == pytest.approx(both, rel=1e-9)
    stats = preloader.stats()
    assert stats["builds_ahead"] == 2 and stats["builds_ahead_used"] == 1
    assert stats["loads"] == 2 and preloader.resident() == {0, 3}


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_simulation_says_one_line(store, tmp_path, sig):
    """Ctrl-C or a kill during a large simulation: the command's one line, not asyncio's
    dozens of lines about the virtual nodes' abandoned tasks."""
    COSTS.save(tmp_path / "costs.json")
    proc = subprocess.Popen(
        [sys.executable, "-m", "vastray.cli", "simulate", store.path, "--nodes", "2000",
         "--width", "64", "--height", "48", "--spp", "2", "--costs", "costs.json"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(6)  # into the virtual nodes' run (started after about 2 s)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    lines = [line for line in err.strip().splitlines() if not line.startswith("simulating ")]
    assert proc.returncode in (130, 143), err
    assert len(lines) == 1 and lines[0].startswith("vastray simulate: "), err
