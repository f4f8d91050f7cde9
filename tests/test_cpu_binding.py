"""Local nodes bound to their own CPUs (``scene.cpu_binding``): which CPUs, the node's
``--cpus``, a real 2-node render's nodes each on its own, and the simulator binding its
virtual nodes as the launcher binds real ones."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.scene.cpu_binding import BIND_ENV, node_cpu_blocks, parse_cpus
from vastray.scene.cpus import available_cpus
from vastray.sim.clock import run_virtual
from vastray.sim.cluster import Cluster
from vastray.sim.cores import SharedCores
from vastray.sim.costs import CostModel

from scenes import bumpy_scene, settings, write_store


def test_each_node_gets_its_share_of_the_cpus_in_order(monkeypatch):
    monkeypatch.delenv(BIND_ENV, raising=False)
    assert node_cpu_blocks(2, [0, 1], 2) == [[0], [1]]
    assert node_cpu_blocks(2, list(range(16)), 16) == [list(range(8)), list(range(8, 16))]
    assert node_cpu_blocks(3, [0, 2, 4, 6, 8, 10, 12], 7) == [[0, 2], [4, 6], [8, 10]]
    # a cgroup quota of 4 CPUs on a mask of 16: 4 threads' worth, 2 a node
    assert node_cpu_blocks(2, list(range(16)), 4) == [[0, 1], [2, 3]]


def test_a_lone_node_more_nodes_than_cpus_or_the_switch_leave_them_unbound(monkeypatch):
    monkeypatch.delenv(BIND_ENV, raising=False)
    assert node_cpu_blocks(1, [0, 1], 2) is None
    assert node_cpu_blocks(8, [0, 1], 2) is None
    monkeypatch.setenv(BIND_ENV, "0")
    assert node_cpu_blocks(2, [0, 1], 2) is None


def test_nodes_asked_for_more_threads_than_their_share_run_unbound(monkeypatch):
    """``--threads 4`` on 2 nodes of 4 CPUs: 2 CPUs a node would hold 4 threads to 2."""
    monkeypatch.delenv(BIND_ENV, raising=False)
    assert node_cpu_blocks(2, [0, 1, 2, 3], 4, threads=4) is None
    assert node_cpu_blocks(2, [0, 1, 2, 3], 4, threads=2) == [[0, 1], [2, 3]]
    assert node_cpu_blocks(2, [0, 1, 2, 3], 4, threads=1) == [[0, 1], [2, 3]]


def test_cpus_lists_and_ranges():
    assert parse_cpus("0-3,8") == [0, 1, 2, 3, 8]
    assert parse_cpus("2, 0") == [0, 2]
    for bad, says in (("x", "expected"), ("3-1", "not a range"), ("-1", "expected"),
                      ("", "expected")):
        with pytest.raises(ValueError, match=says):
            parse_cpus(bad)


def test_a_node_refuses_cpus_it_may_not_use_naming_the_ones_it_may():
    """Before it contacts anyone: a clear error and status 2, not a hang."""
    done = subprocess.run([sys.executable, "-m", "vastray.actors.node", "--cpus", "4096",
                           "--coordinator", "tcp://127.0.0.1:9", "--rank", "0",
                           "--timeout", "5"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    mask = ",".join(map(str, sorted(os.sched_getaffinity(0))))
    assert f"--cpus 4096: none of them may be used here (the CPUs this process may use: {mask})" \
        in done.stderr


def test_binding_reaches_threads_already_running():
    """``bind_process`` binds every thread, not only the caller (a thread started before it
    would keep the whole machine)."""
    code = ("import os, threading\n"
            "from vastray.scene.cpu_binding import bind_process\n"
            "seen = {}\n"
            "go = threading.Event()\n"
            "def worker():\n"
            "    go.wait(); seen['mask'] = sorted(os.sched_getaffinity(0))\n"
            "t = threading.Thread(target=worker); t.start()\n"
            "first = min(os.sched_getaffinity(0))\n"
            "print(bind_process([first]))\n"
            "go.set(); t.join(); print(seen['mask'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout.split("\n")
    first = min(os.sched_getaffinity(0))
    assert out[:2] == [f"[{first}]", f"[{first}]"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("binding") / "kd4", bumpy_scene(), kd=4)


@pytest.mark.skipif(available_cpus() < 2, reason="binding 2 nodes needs 2 CPUs (affinity and quota)")
def test_two_local_nodes_render_each_on_its_own_cpus(store, tmp_path, monkeypatch):
    """Each node says where it is bound (its mask read back after binding), the two masks
    are disjoint, and the image is the unbound render's bit for bit."""
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=2)
    options = JobOptions(scheduler="dynamic", threads=1)
    monkeypatch.delenv(BIND_ENV, raising=False)
    bound = render_distributed(store.path, None, st, 2, options, log_dir=tmp_path / "bound")
    masks = []
    for rank in (0, 1):
        lines = [line for line in (tmp_path / "bound" / f"node{rank}.log").read_text()
                 .splitlines() if "bound to CPU" in line]
        assert len(lines) == 1, lines
        masks.append(set(map(int, lines[0].rsplit(" ", 1)[1].split(","))))
    assert masks[0] and masks[1] and not masks[0] & masks[1], masks
    monkeypatch.setenv(BIND_ENV, "0")
    free = render_distributed(store.path, None, st, 2, options, log_dir=tmp_path / "free")
    assert "bound to CPU" not in (tmp_path / "free" / "node0.log").read_text()
    np.testing.assert_array_equal(bound.film.image(), free.film.image())


def test_the_simulator_binds_its_virtual_nodes_as_the_launcher_binds_real_ones(monkeypatch):
    """Two virtual nodes on 2 shared cores are bound to one core each: a build 1.8 cores
    wide runs on one core even while the other node idles; 8 nodes on 2 cores, or one, are
    not bound and such a build spreads over the idle core."""
    monkeypatch.delenv(BIND_ENV, raising=False)
    costs = CostModel().with_cores(2)

    async def build(size):
        cluster = Cluster(size, costs)
        await cluster.compute(0, 1.8, width=1.8)
        return cluster.bound_width

    assert run_virtual(build(2)) == (1.0, pytest.approx(1.8))
    assert run_virtual(build(8)) == (None, pytest.approx(1.0))
    assert run_virtual(build(1)) == (None, pytest.approx(1.0))
    monkeypatch.setenv(BIND_ENV, "0")
    assert run_virtual(build(2)) == (None, pytest.approx(1.0))


def test_the_simulator_charges_others_beside_bound_virtual_nodes_where_they_sit(
        monkeypatch):
    """Beside one busy process of others, two bound virtual nodes passing work back and
    forth faster than an idle core pulls a process share one core with it; unbound
    (``VASTRAY_BIND_NODES=0``) each takes the idle core."""
    costs = CostModel().with_cores(2).beside(1.0)
    turn = SharedCores.IDLE_PULL_S / 4

    async def by_turns():
        cluster = Cluster(2, costs)
        for rank in (0, 1, 0, 1):
            await cluster.compute(rank, turn)

    monkeypatch.delenv(BIND_ENV, raising=False)
    assert run_virtual(by_turns())[1] == pytest.approx(6 * turn)
    monkeypatch.setenv(BIND_ENV, "0")
    assert run_virtual(by_turns())[1] == pytest.approx(4 * turn)
