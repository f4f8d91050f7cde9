"""``sim.meter``: a virtual node's own code charged at the CPU time it takes here, beyond the
work the cost model charges apart (traces, decisions, loads, messages)."""

from __future__ import annotations

import asyncio
import dataclasses
import time

import pytest
from test_simulate import SETTINGS, TILE_SCHEDULERS, ZERO, charged_on_a_ticking_clock, sim
from test_simulate import domains as domains  # noqa: F401 (fixtures)
from test_simulate import reference as reference  # noqa: F401
from test_simulate import store as store  # noqa: F401

from vastray.actors.job_options import JobOptions
from vastray.sim.clock import run_virtual
from vastray.sim.cluster import Cluster
from vastray.sim.costs import CostModel
from vastray.sim.meter import NodeMeter, start_node_task, start_simulator_task
from vastray.sim.simulate import SIM_SCHEDULERS, simulate


def spin(seconds: float) -> None:
    """Use ``seconds`` of this thread's CPU (other processes on the cores do not count)."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_a_node_task_and_the_tasks_it_starts_are_measured_and_the_simulator_s_are_not():
    meter = NodeMeter(1.0)

    async def child():
        await asyncio.sleep(0)
        spin(0.02)

    async def node():
        spin(0.02)
        await asyncio.sleep(1.0)  # steps apart: each one measured
        await asyncio.ensure_future(child())  # inherits the node's context

    async def simulator():
        spin(0.05)

    async def main():
        loop = asyncio.get_running_loop()
        loop.set_task_factory(meter.task_factory)
        await asyncio.gather(start_node_task(loop, 0, node()), start_simulator_task(simulator()))

    run_virtual(main())
    assert 0.04 <= meter.measured[0] < 0.04 + 0.04  # the simulator's 0.05 s is not in it
    assert set(meter.measured) == {0}


def test_what_a_node_accounted_is_not_charged_twice_and_an_excess_waits():
    meter = NodeMeter(2.0)
    meter._add(3, 0.010)
    meter.account(3, 0.004)
    assert meter.take(3) == pytest.approx(0.012)  # (0.010 - 0.004) x 2
    assert meter.take(3) == 0.0
    meter.account(3, 0.005)  # a bookkeeping measured before, charged with a decision now
    assert meter.take(3) == 0.0
    meter._add(3, 0.007)
    assert meter.take(3) == pytest.approx(0.004)  # the excess came off the next step's


def test_a_cancelled_node_task_still_counts_what_it_computed():
    meter = NodeMeter(1.0)

    async def node():
        spin(0.01)
        await asyncio.sleep(10.0)

    async def main():
        loop = asyncio.get_running_loop()
        loop.set_task_factory(meter.task_factory)
        task = start_node_task(loop, 1, node())
        await asyncio.sleep(1.0)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    run_virtual(main())
    assert meter.measured[1] >= 0.01


def test_a_compute_takes_along_what_the_node_computed_since_its_last_charge():
    async def main():
        cluster = Cluster(2, dataclasses.replace(ZERO, node_cpu_scale=1.0))
        cluster.meter._add(1, 0.25)
        await cluster.compute(1, 0.5)
        await cluster.flush(0)  # nothing pending: nothing charged
        return cluster

    cluster, seconds = run_virtual(main())
    assert cluster.compute_s[1] == pytest.approx(0.75) and seconds == pytest.approx(0.75)
    assert cluster.compute_s[0] == 0.0


def test_without_node_cpu_scale_nothing_is_measured_or_charged(store, domains):
    result = sim(store, domains, "async", 2, ZERO)
    assert result.compute_seconds.sum() == 0.0


@pytest.mark.parametrize("scheduler", SIM_SCHEDULERS)
def test_a_node_s_own_code_is_charged_and_the_image_stays_the_reference(store, domains,
                                                                        reference, scheduler):
    """With every other cost 0, the nodes are charged the CPU their own code took here: more
    than nothing (every node, where each owns domains), at most the simulation's wall time,
    and the image is the reference's."""
    result = simulate(store, JobOptions(scheduler=scheduler), 2,
                      dataclasses.replace(ZERO, node_cpu_scale=1.0), SETTINGS, max_pass_spp=None,
                      domains=domains)
    nodes = result.compute_seconds[:-1]
    assert nodes.max() > 0 and result.seconds > 0
    if scheduler not in TILE_SCHEDULERS:  # a sort-first node may get no tile of 32x24
        assert (nodes > 0).all()
    assert nodes.sum() <= result.wall_s
    assert (result.film.image() == reference).all()


def test_charged_seconds_scale_with_node_cpu_scale(store, domains, monkeypatch):
    """At node_cpu_scale 2 a render is charged twice what the same clock readings cost at 1
    (on a ticking clock: two real runs' CPU differ on a busy machine)."""
    charged = charged_on_a_ticking_clock(monkeypatch, lambda scale: sim(
        store, domains, "async", 1, dataclasses.replace(ZERO, node_cpu_scale=scale)).seconds)
    assert charged[1.0] > 0.0
    assert charged[2.0] == pytest.approx(2.0 * charged[1.0], rel=1e-9)


def test_node_cpu_scale_is_a_cost_field_a_calibration_file_keeps(tmp_path):
    path = tmp_path / "costs.json"
    CostModel(node_cpu_scale=1.0).save(path)
    assert CostModel.load(path).node_cpu_scale == 1.0
    with pytest.raises(ValueError, match="node_cpu_scale"):
        CostModel(node_cpu_scale=-1.0)


def test_a_simulation_that_measures_nothing_reports_no_own_seconds(store, domains):
    result = sim(store, domains, "async", 2, ZERO)
    assert result.own_seconds.tolist() == [0.0, 0.0]
