"""The host's steal and other processes' load read from /proc/stat, and the cores a model
charges under them (the steal as a share, other processes as busy processes beside the
nodes)."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import pytest

from vastray.sim.clock import run_virtual
from vastray.sim.cores import SharedCores
from vastray.sim.costs import CostModel, aggregate_throughput
from vastray.sim.node_cost import span_per_setup
from vastray.sim.steal import (
    Contention,
    StealMeter,
    cpu_ticks,
    others_running,
    running_now,
    stolen_share,
)


def stat_file(tmp_path, user, system, idle, steal, name="stat"):
    path = tmp_path / name
    path.write_text(f"cpu  {user} 0 {system} {idle} 5 1 2 {steal} 0 0\n"
                    f"cpu0 {user} 0 {system} {idle} 5 1 2 {steal} 0 0\nintr 1 2 3\n")
    return path


def test_ticks_are_the_busy_and_stolen_fields_of_the_first_line(tmp_path):
    # busy: user, nice, system, irq, softirq; idle and iowait are not wanted time
    assert cpu_ticks(stat_file(tmp_path, 100, 20, 500, 30)) == (100 + 20 + 1 + 2, 30)


def test_the_stolen_share_is_of_the_time_wanted_between_two_readings():
    assert stolen_share((100, 10), (170, 40)) == pytest.approx(30 / (70 + 30))
    assert stolen_share((100, 10), (170, 10)) == 0.0  # nothing stolen
    assert stolen_share((100, 10), (100, 10)) == 0.0  # nothing ran
    assert stolen_share(None, (170, 40)) == 0.0 and stolen_share((1, 1), None) == 0.0


def test_a_missing_or_foreign_stat_file_reads_as_no_steal(tmp_path):
    assert cpu_ticks(tmp_path / "missing") is None
    (tmp_path / "odd").write_text("something else\n")
    assert cpu_ticks(tmp_path / "odd") is None
    with StealMeter(tmp_path / "missing") as meter:
        pass
    assert meter.share == 0.0


def test_the_meter_measures_the_span_it_wraps(tmp_path):
    path = stat_file(tmp_path, 100, 0, 500, 0)
    with StealMeter(path) as meter:
        stat_file(tmp_path, 160, 0, 600, 40)  # 60 busy, 40 stolen meanwhile
    assert meter.share == pytest.approx(0.4)


def test_this_machine_s_share_is_a_share():
    with StealMeter() as meter:
        sum(range(100_000))
    assert 0.0 <= meter.share < 1.0


def test_stolen_cores_scale_the_throughput_for_every_process_count():
    model = CostModel(cores=2, throughput=(1.0, 1.8, 1.9, 2.0))
    stolen = model.stolen(0.25)
    assert stolen.throughput == pytest.approx((0.75, 1.35, 1.425, 1.5))
    # an ideal machine (no throughput measured): min(k, cores) for 1 .. 2 x cores
    assert CostModel(cores=2).stolen(0.5).throughput == pytest.approx((0.5, 1.0, 1.0, 1.0))
    # nothing stolen, or a core a node (no shared machine): the same model
    assert model.stolen(0.0) is model and CostModel().stolen(0.3) == CostModel()
    with pytest.raises(ValueError, match="stolen share"):
        model.stolen(1.0)


def test_a_process_alone_on_cores_with_steal_runs_slower_by_the_share():
    cores = SharedCores(2, CostModel(cores=2, throughput=(1.0, 2.0)).stolen(0.2).throughput)
    assert cores.speed(1) == pytest.approx(0.8) and cores.speed(2) == pytest.approx(0.8)


def test_others_running_is_the_runnable_tasks_beside_this_one(tmp_path):
    path = stat_file(tmp_path, 100, 20, 500, 0)
    path.write_text(path.read_text() + "procs_running 4\nprocs_blocked 0\n")
    assert running_now(path) == 4
    assert others_running(0.02, path) == 3.0  # this process is one of the four
    assert running_now(tmp_path / "missing") is None
    assert others_running(0.02, tmp_path / "missing") == 0.0
    # no procs_running line (not Linux's format): nothing known, nothing charged
    assert others_running(0.02, stat_file(tmp_path, 1, 1, 1, 0, name="plain")) == 0.0


def test_a_spinner_beside_this_process_is_one_process_running():
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
    from hogs import busy_processes

    with busy_processes(1):
        beside = others_running()
    # the spinner wants a core all the time; whatever else runs (the suite's other workers)
    # only adds to it
    assert beside >= 0.9, beside


def test_contention_charges_the_steal_as_a_share_and_others_as_processes(tmp_path):
    path = stat_file(tmp_path, 100, 20, 500, 0)
    path.write_text(path.read_text() + "procs_running 2\n")
    with Contention(path) as seen:
        pass
    assert seen.share == 0.0 and seen.others == 1.0
    model = CostModel(cores=2, throughput=(1.0, 2.0, 1.9))
    assert seen.charged(model) == model.beside(1.0)
    assert seen.charged(CostModel()) == CostModel()  # a core a node: nothing shared


def test_throughput_between_counts_is_interpolated():
    assert aggregate_throughput((1.0, 2.0, 1.8), 2, 2.5) == pytest.approx(1.9)
    assert aggregate_throughput((1.0, 2.0, 1.8), 2, 9) == pytest.approx(1.8)  # the last
    assert aggregate_throughput((0.9, 1.8), 2, 0.5) == pytest.approx(0.45)
    assert aggregate_throughput((), 2, 3.5) == 2.0 and aggregate_throughput((), None, 3.5) == 3.5
    assert CostModel(cores=2, throughput=(1.0, 2.0)).throughput_at(1.5) == pytest.approx(1.5)


def test_others_beside_the_nodes_take_their_share_of_the_cores():
    throughput = (1.0, 2.0, 2.0, 2.0)
    alone = SharedCores(2, throughput)
    beside = SharedCores(2, throughput, others=1.0)
    # one node beside one busy process: each has a core, as the operating system gives it
    assert beside.speed(1) == pytest.approx(1.0) == alone.speed(1)
    # two nodes and the process: 2 cores among 3; eight nodes: among 9
    assert beside.speed(2) == pytest.approx(2 / 3) and alone.speed(2) == pytest.approx(1.0)
    assert beside.speed(8) == pytest.approx(2 / 9)
    with pytest.raises(ValueError, match="other processes"):
        CostModel(cores=2).beside(-1.0)
    assert CostModel().beside(1.0) == CostModel()  # a core a node: nothing shared
    # a cost every busy node pays once spans more with others on the cores
    assert span_per_setup(CostModel(cores=2, throughput=throughput), 2) == 1.0
    assert span_per_setup(CostModel(cores=2, throughput=throughput).beside(1.0), 2) == \
        pytest.approx(1.5)


def test_others_beside_bound_nodes_stay_on_a_node_core_until_another_waits_long(monkeypatch):
    """Nodes bound to their own cores: the operating system can move only the others, to a
    core idle for ``IDLE_PULL_S`` or, after ``BUSY_MOVE_S`` on a busy node's core, to a
    busy node's core with fewer; unbound, a woken node takes the idle core."""
    monkeypatch.setattr(SharedCores, "IDLE_PULL_S", 0.004)
    monkeypatch.setattr(SharedCores, "BUSY_MOVE_S", 0.3)
    pull = SharedCores.IDLE_PULL_S

    async def by_turns(cores, burst):
        """Two nodes working by turns, ``burst`` s each, twice (a message back and forth)."""
        for _ in range(2):
            for rank in (0, 1):
                await cores.run(burst, owner=rank)

    def bound():
        return SharedCores(2, (), others=1.0, bound_nodes=(2, 1))

    # turns shorter than the pull: the busy process stays on node 1's core, halving it
    short = pull / 4
    assert run_virtual(by_turns(bound(), short))[1] == pytest.approx(6 * short)
    assert run_virtual(by_turns(SharedCores(2, (), others=1.0), short))[1] == \
        pytest.approx(4 * short)
    # long turns: each waiting core pulls it after IDLE_PULL_S, so each turn but the first
    # pays half of that
    assert run_virtual(by_turns(bound(), 1.0))[1] == pytest.approx(4.0 + 3 * pull / 2)

    async def together(cores):
        """Both nodes at once, 1 s each."""
        loop = asyncio.get_running_loop()
        ends = {}

        async def node(rank):
            await cores.run(1.0, owner=rank)
            ends[rank] = loop.time()

        await asyncio.gather(node(0), node(1))
        return ends

    # the busy process halves node 1's core, then node 0's after 0.3 s, and so on; once
    # node 0 is done, its core waits IDLE_PULL_S and takes the process: node 1 at full
    # speed from 1.304 s with 0.952 s done
    ends, _ = run_virtual(together(bound()))
    assert ends == {0: pytest.approx(1.3), 1: pytest.approx(1.304 + 0.048)}
    # a core no node is bound to takes the busy process first: both nodes at full speed
    ends, _ = run_virtual(together(SharedCores(3, (), others=1.0, bound_nodes=(2, 1))))
    assert ends == {0: pytest.approx(1.0), 1: pytest.approx(1.0)}
    # a node with two cores keeps one beside the process
    ends, _ = run_virtual(together(SharedCores(4, (), others=2.0, bound_nodes=(2, 2))))
    assert ends == {0: pytest.approx(1.0), 1: pytest.approx(1.0)}
    with pytest.raises(ValueError, match="do not fit"):
        SharedCores(2, (), bound_nodes=(2, 2))


def test_beside_bound_nodes_the_others_slow_the_machine_and_a_remainder_shares_fairly():
    # three busy processes on 2 cores: the machine's throughput at 3 spread over both
    assert SharedCores(2, (1.0, 2.0, 1.8), others=1.0, bound_nodes=(2, 1)).speed(2) == \
        pytest.approx(0.9)
    # nothing of others: the unbound machine's speed, throughput and all
    slow = (1.0, 1.6, 1.6)
    assert SharedCores(2, slow, bound_nodes=(2, 1)).speed(2) == SharedCores(2, slow).speed(2)
    # a tenth of a process of others shares the cores fairly, as unbound
    assert SharedCores(2, slow, others=0.1, bound_nodes=(2, 1)).speed(2) == \
        pytest.approx(SharedCores(2, slow, others=0.1).speed(2))


def test_a_wide_job_gets_no_spare_core_the_others_hold():
    """An Embree build alone (2 cores wide) takes the idle second core, but not the one a
    busy process of others holds."""
    async def build(others):
        cores = SharedCores(2, (1.0, 2.0, 2.0), others=others)
        loop = asyncio.get_running_loop()
        start = loop.time()
        await cores.run(1.0, owner="node", width=2.0)
        return loop.time() - start

    assert run_virtual(build(0.0))[0] == pytest.approx(0.5)
    assert run_virtual(build(1.0))[0] == pytest.approx(1.0)
