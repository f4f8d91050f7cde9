"""A domain cache bounded by bytes (``DomainCache``'s ``max_bytes``, set by ``--memory-limit``):
it holds whichever domains fit the bytes, each counted as the preflight counts it, where a
count of domains had to assume the largest ones."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions, JobOptionsError
from vastray.actors.local import render_out_of_core
from vastray.planning import plan_render
from vastray.preflight import domain_footprints
from vastray.request import RenderRequest
from vastray.scene.cache import DomainCache
from vastray.scene.errors import InputError

from scenes import bumpy_scene, camera_config, settings, write_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Domains of unequal sizes: the displaced sphere's cells against the ground's."""
    return write_store(tmp_path_factory.mktemp("bytes") / "s.store", bumpy_scene(),
                       grid=(3, 2, 3))


def nonempty(store) -> list[int]:
    return [d.id for d in store.domains if d.n_triangles]


def sizes(store) -> np.ndarray:
    return np.asarray(domain_footprints(store.domains), np.int64)


def test_the_store_has_domains_of_unequal_sizes(store):
    fp = sizes(store)[nonempty(store)]
    assert fp.max() > 2.5 * fp.min(), fp  # else the byte bound would hold what a count holds


def test_the_cache_never_holds_more_bytes_than_its_bound_and_more_domains_than_a_count(store):
    fp = sizes(store)
    ids = nonempty(store)
    largest = sorted(fp[ids], reverse=True)
    bound = int(sum(largest[:3]))  # a count-based cache under the same bytes holds 3
    cache = DomainCache(store, len(store.domains), max_bytes=bound)
    rng = np.random.default_rng(1)
    most = 0
    for domain in rng.choice(ids, 200):
        cache.get(int(domain))
        held = cache.resident()
        assert int(fp[held].sum()) <= bound
        assert cache.charged_bytes() == int(fp[held].sum())
        most = max(most, len(held))
    assert most > 3, most
    assert cache.stats.evictions > 0
    assert cache.stats.as_dict()["peak_resident_domains"] == most


def test_a_large_domain_evicts_as_many_small_ones_as_it_needs(store):
    fp = sizes(store)
    ids = sorted(nonempty(store), key=lambda d: fp[d])
    small, big = ids[:4], ids[-1]
    bound = int(fp[small].sum())
    assert fp[big] <= bound
    cache = DomainCache(store, len(store.domains), max_bytes=bound)
    for domain in small:
        cache.get(domain)
    assert cache.resident() == small and cache.stats.evictions == 0
    cache.get(big)
    assert big in cache.resident() and cache.charged_bytes() <= bound
    left = [d for d in small if d in cache.resident()]
    assert cache.stats.evictions == len(small) - len(left) >= 1
    assert int(fp[left].sum()) + int(fp[big]) <= bound
    # the least recently used went first
    assert left == small[len(small) - len(left):]


def test_victim_is_named_only_when_the_largest_domain_would_not_fit(store):
    fp = sizes(store)
    ids = sorted(nonempty(store), key=lambda d: fp[d])
    bound = int(fp[ids[-1]] + fp[ids[0]])
    cache = DomainCache(store, len(store.domains), max_bytes=bound)
    assert cache.victim() is None  # nothing resident
    cache.get(ids[0])
    assert cache.victim() is None  # room for the largest beside it
    cache.get(ids[1])
    if fp[ids[0]] + fp[ids[1]] + fp[ids[-1]] > bound:
        assert cache.victim() == ids[0]  # the least recently used


def test_a_parting_domain_stays_the_victim_for_one_use(store):
    ids = nonempty(store)[:3]
    cache = DomainCache(store, 3)
    for d in ids:
        cache.get(d)
    assert cache.victim() == ids[0]  # full: the least recently used goes next
    cache.parting(ids[0])
    cache.get(ids[0])  # served before it goes: still the victim
    assert cache.victim() == ids[0]
    cache.get(ids[0])  # the mark held for one use only
    assert cache.victim() == ids[1]
    cache.parting(ids[1])
    cache.get(ids[2])  # another domain's use clears the mark: ids[0] goes next
    cache.get(ids[1])  # used as any other: the most recently used
    assert cache.victim() == ids[0]
    cache.get(ids[0])
    assert cache.victim() == ids[2]


def test_a_preload_respects_the_bytes_and_never_evicts_a_protected_domain(store):
    fp = sizes(store)
    ids = sorted(nonempty(store), key=lambda d: fp[d])
    bound = int(fp[ids[-1]] + fp[ids[-2]])
    cache = DomainCache(store, len(store.domains), max_bytes=bound)
    try:
        cache.get(ids[-1])
        cache.prioritise(None, protect=(ids[-1],))
        cache.prefetch(ids[-2])  # fits beside it
        cache.get(ids[-2])
        assert sorted(cache.resident()) == sorted([ids[-1], ids[-2]])
        cache.prioritise(None, protect=(ids[-1], ids[-2]))
        cache.prefetch(ids[0])  # would need a protected domain's room: not started
        assert ids[0] not in cache.resident_set()
        assert cache.stats.preloads == 1 and cache.stats.evictions == 0
    finally:
        cache.close()


def test_a_byte_bound_must_be_positive_and_a_larger_reservation_lifts_it(store):
    with pytest.raises(ValueError, match="positive"):
        DomainCache(store, 2, max_bytes=0)
    cache = DomainCache(store, 2, max_bytes=10**9)
    cache.reserve(2)
    assert cache.max_bytes == 10**9
    cache.reserve(5)  # a frame whose holdings must all stay resident: the count governs
    assert cache.max_bytes is None and cache.capacity == 5
    with pytest.raises(JobOptionsError, match="cache_bytes"):
        JobOptions(scheduler="spec-ooc", cache=2, cache_bytes=0)
    options = JobOptions(scheduler="spec-ooc", cache=2, cache_bytes=123_456_789)
    assert JobOptions.from_wire(options.to_wire()) == options


def test_a_memory_limit_bounds_the_cache_by_bytes(store):
    """The plan gives the cache the room the limit leaves, and as its count the most domains
    that could fit in it (the smallest first, below the store's); a limit every domain fits
    under sets no byte bound."""
    request = RenderRequest(store=str(store.path), scheduler="spec-ooc", width=48, height=36,
                            spp=2, quiet=True)
    everything = plan_render(request)
    fp = sorted(domain_footprints(store.domains, False))
    tight = smallest_plan(request)
    room = tight.options.cache_bytes
    assert max(fp) <= room < sum(fp)
    smallest_first = int(np.searchsorted(np.cumsum(fp), room, side="right"))
    assert tight.options.cache == min(smallest_first, len(fp) - 1)
    roomy = plan_render(RenderRequest(**{**vars(request), "memory_limit": 20 << 30}))
    assert roomy.options.cache_bytes is None and everything.options.cache_bytes is None


def smallest_plan(request: RenderRequest):
    """The plan of ``request`` under the smallest ``--memory-limit`` the planner accepts (to
    the byte): its cache bounded by the bytes of little more than the largest domain."""
    def plan(limit):
        try:
            return plan_render(RenderRequest(**{**vars(request), "memory_limit": limit}))
        except InputError:  # too small for the film, the paths and the largest domain
            return None

    low, high = 1 << 20, 8 << 30
    assert plan(low) is None and plan(high) is not None
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (low, middle) if plan(middle) is not None else (middle, high)
    return plan(high)


def test_the_in_core_reference_under_a_limit_is_bounded_by_bytes_too(store):
    """``--scheduler reference --memory-limit``: the in-core renderer's cache (``FrameCache``)
    gets the bound, evicts and reloads, and the image is the unlimited render's."""
    request = RenderRequest(store=str(store.path), scheduler="reference", width=32, height=24,
                            spp=1, integrator="pt", quiet=True)
    tight = smallest_plan(request)
    assert tight.options.cache_bytes is not None
    bounded = tight.render_one(tight.config, tight.settings)
    whole = plan_render(request)
    unbounded = whole.render_one(whole.config, whole.settings)
    assert bounded.counters["cache_bytes"] == tight.options.cache_bytes
    assert unbounded.counters["cache_bytes"] is None
    assert bounded.counters["peak_resident_bytes"] <= tight.options.cache_bytes
    assert bounded.counters["loads"] > unbounded.counters["loads"]
    np.testing.assert_array_equal(bounded.film.image(), unbounded.film.image())


def test_a_render_bounded_by_bytes_gives_the_all_in_memory_image(store):
    fp = sizes(store)
    bound = int(2 * fp.max())
    config = camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0])
    st = settings(integrator="pt")
    bounded = render_out_of_core(store, config, st, options=JobOptions(
        scheduler="spec-ooc", cache=len(store.domains) - 1, cache_bytes=bound), progress=False)
    whole = render_out_of_core(store, config, st, options=JobOptions(scheduler="spec-ooc"),
                               progress=False)
    assert bounded.counters["cache_bytes"] == bound
    assert bounded.counters["loads"] > whole.counters["loads"]  # it evicted and reloaded
    np.testing.assert_array_equal(bounded.film.image(), whole.film.image())


@pytest.mark.parametrize("scheduler", ["spec-ooc", "async"])
def test_node_processes_bound_their_caches_by_the_bytes_the_job_gives(store, tmp_path, scheduler):
    """The byte bound travels with the job to real node processes (sort-first tiles and
    domain decomposition), each cache keeps to it, and the image is the whole-memory one."""
    from vastray.actors.coordinator import render_distributed

    bound = int(2 * sizes(store).max())
    st = settings(integrator="pt", width=24, height=18, spp=1)
    toml = tmp_path / "scene.toml"
    toml.write_text('[camera]\nposition = [3.0, 2.2, 4.5]\nlook_at = [0.0, -0.5, 0.0]\n')
    bounded = render_distributed(store.path, toml, st, 2, options=JobOptions(
        scheduler=scheduler, cache=len(store.domains) - 1, cache_bytes=bound), timeout=120)
    whole = render_distributed(store.path, toml, st, 2,
                               options=JobOptions(scheduler=scheduler), timeout=120)
    for node in bounded.counters["per_node"]:
        assert node["counters"]["cache_bytes"] == bound
        assert node["counters"]["peak_resident_bytes"] <= bound
    np.testing.assert_allclose(bounded.film.image(), whole.film.image(), rtol=1e-6, atol=1e-6)
