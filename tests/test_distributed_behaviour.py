"""What the distributed schedulers do, beyond giving the reference image: ``async`` has no
barrier inside a frame, ray delivery cannot deadlock however many domains and however small
the batches, ``spec-insitu`` speculates."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render
from vastray.render.scene_config import load_scene_config
from vastray.scene.store import DomainArrays

from scenes import POINT_AND_SKY_TOML, bumpy_scene, settings, write_store

SCENE_TOML = POINT_AND_SKY_TOML


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("behaviour")
    (root / "scene.toml").write_text(SCENE_TOML)
    return write_store(root / "s.store", bumpy_scene(), grid=(3, 2, 3)), root / "scene.toml"


def _reference(store, toml, st):
    return render(store, load_scene_config(toml), st, progress=False).film


def test_async_has_one_barrier_per_frame_of_many_tiles(scene):
    store, toml = scene
    st = settings(width=32, height=24, spp=2, integrator="pt")
    result = render_distributed(store.path, toml, st, 3,
                                options=JobOptions(scheduler="async", max_samples_in_flight=200),
                                timeout=60)
    tiles = -(-32 * 24 * 2 // 200)
    assert tiles >= 8
    assert result.counters["global_barriers"] == 1
    reference = _reference(store, toml, st)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(result.film.count, reference.count)
    # tiles overlapped: some node held more than one tile's paths at once or took late rays
    assert sum(r["counters"]["tiles_made"] for r in result.counters["per_node"]) >= 3 * tiles


def test_the_cached_first_order_takes_the_fullest_cached_domain_first():
    from vastray.schedule.image import fullest  # async's order and the baseline's out of core

    waiting = np.array([5, 9, 0, 9, 3])
    assert fullest(waiting) == 1  # the fullest, ties -> lower id
    assert fullest(waiting, frozenset({0, 4})) == 0  # a cached one with rays goes first
    assert fullest(waiting, frozenset({2})) == 1  # cached but empty: the fullest
    assert fullest(waiting, frozenset({4, 3, 1})) == 1  # ties among the cached -> lower id


@pytest.mark.parametrize("resident_first", [False, True])
def test_async_with_a_small_cache_gives_the_reference_in_either_order(scene, resident_first):
    # Cached domains first (the default) or Galaxy's fullest-queue order: the same image.
    store, toml = scene
    st = settings(width=32, height=24, spp=2, integrator="pt")
    result = render_distributed(store.path, toml, st, 2,
                                options=JobOptions(scheduler="async", cache=2,
                                                   max_samples_in_flight=400,
                                                   resident_first=resident_first), timeout=60)
    reference = _reference(store, toml, st)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    per_node = [r["counters"] for r in result.counters["per_node"]]
    assert all(c["loads"] > c["cache_capacity"] for c in per_node)  # the cache was too small


def test_domain_rounds_are_barriers(scene):
    store, toml = scene
    st = settings(width=24, height=18, spp=1, integrator="ao")
    result = render_distributed(store.path, toml, st, 2,
                                options=JobOptions(scheduler="domain", max_samples_in_flight=200),
                                timeout=60)
    rounds = result.counters["per_node"][0]["counters"]["rounds"]
    assert result.counters["global_barriers"] == rounds > 1


def _soup(n_cells: int, seed: int = 5) -> DomainArrays:
    """Small triangles scattered through the unit cube, a few in every cell of an
    ``n_cells``^3 grid, so every domain of that grid holds triangles."""
    rng = np.random.default_rng(seed)
    cells = np.stack(np.meshgrid(*[np.arange(n_cells)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = (np.repeat(cells, 2, axis=0) + rng.uniform(0.2, 0.8, (2 * len(cells), 3))) / n_cells
    size = 0.3 / n_cells
    vertices = (centres[:, None, :] + rng.uniform(-size, size, (len(centres), 3, 3)))
    return DomainArrays(vertices.reshape(-1, 3).astype(np.float32),
                        np.arange(3 * len(centres), dtype=np.uint32).reshape(-1, 3))


@pytest.mark.parametrize("scheduler", ["async", "domain"])
def test_hundreds_of_domains_and_tiny_batches_never_deadlock(tmp_path, scheduler):
    # 512 domains over 3 nodes, batches of at most 2 rays: thousands of messages cross at
    # once, in both directions; bounded mailboxes used to stall every kind behind one.
    store = write_store(tmp_path / "soup", _soup(8), grid=(8, 8, 8))
    assert len(store.domains) == 512
    toml = tmp_path / "scene.toml"
    toml.write_text('[camera]\nposition = [1.6, 1.3, 2.2]\nlook_at = [0.5, 0.5, 0.5]\n'
                    '[[light]]\ntype = "ambient"\nradiance = 1.0\n')
    st = settings(width=32, height=24, spp=1, integrator="ao", shadow_samples=2,
                  ao_distance=0.2)
    result = render_distributed(store.path, toml, st, 3,
                                options=JobOptions(scheduler=scheduler, max_samples_in_flight=60,
                                                   max_batch_rays=2), timeout=120)
    reference = _reference(store, toml, st)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    sent = sum(r["counters"]["batches_sent"] for r in result.counters["per_node"])
    assert sent >= 500


def test_spec_insitu_speculates(scene):
    store, toml = scene
    st = settings(width=24, height=18, spp=2, integrator="pt")
    result = render_distributed(store.path, toml, st, 2,
                                options=JobOptions(scheduler="spec-insitu", max_samples_in_flight=400),
                                timeout=60)
    per_node = [r["counters"] for r in result.counters["per_node"]]
    assert sum(c["speculative_rays"] for c in per_node) > 0
    assert sum(c["wasted_rays"] for c in per_node) > 0  # speculation costs something
    assert sum(c["intersection_cache_hits"] for c in per_node) > 0  # and pays off
    # each node counted the CPU of cutting its copies into batches and copying peers' out
    assert all(c["bookkeeping_cpu_s"] > 0 for c in per_node), per_node


def test_dynamic_keeps_resident_domains_where_they_are(scene):
    # Nodes report every resident domain (not the last one traced), so with room for all of
    # them each domain is loaded once in the whole cluster, and the work is spread. (Room for
    # all: every node may hold every domain. The default, a node's initial share, fits only
    # while the ray-weighted schedule hands each node no more than that share.)
    store, toml = scene
    st = settings(width=32, height=24, spp=2, integrator="pt")
    result = render_distributed(store.path, toml, st, 2,
                                options=JobOptions(scheduler="dynamic", max_samples_in_flight=800,
                                                   cache=len(store.domains)),
                                timeout=60)
    loads = [r["counters"]["loads"] for r in result.counters["per_node"]]
    assert sum(loads) <= sum(d.n_triangles > 0 for d in store.domains)
    assert min(loads) > 0  # both nodes were handed domains
    assert result.counters["global_barriers"] > 1  # and it still works in rounds
    reference = _reference(store, toml, st)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
