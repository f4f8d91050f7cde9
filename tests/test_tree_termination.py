"""Termination detection of the asynchronous frames over the tree of ranks
(``actors.tree_termination``): a model of P nodes exchanging ray batches, with every message
delivered in a random order, never sees a frame end while a batch is in flight, and always
sees it end; real node processes, and virtual ones in the simulator, render ``async`` and
``temporal`` frames to the reference image while their coordinator hears no message about
termination."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from vastray.actors import protocol
from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.tree_termination import TreeTermination
from vastray.render.driver import render, shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig, load_scene_config
from vastray.scene.generate import generate
from vastray.scene.store import Store
from vastray.sim.cache import Domains
from vastray.sim.costs import CostModel
from vastray.sim.simulate import simulate
from vastray.transport.codec import Message

from scenes import POINT_AND_SKY_TOML, bumpy_scene, settings, write_store


class Model:
    """P nodes running ``TreeTermination`` as the frames do: a node with work does one unit
    of it (which may send ray batches), a delivered batch is one more unit of work, and a
    node with no work calls ``passive`` with its counts after everything it does. Every
    message in flight (batches and the detection's) may be delivered next, in any order.

    Parameters
    ----------
    size : P.
    work : (P,) units of work each node starts with (its tiles).
    budget : batches the nodes may send in all (so the work ends).
    """

    def __init__(self, size: int, work: list[int], budget: int):
        self.size, self.work, self.budget = size, list(work), budget
        self.nodes = [TreeTermination(rank, size, label=7) for rank in range(size)]
        self.sent, self.received = [0] * size, [0] * size
        self.flight: list[tuple[int, int, str, dict]] = []  # (from, to, kind, meta)
        self.declared_with_batches_in_flight = False
        self.declared_with_work_left = False
        for rank in range(size):
            self.settle(rank)

    def batches_in_flight(self) -> int:
        return sum(kind == protocol.RAYS for _, _, kind, _ in self.flight)

    def post(self, rank: int, sends) -> None:
        for to, kind, meta in sends:
            # every message fits its schema and the tree's rules, as a receiver checks them
            message = Message(kind, {}, meta)
            protocol.check(message, protocol.FROM_PEER)
            protocol.check_peer_kind(message, rank, to, self.size)
            assert meta["label"] == 7
            self.flight.append((rank, to, kind, meta))

    def settle(self, rank: int) -> None:
        """A node with no work left is passive: it tells its detection so."""
        node = self.nodes[rank]
        if self.work[rank] == 0 and not node.finished:
            was = [n.finished for n in self.nodes]
            self.post(rank, node.passive(self.sent[rank], self.received[rank]))
            if rank == 0 and node.finished and not was[0]:
                self.declared_with_batches_in_flight |= self.batches_in_flight() > 0
                self.declared_with_work_left |= any(self.work)

    def do_work(self, rank: int, destinations: list[int]) -> None:
        """Node ``rank`` does one unit of its work, sending a batch to each destination."""
        self.work[rank] -= 1
        for to in destinations[:self.budget]:
            self.budget -= 1
            self.sent[rank] += 1
            self.flight.append((rank, to, protocol.RAYS, {}))
        self.settle(rank)

    def deliver(self, index: int) -> None:
        source, to, kind, meta = self.flight.pop(index)
        node = self.nodes[to]
        if kind == protocol.RAYS:
            assert not node.finished, "a batch reached a node whose frame had ended"
            self.received[to] += 1
            self.work[to] += 1
        elif kind == protocol.WAVE:
            self.post(to, node.on_wave(meta))
        else:
            node.on_reply(meta)
        self.settle(to)

    def events(self) -> list[tuple]:
        """What may happen next: a node with work works, a message in flight arrives."""
        return ([("work", r) for r in range(self.size) if self.work[r]]
                + [("deliver", i) for i in range(len(self.flight))])


def _property(examples: int):
    """The frame-end property below as a test of ``examples`` random runs of the model."""
    return hsettings(max_examples=examples, deadline=None,
                     suppress_health_check=[HealthCheck.too_slow])(given(st.data())(_frame_ends))


def _frame_ends(data):
    size = data.draw(st.integers(1, 9), label="nodes")
    work = data.draw(st.lists(st.integers(0, 3), min_size=size, max_size=size), label="tiles")
    model = Model(size, work, budget=data.draw(st.integers(0, 40), label="batches"))
    steps = 0
    while model.events():
        kind, which = data.draw(st.sampled_from(model.events()), label="event")
        if kind == "work":
            others = [r for r in range(size) if r != which]  # no node sends to itself
            model.do_work(which, data.draw(st.lists(st.sampled_from(others), max_size=3)
                                           if others else st.just([]), label="sends"))
        else:
            model.deliver(which)
        steps += 1
        assert steps < 100_000
    # safety: the root declared the end only with no batch in flight and no work anywhere
    assert not model.declared_with_batches_in_flight
    assert not model.declared_with_work_left
    # liveness: once nothing is left to happen, every node's frame has ended
    assert all(node.finished for node in model.nodes)
    assert sum(model.sent) == sum(model.received)
    # the root needs two waves at least: one to see the counts, one to see them again
    assert model.nodes[0].waves >= 2


# 250 random runs of the model by default (6 s); 3,000 with -m slow (a minute; CI runs them)
test_the_frame_ends_exactly_when_no_batch_is_in_flight_whatever_the_delivery_order = _property(250)
test_the_frame_ends_exactly_in_many_more_delivery_orders = pytest.mark.slow(_property(3000))


def test_a_batch_in_flight_makes_the_root_wave_again_until_the_counts_repeat():
    # three nodes: 1 and 2 are the root's children
    nodes = [TreeTermination(rank, 3, label=0) for rank in range(3)]
    waves = nodes[0].passive(0, 0)
    assert [(to, kind) for to, kind, _ in waves] == [(1, protocol.WAVE), (2, protocol.WAVE)]
    assert nodes[1].on_wave(waves[0][2]) == [] and nodes[2].on_wave(waves[1][2]) == []
    # node 1 sent a batch to node 2 and is passive; node 2 has not received it
    (reply1,) = nodes[1].passive(1, 0)
    nodes[0].on_reply(reply1[2])
    assert nodes[0].passive(0, 0) == []  # node 2 has not answered: nothing to decide
    (reply2,) = nodes[2].passive(0, 0)
    nodes[0].on_reply(reply2[2])
    second = nodes[0].passive(0, 0)  # totals (1, 0): unbalanced, so a second wave
    assert not nodes[0].finished and [m["wave"] for _, _, m in second] == [2, 2]
    for rank in (1, 2):
        nodes[rank].on_wave(second[rank - 1][2])
    (reply1,) = nodes[1].passive(1, 0)
    nodes[0].on_reply(reply1[2])
    # the batch arrives at node 2, which is busy until it has traced it: no answer yet
    (reply2,) = nodes[2].passive(0, 1)
    nodes[0].on_reply(reply2[2])
    third = nodes[0].passive(0, 0)  # totals (1, 1), but not those of the wave before
    assert not nodes[0].finished and [m["wave"] for _, _, m in third] == [3, 3]
    for rank in (1, 2):
        nodes[rank].on_wave(third[rank - 1][2])
        nodes[0].on_reply(nodes[rank].passive(1 if rank == 1 else 0,
                                              1 if rank == 2 else 0)[0][2])
    finish = nodes[0].passive(0, 0)  # (1, 1) twice: the end, sent down the tree
    assert nodes[0].finished and all(m["finished"] for _, _, m in finish)
    for rank in (1, 2):
        assert nodes[rank].on_wave(finish[rank - 1][2]) == [] and nodes[rank].finished


def test_one_balanced_wave_is_not_enough():
    # Node 2 answers wave 1 idle; node 1 then sends it X, node 2 answers with Y (its read
    # came first), node 1 takes Y and answers (sent 1, received 1); node 2 has meanwhile sent
    # Z to the root. Wave 1 sums to (1, 1), balanced, with Z in flight: only a second wave,
    # which reads node 2's send of Y and Z, can tell.
    nodes = [TreeTermination(rank, 3, label=0) for rank in range(3)]
    down = nodes[0].passive(0, 0)
    for rank in (1, 2):
        nodes[rank].on_wave(down[rank - 1][2])
    (reply2,) = nodes[2].passive(0, 0)
    (reply1,) = nodes[1].passive(1, 1)
    for reply in (reply1, reply2):
        nodes[0].on_reply(reply[2])
    again = nodes[0].passive(0, 0)
    assert not nodes[0].finished and [m["wave"] for _, _, m in again] == [2, 2]
    for rank in (1, 2):
        nodes[rank].on_wave(again[rank - 1][2])
    nodes[0].on_reply(nodes[1].passive(1, 1)[0][2])
    nodes[0].on_reply(nodes[2].passive(2, 1)[0][2])  # (3, 2) with Z in flight: not the end
    assert not nodes[0].finished


def test_waves_and_replies_follow_the_tree_only():
    wave = Message(protocol.WAVE, {}, {"rank": 0, "label": 0, "wave": 1, "finished": False})
    reply = Message(protocol.WAVE_REPLY, {}, {"rank": 3, "label": 0, "wave": 1, "sent": 0,
                                              "received": 0})
    protocol.check_peer_kind(wave, 0, 1, 4)  # parent -> child
    protocol.check_peer_kind(reply, 3, 1, 4)  # child -> parent
    with pytest.raises(protocol.ProtocolError, match="parent"):
        protocol.check_peer_kind(wave, 2, 1, 4)
    with pytest.raises(protocol.ProtocolError, match="not a child"):
        protocol.check_peer_kind(reply, 2, 1, 4)
    with pytest.raises(protocol.ProtocolError, match="wave"):
        protocol.check(Message(protocol.WAVE, {}, {"rank": 0, "label": 0, "wave": 1}),
                       protocol.FROM_PEER)
    for gone in ("status", "probe"):  # the coordinator's detection is gone
        assert gone not in protocol.FROM_NODE | protocol.FROM_COORDINATOR


# -- real node processes ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("tree_termination")
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    return write_store(root / "s.store", bumpy_scene(), grid=(3, 2, 3)), root / "scene.toml"


@pytest.mark.parametrize("scheduler, nodes", [("async", 4), ("temporal", 3)])
def test_real_nodes_end_frames_over_the_tree_and_the_coordinator_hears_nothing_of_it(
        scene, scheduler, nodes):
    store, toml = scene
    st_ = settings(width=32, height=24, spp=2, integrator="pt")
    result = render_distributed(store.path, toml, st_, nodes,
                                options=JobOptions(scheduler=scheduler, cache=4,
                                                   max_samples_in_flight=300), timeout=60)
    reference = render(store, load_scene_config(toml), st_, progress=False).film
    np.testing.assert_array_equal(result.film.count, reference.count)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    per_node = [r["counters"] for r in result.counters["per_node"]]
    assert sum(c["batches_sent"] for c in per_node) > 0  # rays did move between nodes
    assert all(c["termination_waves"] >= 1 for c in per_node)
    assert per_node[0]["termination_waves"] >= 2
    heard = per_node[0]["coordinator_messages"]
    assert heard.get(protocol.FILM) and heard.get(protocol.DONE) == nodes
    # nothing per wave or per round: only the job's start, liveness, progress and the result
    assert set(heard) <= {protocol.HELLO, protocol.HEARTBEAT, protocol.PROGRESS, protocol.FILM,
                          protocol.DONE, protocol.FRAME}, heard


# -- virtual nodes (the simulator runs the frames' own code) ----------------------------------
SIM_SETTINGS = RenderSettings(width=32, height=24, spp=2, bounces=1, shadow_samples=2, seed=3)


@pytest.fixture(scope="module")
def sim_store(tmp_path_factory) -> Store:
    path = tmp_path_factory.mktemp("tree_termination_sim") / "rm.store"
    generate("rm", path, 32, grid=(3, 2, 2))
    return Store(path)


@pytest.mark.parametrize("scheduler", ["async", "temporal"])
def test_virtual_nodes_end_frames_without_the_simulated_coordinator(sim_store, scheduler):
    built = Domains(sim_store, shading_inputs(sim_store, SceneConfig(),
                                              SIM_SETTINGS.integrator)[1])
    try:
        result = simulate(sim_store, JobOptions(scheduler=scheduler, max_samples_in_flight=200),
                          5, CostModel(), SIM_SETTINGS, max_pass_spp=1, domains=built)
    finally:
        built.close()
    reference = render(sim_store, SceneConfig(), SIM_SETTINGS, progress=False).film
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    assert result.counters["batches_sent"] == result.counters["batches_received"] > 0
    assert result.counters["termination_waves"] >= 2 * 5  # every node, both passes
    assert result.compute_seconds[-1] == 0  # the coordinator sent nothing: no probe waves
