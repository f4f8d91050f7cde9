"""``dynamic``'s frame takes the next tile in while the last one's rays thin out
(``actors.dynamic_frame``): fewer all-reductions than one tile at a time, the same image, at
most two tiles' path state on a node. Run on virtual nodes (``vastray.sim``), which run the
nodes' own frame code in one process, so a test can change ``MAX_TILES``; the real processes'
image is checked in ``test_tree_rounds.py`` and ``test_distributed_tiles.py``."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors import dynamic_frame
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render, shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.sim.cache import Domains
from vastray.sim.costs import CostModel
from vastray.sim.simulate import simulate

from scenes import rm_store

SETTINGS = RenderSettings(width=32, height=24, spp=2, bounces=2, shadow_samples=1, seed=5)
#: 1,536 paths in tiles of 128: twelve tiles
TILE = 128


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return rm_store(tmp_path_factory.mktemp("dynamic") / "rm.store", 32, (3, 2, 2))


@pytest.fixture(scope="module")
def domains(store):
    built = Domains(store, shading_inputs(store, SceneConfig(), SETTINGS.integrator)[1])
    yield built
    built.close()


def frame(store, domains, nodes: int, max_tiles: int, monkeypatch):
    monkeypatch.setattr(dynamic_frame, "MAX_TILES", max_tiles)
    options = JobOptions(scheduler="dynamic", cache=2, max_samples_in_flight=TILE)
    return simulate(store, options, nodes, CostModel(), SETTINGS, max_pass_spp=None,
                    domains=domains)


@pytest.mark.parametrize("nodes", [1, 3])
def test_the_next_tile_comes_in_early_and_saves_all_reductions(store, domains, nodes,
                                                               monkeypatch):
    reference = render(store, SceneConfig(), SETTINGS, progress=False).film.image()
    alone = frame(store, domains, nodes, 1, monkeypatch)
    pipelined = frame(store, domains, nodes, 2, monkeypatch)
    tiles = -(-SETTINGS.paths // TILE)
    for result in (alone, pipelined):
        assert np.array_equal(result.film.image(), reference)
        for counters in result.node_counters:
            # every node went through the same all-reductions
            assert counters["global_barriers"] == result.node_counters[0]["global_barriers"]
    one = alone.node_counters[0]
    two = pipelined.node_counters[0]
    # one tile at a time: each tile's rounds, then an all-reduction in which no ray waits
    assert one["most_tiles_in_flight"] == 1 and "rounds_with_tiles_overlapping" not in one
    assert one["global_barriers"] == one["rounds"] + tiles
    # two at a time: most tiles come in while the one before still has rays, so fewer
    # all-reductions find nothing waiting, and fewer rounds trace a few rays each
    assert two["most_tiles_in_flight"] == 2 and two["rounds_with_tiles_overlapping"] > 0
    assert two["global_barriers"] < one["global_barriers"]
    assert two["global_barriers"] - two["rounds"] < tiles
    assert two["rounds"] <= one["rounds"]


def test_the_next_tile_comes_in_under_an_eighth_of_a_tile_unless_rays_wait_for_an_unheld_domain():
    holder = np.array([0, 1, 2, 0])  # 3 nodes; every domain held
    below = dynamic_frame.TAKE_IN_BELOW
    assert dynamic_frame.takes_next_tile(np.array([0, 0, 1, 0]), holder, 3, tile=2 * below)
    assert not dynamic_frame.takes_next_tile(np.array([1, 0, 1, 0]), holder, 3, tile=2 * below)
    assert dynamic_frame.takes_next_tile(np.zeros(4, np.int64), holder, 3, tile=1)
    # rays wait for domain 3, which no node holds: rule 3 gives it a node only once some
    # node has no wanted domain, which a new tile's rays would put off
    unheld = np.array([0, 1, 2, 3])
    assert not dynamic_frame.takes_next_tile(np.array([0, 0, 0, 1]), unheld, 3, tile=64 * below)
    assert dynamic_frame.takes_next_tile(np.array([1, 0, 0, 0]), unheld, 3, tile=64 * below)


def test_a_tile_comes_in_only_under_one_tiles_rays_waiting(store, domains, monkeypatch):
    # a tile as large as the frame: nothing to overlap, one all-reduction finds no ray
    monkeypatch.setattr(dynamic_frame, "MAX_TILES", 2)
    options = JobOptions(scheduler="dynamic", cache=2, max_samples_in_flight=SETTINGS.paths)
    result = simulate(store, options, 2, CostModel(), SETTINGS, max_pass_spp=None,
                      domains=domains)
    counters = result.node_counters[0]
    assert counters["most_tiles_in_flight"] == 1
    assert counters["global_barriers"] == counters["rounds"] + 1
