"""``domain`` and ``dynamic`` rounds end with all-reductions over the tree of ranks (issue 38):
the coordinator takes no message per round, whatever the number of rounds, every node computes
the same round, and the image is the single-process one. Real node processes, real sockets."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render
from vastray.render.scene_config import load_scene_config
from vastray.schedule.dynamic import RayWeightedRounds

from scenes import bumpy_scene, settings, write_store

SCENE_TOML = """
[camera]
position = [0.0, 0.4, 3.2]
look_at = [0.0, 0.0, 0.0]
[[light]]
type = "point"
position = [1.5, 2.0, 2.0]
intensity = 10.0
"""

#: What a node tells the coordinator: joining, liveness, progress, its film and report.
#: Nothing per round (``round`` and ``queues`` were one message per node and round).
PER_JOB_KINDS = {"hello", "heartbeat", "progress", "film", "done", "frame"}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("tree-rounds")
    (root / "scene.toml").write_text(SCENE_TOML)
    return write_store(root / "s.store", bumpy_scene(), grid=(3, 2, 3)), root / "scene.toml"


@pytest.mark.parametrize("scheduler", ["domain", "dynamic"])
def test_rounds_send_the_coordinator_nothing_and_give_the_reference(scene, scheduler):
    store, toml = scene
    st = settings(width=32, height=24, spp=2, integrator="pt")
    results = {}
    for tile in (400, 150):  # more tiles, more rounds: the coordinator's load must not grow
        results[tile] = render_distributed(
            store.path, toml, st, 3, options=JobOptions(scheduler=scheduler, cache=3,
                                                        max_samples_in_flight=tile),
            timeout=120)
    reference = render(store, load_scene_config(toml), st, progress=False).film
    for tile, result in results.items():
        np.testing.assert_array_equal(result.film.count, reference.count)
        np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
        per_node = [r["counters"] for r in result.counters["per_node"]]
        taken = per_node[0]["coordinator_messages"]
        assert set(taken) <= PER_JOB_KINDS, taken
        # every node went through the same rounds (the same all-reductions)
        assert len({c["global_barriers"] for c in per_node}) == 1
        assert result.counters["global_barriers"] == per_node[0]["global_barriers"] > 1
        tiles = -(-st.paths // tile)
        for c in per_node:
            if scheduler == "dynamic":
                # one all-reduction a round, and one where no ray waited anywhere: the frame's
                # end, and a tile's where the next one had not come in yet (at most one a tile)
                assert c["rounds"] + 1 <= c["global_barriers"] <= c["rounds"] + tiles
                assert 1 <= c["most_tiles_in_flight"] <= min(2, tiles)
            else:  # a round's rays leave in a batch per peer and queue, not per activation
                assert c["global_barriers"] == c["rounds"]
                assert c["batches_sent"] <= c["rounds"] * 2 * 2 * (3 - 1)
            # a node that took rays in counted the CPU of putting them in its queues
            if c["rays_received"]:
                assert c["bookkeeping_cpu_s"] > 0, c
        assert sum(c["rays_received"] for c in per_node) > 0
    few, many = (results[t].counters["per_node"][0]["counters"] for t in (400, 150))
    assert many["rounds"] > few["rounds"]
    assert many["coordinator_messages"]["film"] == few["coordinator_messages"]["film"] == 1
    assert many["coordinator_messages"]["done"] == few["coordinator_messages"]["done"] == 3


def test_every_node_computes_the_round_the_coordinator_computed():
    # the vectors each node all-reduces give the schedule the reports gave
    rng = np.random.default_rng(3)
    policy = RayWeightedRounds()
    for _ in range(200):
        size, n_domains = int(rng.integers(1, 6)), int(rng.integers(1, 12))
        queues = {r: {d: int(rng.integers(1, 50)) for d in range(n_domains)
                      if rng.random() < 0.3} for r in range(size)}
        loaded = {r: sorted(int(d) for d in rng.choice(n_domains, min(n_domains, int(rng.integers(0, 3))),
                                                        replace=False)) for r in range(size)}
        wanted = np.zeros(n_domains, np.int64)
        holder = np.full(n_domains, size, np.int64)
        for rank in range(size):
            for domain, count in queues[rank].items():
                wanted[domain] += count
            for domain in loaded[rank]:
                holder[domain] = min(holder[domain], rank)
        by_reports = policy.next_round(queues, loaded)
        by_vectors = policy.from_totals(wanted, holder, size)
        assert by_vectors.assign == by_reports.assign and by_vectors.finished == by_reports.finished
        # the rules: a held wanted domain stays with its lowest holder; a node gets at most
        # one new domain, and a busy one only where it stays within the busiest's kept rays
        kept = np.zeros(size, np.int64)
        for domain, node in by_vectors.assign.items():
            if holder[domain] < size:
                assert node == holder[domain]
                kept[node] += wanted[domain]
        new = {d: n for d, n in by_vectors.assign.items() if holder[d] >= size}
        assert len(new) == len(set(new.values()))
        for domain, node in new.items():
            assert kept[node] == 0 or kept[node] + wanted[domain] <= kept.max()
