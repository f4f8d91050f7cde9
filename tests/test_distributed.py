"""Distributed runtime: real node processes over ZeroMQ give the reference image; a node
killed mid-render fails the run naming the node, and leaves no output."""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.node_failure import NodeFailure
from vastray.cli import main
from vastray.render.driver import render
from vastray.render.scene_config import load_scene_config
from vastray.scene.errors import InputError
from vastray.transport.keys import load_coordinator_keys
from vastray.transport.tree import children, parent

from scenes import POINT_AND_SKY_TOML, allreduce_over_sockets, bumpy_scene, free_port, settings, write_store

SCENE_TOML = POINT_AND_SKY_TOML


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("dist")
    store = write_store(root / "kd12", bumpy_scene(), kd=12)
    (root / "scene.toml").write_text(SCENE_TOML)
    return store, root / "scene.toml"


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_sort_first_nodes_all_trace_a_frame_smaller_than_their_tile(scene, scheduler):
    """The nodes' default tile (65,536 paths) holds this 1,536-path frame many times over;
    each node still traces a band of it (until session 42 node 0 traced it alone), and the
    image is the reference's, bit for bit."""
    store, toml = scene
    st = settings(width=32, height=24, spp=2)
    reference = render(store, load_scene_config(toml), st, progress=False).film
    result = render_distributed(store.path, toml, st, 3,
                                options=JobOptions(scheduler=scheduler, threads=1), timeout=60)
    np.testing.assert_array_equal(result.film.image(), reference.image())
    activations = [n["counters"]["activations"] for n in result.counters["per_node"]]
    assert len(activations) == 3 and min(activations) > 0, activations


@pytest.mark.parametrize("size", range(1, 10))
def test_tree_edges_cover_every_rank_once(size):
    ranks = range(size)
    assert sorted(c for r in ranks for c in children(r, size)) == list(range(1, size))
    assert all(parent(c) == r for r in ranks for c in children(r, size))


@pytest.fixture(scope="module")
def references(scene):
    """{integrator: the single-process film at ``_reference_settings(integrator)``}, rendered
    once for every scheduler and node count."""
    store, toml = scene
    return {integrator: render(store, load_scene_config(toml), _reference_settings(integrator),
                               progress=False).film for integrator in ("ao", "pt")}


def _reference_settings(integrator: str):
    return settings(width=32, height=24, spp=2, integrator=integrator)


# Path tracing on every scheduler on 1 node (no peer) and 4 (a tree two levels deep); ambient
# occlusion on one scheduler; every other pair and 2 and 3 nodes with -m slow (CI runs them).
@pytest.mark.parametrize("scheduler, integrator, nodes", [
    pytest.param(s, i, n, marks=[pytest.mark.slow]
                 if (i == "ao" and s != "image") or n in (2, 3) else [])
    for s in ("image", "spec-ooc", "domain", "async", "dynamic", "spec-insitu")
    for i in ("ao", "pt") for n in (1, 2, 3, 4)])
def test_nodes_give_the_reference_image(scene, references, integrator, scheduler, nodes):
    store, toml = scene
    reference = references[integrator]
    result = render_distributed(store.path, toml, _reference_settings(integrator), nodes,
                                options=JobOptions(scheduler=scheduler, cache=4,
                                                   max_samples_in_flight=300), timeout=60)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6,
                               atol=1e-6, err_msg=f"{scheduler} on {nodes} nodes")
    np.testing.assert_array_equal(result.film.count, reference.count)
    np.testing.assert_array_equal(result.film.depth, reference.depth)
    per_node = result.counters["per_node"]
    assert len(per_node) == nodes
    for report in per_node:  # the per-node timings the report promises
        assert report["busy_s"] > 0 and report["reduce_s"] >= 0
        assert report["counters"]["shade_s"] >= 0
        # the process's CPU over its busy span: some, and no more than its threads
        # could use in that span on this machine's cores
        cpu = report["counters"]["busy_cpu_s"]
        assert 0 < cpu <= report["busy_s"] * (os.cpu_count() or 1) + 0.05
        # pages first touched in the span (none where the node reuses what its warm-up
        # freed; counting them is tests/test_cpus.py's)
        assert report["counters"]["page_faults"] >= 0
    assert sum(report["counters"]["shade_s"] for report in per_node) > 0
    if scheduler in ("domain", "async", "dynamic", "spec-insitu"):
        # Ray batches are conserved: every batch sent was received, none twice.
        sent = sum(n["counters"]["batches_sent"] for n in per_node)
        assert sent == sum(n["counters"]["batches_received"] for n in per_node)
        rays = sum(n["counters"]["rays_sent"] for n in per_node)
        assert rays == sum(n["counters"]["rays_received"] for n in per_node)
        assert (sent > 0) == (nodes > 1)


def test_zorder_ownership_is_balanced_and_compact():
    from vastray.schedule.ownership import zorder_owners

    lo = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    owner = zorder_owners(lo, lo + 1, 8)
    assert np.bincount(owner).tolist() == [8] * 8
    for rank in range(8):  # each node's 8 domains form one 2x2x2 block along the curve
        block = lo[owner == rank]
        assert np.all(block.max(axis=0) - block.min(axis=0) == 1)


def test_weighted_zorder_runs_hold_equal_weight_and_stay_contiguous():
    from vastray.schedule.ownership import zorder_owners

    lo = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    rank_along = zorder_owners(lo, lo + 1, len(lo))  # each domain's place on the curve
    weights = np.ones(len(lo), np.int64)
    weights[rank_along < 8] = 7  # the first 8 domains of the curve weigh 7 times the others
    owner = zorder_owners(lo, lo + 1, 8, weights)
    held = np.bincount(owner, weights=weights, minlength=8)
    assert held.max() - held.min() <= weights.max()  # equal as whole domains allow
    assert np.bincount(owner, minlength=8)[0] < 8  # the heavy run is split over more nodes
    along = owner[np.argsort(rank_along)]
    assert np.all(np.diff(along) >= 0)  # runs of the curve, in rank order
    # equal weights give the runs of equal counts; the weights are integers, so every node
    # computes the same owners
    assert np.array_equal(zorder_owners(lo, lo + 1, 8, np.full(len(lo), 5)),
                          zorder_owners(lo, lo + 1, 8))
    with pytest.raises(ValueError, match="non-negative"):
        zorder_owners(lo, lo + 1, 8, -weights)


def test_insitu_owners_balance_triangles_and_may_leave_a_node_none():
    from vastray.schedule.ownership import insitu_owners

    lo = np.stack(np.meshgrid(*[np.arange(2.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    triangles = np.array([1000, 0, 0, 0, 0, 0, 0, 10])  # one domain holds the data
    owner = insitu_owners(lo, lo + 1, triangles, 4)
    held = np.bincount(owner, weights=triangles, minlength=4)
    assert held.max() == 1000 and np.count_nonzero(owner == owner[0]) <= 2
    assert len(set(owner.tolist())) < 4  # the heavy domain spans the shares of several nodes
    # a store of empty domains is cut by count
    assert np.bincount(insitu_owners(lo, lo + 1, np.zeros(8, int), 4)).tolist() == [2] * 4


def test_insitu_holders_split_the_most_crossed_domains_within_the_owners_bytes():
    """A domain crossed k node shares' worth gets k holders where the bytes allow (the
    least loaded nodes, no node holding more than the most any node owns); a path's copy in
    it goes to one holder, the paths dealt evenly; every node computes the same."""
    from vastray.schedule.ownership import Holders, insitu_holders

    owner = np.repeat(np.arange(4), 4)  # 16 domains, 4 a node
    weights = np.ones(16, np.int64)
    weights[5] = 60  # domain 5 (node 1's) crossed 60 times of 75: 3 node shares
    footprints = np.full(16, 10)
    holders = insitu_holders(owner, weights, 4, footprints)
    assert holders.count[5] == 1  # every node already holds the most any node owns
    footprints[[4, 6, 7]] = 20  # node 1 holds the most bytes (100): room for 5 on others
    footprints[5] = 40
    holders = insitu_holders(owner, weights, 4, footprints)
    assert holders.owner.tolist() == owner.tolist()
    assert holders.count.tolist() == [1] * 5 + [3] + [1] * 10
    extra = holders.nodes[holders.first[5] + 1:holders.first[6]]
    assert holders.nodes[holders.first[5]] == 1 and 1 not in extra.tolist()
    held = [int(footprints[holders.held_by(n)].sum()) for n in range(4)]
    assert held[1] == max(held) == 100  # none more than the most any node owned
    paths = np.arange(300)
    to = holders.destination(np.full(300, 5), paths)
    assert sorted(set(to.tolist())) == sorted([1, *extra.tolist()])
    assert np.bincount(to, minlength=4)[[1, *extra.tolist()]].tolist() == [100] * 3
    assert np.array_equal(holders.destination(np.zeros(300, int), paths), np.zeros(300))
    again = insitu_holders(owner, weights, 4, footprints)
    assert np.array_equal(again.nodes, holders.nodes)
    # nothing crossed, or one node: each domain its owner's
    for h in (insitu_holders(owner, np.zeros(16, int), 4, footprints),
              insitu_holders(np.zeros(16, int), weights, 1, footprints)):
        assert h.count.tolist() == [1] * 16
    assert Holders.owned(owner).held_by(2).tolist() == [8, 9, 10, 11]


@pytest.mark.slow
def test_spec_insitu_with_a_node_that_owns_no_domain_gives_the_reference(tmp_path):
    """Runs of equal triangles leave a node nothing to own where one domain outweighs its
    share; that node still makes its camera rays and holds paths, and the image is the
    reference's."""
    from vastray.schedule.ownership import insitu_owners

    store = write_store(tmp_path / "g3", bumpy_scene(), grid=(3, 3, 3))
    (tmp_path / "scene.toml").write_text(SCENE_TOML)
    nodes = 7
    owner = insitu_owners(*store.domain_boxes(), [d.n_triangles for d in store.domains], nodes)
    assert len(set(owner.tolist())) < nodes  # the premise: some node owns nothing
    st = _reference_settings("pt")
    reference = render(store, load_scene_config(tmp_path / "scene.toml"), st, progress=False)
    result = render_distributed(store.path, tmp_path / "scene.toml", st, nodes,
                                options=JobOptions(scheduler="spec-insitu", threads=1),
                                timeout=120)
    np.testing.assert_allclose(result.film.image(), reference.film.image(), rtol=1e-6,
                               atol=1e-6)
    np.testing.assert_array_equal(result.film.count, reference.film.count)


def test_spec_insitu_reduces_only_the_paths_still_in_flight(scene, references):
    """The t-buffer and o-buffer cover every path of the tile in the first iteration and,
    after it, only the paths whose last iteration hit something (the others have no ray on
    any node): fewer than every path every iteration, the image still the reference's."""
    store, toml = scene
    st = _reference_settings("pt")
    result = render_distributed(store.path, toml, st, 2,
                                options=JobOptions(scheduler="spec-insitu"), timeout=60)
    np.testing.assert_allclose(result.film.image(), references["pt"].image(), rtol=1e-6,
                               atol=1e-6)
    for report in result.counters["per_node"]:
        counters = report["counters"]
        covered, iterations = counters["tbuffer_paths"], counters["iterations"]
        assert st.paths < covered < iterations * st.paths, (covered, iterations)


def test_spec_insitu_relays_its_copies_over_two_hops(scene, references):
    """On 5 nodes (a grid of 3 columns whose last row is short) each node sends one batch a
    queue to each node its routes name, empty or not, every iteration, and no other: fewer
    than a batch to each of its 4 peers; copies between nodes of different rows and columns
    are relayed, and the image is the reference's."""
    from vastray.schedule.relay import routes

    store, toml = scene
    st = _reference_settings("pt")
    nodes = 5
    result = render_distributed(store.path, toml, st, nodes,
                                options=JobOptions(scheduler="spec-insitu", threads=1),
                                timeout=120)
    np.testing.assert_allclose(result.film.image(), references["pt"].image(), rtol=1e-6,
                               atol=1e-6)
    first, second = routes(nodes)
    relayed = 0
    for rank, report in enumerate(result.counters["per_node"]):
        counters = report["counters"]
        pairs = len(first.to(rank)) + len(second.to(rank))
        assert counters["batches_sent"] == 2 * pairs * counters["iterations"]
        assert counters["batches_received"] == 2 * counters["iterations"] * (
            first.count_from(rank) + second.count_from(rank))
        relayed += counters["rays_relayed"]
    assert sum(len(first.to(r)) + len(second.to(r)) for r in range(nodes)) < nodes * (nodes - 1)
    assert relayed > 0


def test_spec_insitu_gives_the_most_crossed_domains_more_holders(tmp_path):
    """On 6 nodes over a 3 x 3 x 1 grid of domains the two the camera rays cross most (a
    sixth of the crossings each, two node shares) get another holder each within the bytes
    the busiest owner holds (``ownership.insitu_holders``): each path's copy in such a
    domain is traced by one holder, and the image is the reference's."""
    store = write_store(tmp_path / "g331", bumpy_scene(), grid=(3, 3, 1))
    (tmp_path / "scene.toml").write_text(SCENE_TOML)
    st = _reference_settings("pt")
    reference = render(store, load_scene_config(tmp_path / "scene.toml"), st, progress=False)
    result = render_distributed(store.path, tmp_path / "scene.toml", st, 6,
                                options=JobOptions(scheduler="spec-insitu", threads=1),
                                timeout=120)
    np.testing.assert_allclose(result.film.image(), reference.film.image(), rtol=1e-6,
                               atol=1e-6)
    np.testing.assert_array_equal(result.film.count, reference.film.count)
    also = [report["counters"]["domains_also_held"] for report in result.counters["per_node"]]
    assert sum(also) == 2, also


def test_big_outboxes_travel_in_bounded_batches(scene):
    # With a tiny batch bound, the same render needs many more batches and still matches.
    store, toml = scene
    st = settings(width=24, height=18, spp=2, integrator="ao")
    reference = render(store, load_scene_config(toml), st, progress=False).film.image()
    counts = []
    for bound in (65536, 50):
        result = render_distributed(store.path, toml, st, 2,
                                    options=JobOptions(scheduler="async", max_batch_rays=bound),
                                    timeout=60)
        np.testing.assert_allclose(result.film.image(), reference, rtol=1e-6, atol=1e-6)
        counts.append(sum(n["counters"]["batches_sent"] for n in result.counters["per_node"]))
    assert counts[1] > counts[0]


def _node_pids(rank: int) -> list[int]:
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        try:
            parent = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        # only this test's own nodes (children of this process), never another run's
        if b"vastray.actors.node" in cmd and b"--rank" in cmd and \
                cmd[cmd.index(b"--rank") + 1] == str(rank).encode() and parent == os.getpid():
            pids.append(int(proc.name))
    return pids


def test_killed_last_node_fails_the_run_with_its_name_and_no_output(scene, tmp_path, capsys):
    # With no other node left to take over, a killed node ends the run, naming it.
    store, toml = scene
    out = tmp_path / "never.exr"
    killed = []

    def killer():
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not killed:
            for pid in _node_pids(0):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            time.sleep(0.2)

    thread = threading.Thread(target=killer)
    thread.start()
    start = time.monotonic()
    code = main(["render", str(store.path), "-o", str(out), "--scene", str(toml), "--nodes", "1",
                 "--width", "64", "--height", "48", "--spp", "256", "--node-timeout", "30",
                 "--max-samples-in-flight", "500", "--quiet"])
    thread.join()
    assert killed, "the test could not find node 0 to kill"
    assert code != 0
    assert time.monotonic() - start < 60
    err = capsys.readouterr().err
    assert "node 0" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_unknown_scheduler_for_nodes_is_refused(scene):
    store, toml = scene
    with pytest.raises(ValueError, match="unknown scheduler"):
        render_distributed(store.path, toml, settings(), 2, options=JobOptions(scheduler="galaxy"))


def _start_external_node(coordinator: str, keys: Path | None, log: Path,
                         key_name: str = "n0"):
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "vastray.cli", "node", "--coordinator", coordinator,
           "--timeout", "30"]
    if keys is not None:
        cmd += ["--keys", str(keys), "--key-name", key_name]
    with open(log, "wb") as err:
        return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)


def test_external_nodes_join_with_curve_keys(scene, tmp_path):
    # The multi-host path (docker compose, SSH): nodes started separately find the
    # coordinator, get ranks assigned, and all traffic is CURVE-encrypted and authenticated.
    store, toml = scene
    assert main(["keys", "-o", str(tmp_path / "keys"), "--node", "n0", "--node", "n1",
                 "--node", "n2"]) == 0
    for i in range(3):  # what each node's host needs: the coordinator's public key, its own
        mine = tmp_path / f"host{i}"
        (mine / "nodes").mkdir(parents=True)
        shutil.copy(tmp_path / "keys" / "coordinator.pub", mine)
        shutil.copy(tmp_path / "keys" / "nodes" / f"n{i}.key", mine / "nodes")
    port = free_port()
    nodes = [_start_external_node(f"tcp://127.0.0.1:{port}", tmp_path / f"host{i}",
                                  tmp_path / f"n{i}.log", f"n{i}") for i in range(3)]
    try:
        st = settings(width=24, height=18, spp=2, integrator="pt")
        result = render_distributed(store.path, toml, st, 3, listen=f"127.0.0.1:{port}",
                                    keys=load_coordinator_keys(tmp_path / "keys"), timeout=30,
                                    options=JobOptions(max_samples_in_flight=200))
        reference = render(store, load_scene_config(toml), st, progress=False).film.image()
        np.testing.assert_allclose(result.film.image(), reference, rtol=1e-6, atol=1e-6)
    finally:
        for node in nodes:
            node.wait(timeout=30)
    assert all(node.returncode == 0 for node in nodes)


def test_node_without_the_key_is_not_admitted(scene, tmp_path):
    store, toml = scene
    main(["keys", "-o", str(tmp_path / "keys"), "--node", "n0"])
    main(["keys", "-o", str(tmp_path / "other"), "--node", "n0"])
    port = free_port()
    intruder = _start_external_node(f"tcp://127.0.0.1:{port}", tmp_path / "other",
                                    tmp_path / "intruder.log")
    try:
        with pytest.raises(NodeFailure, match="no node joined"):
            render_distributed(store.path, toml, settings(), 1, listen=f"127.0.0.1:{port}",
                               keys=load_coordinator_keys(tmp_path / "keys"), timeout=4)
    finally:
        intruder.kill()
        intruder.wait()


def test_listening_beyond_loopback_needs_keys(scene):
    store, toml = scene
    with pytest.raises(InputError, match="needs keys"):
        render_distributed(store.path, toml, settings(), 1, listen="0.0.0.0:0")


@pytest.mark.parametrize("size", range(1, 10))
async def test_butterfly_allreduce_over_real_sockets(size):
    """The tree-reduce actor of P nodes (real ZeroMQ sockets, one event loop): MIN, OR and
    SUM reach every node in log2 C exchange steps (C the largest power of two <= P; two more
    where P is not one), and float sums are the same bits on every node."""
    rng = np.random.default_rng(size)
    values = [{"t": rng.integers(0, 1 << 60, 100, dtype=np.uint64),
               "o": rng.integers(0, 256, 64).astype(np.uint8),
               "n": rng.integers(0, 1000, 10),
               "f": rng.random(50) * 10.0 ** rng.integers(-8, 8, 50)} for _ in range(size)]
    ops = {"t": "min", "o": "or", "n": "sum", "f": "sum"}
    results, actors = await allreduce_over_sockets(values, ops)
    core = 1 << (size.bit_length() - 1)
    log_core = core.bit_length() - 1
    assert actors[0].steps == log_core + (2 if size > core else 0)
    assert actors[0].steps < 2 * max(int(np.ceil(np.log2(size))), 1)  # the tree's up and down
    for rank, actor in enumerate(actors):
        assert actor.steps == (2 if rank >= core else actors[0].steps if rank < size - core
                               else log_core)
    for result in results:
        np.testing.assert_array_equal(result["t"], np.minimum.reduce([v["t"] for v in values]))
        np.testing.assert_array_equal(result["o"], np.bitwise_or.reduce([v["o"] for v in values]))
        np.testing.assert_array_equal(result["n"], np.sum([v["n"] for v in values], axis=0))
        np.testing.assert_allclose(result["f"], np.sum([v["f"] for v in values], axis=0),
                                   rtol=1e-14)
        assert result["f"].tobytes() == results[0]["f"].tobytes()  # the same bits everywhere
