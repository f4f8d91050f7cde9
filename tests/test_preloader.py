"""The domain preloader actor and the cache under it: priority eviction, protected domains,
the capacity bound, loading ahead while the caller works, and emulated storage bandwidth."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions, JobOptionsError
from vastray.actors.node_state import NodeState
from vastray.actors.preloader import DomainPreloader
from vastray.scene.cache import DomainCache

from scenes import bumpy_scene, write_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("pre") / "s.store", bumpy_scene(), grid=(2, 2, 2))


def nonempty(store) -> list[int]:
    return [d.id for d in store.domains if d.n_triangles]


def test_lowest_priority_is_evicted_and_the_cache_never_overflows(store):
    ids = nonempty(store)[:4]
    cache = DomainCache(store, 2)
    priority = np.zeros(len(store.domains))
    priority[ids[0]], priority[ids[1]] = 5.0, 1.0
    cache.prioritise(priority)
    cache.get(ids[0])
    cache.get(ids[1])
    cache.get(ids[2])  # evicts ids[1], the lower priority, though ids[0] is older
    assert set(cache.resident()) == {ids[0], ids[2]}
    assert len(cache.resident()) <= 2
    cache.prioritise(None)  # back to least recently used
    cache.get(ids[3])
    assert set(cache.resident()) == {ids[2], ids[3]}


def test_a_preload_never_evicts_a_protected_domain(store):
    ids = nonempty(store)[:3]
    cache = DomainCache(store, 2)
    cache.get(ids[0])
    cache.get(ids[1])
    cache.prioritise(np.zeros(len(store.domains)), protect={ids[0], ids[1]})
    cache.prefetch(ids[2])  # only protected domains could make room: no preload
    cache.close()
    assert set(cache.resident()) == {ids[0], ids[1]}
    assert cache.stats.preloads == 0
    cache.prioritise(None, protect={ids[0]})
    cache.prefetch(ids[2])
    cache.close()
    assert set(cache.resident()) == {ids[0], ids[2]}
    assert cache.stats.preloads == 1


def test_preloading_overlaps_the_callers_work(store):
    ids = nonempty(store)[:2]

    async def run():
        preloader = DomainPreloader(store, 2, load_bandwidth=store.domains[ids[1]].nbytes / 0.3)
        try:
            await preloader.get(ids[0])
            preloader.preload(ids[1])
            await asyncio.sleep(0.5)  # the render worker traces meanwhile
            await preloader.get(ids[1])
            return preloader.stats()
        finally:
            preloader.close()

    stats = asyncio.run(run())
    assert stats["preloads"] == 1
    # The first load was waited for; the preloaded one (>= 0.3 s) was not, or barely.
    assert stats["load_wait_s"] < stats["load_s"]
    assert stats["bytes_loaded"] == sum(store.domains[d].nbytes for d in ids)


def test_emulated_bandwidth_bounds_the_load_time(store):
    domain = nonempty(store)[0]
    size = store.domains[domain].nbytes
    cache = DomainCache(store, 1, load_bandwidth=size / 0.25)  # 0.25 s per load
    start = time.perf_counter()
    cache.get(domain)
    assert time.perf_counter() - start >= 0.25
    assert cache.stats.throttle_seconds > 0
    with pytest.raises(ValueError, match="bandwidth"):
        DomainCache(store, 1, load_bandwidth=0.0)


def test_disabled_preloading_loads_nothing_ahead(store):
    ids = nonempty(store)[:2]
    preloader = DomainPreloader(store, 2, preload=False)
    preloader.preload(ids[0])
    preloader.close()
    assert preloader.stats()["loads"] == 0


def test_node_bandwidth_per_rank():
    assert JobOptions().load_bytes_per_second(0) is None
    assert JobOptions(load_bandwidth=50).load_bytes_per_second(1) == 50e6
    assert JobOptions(load_bandwidth=[100, 50]).load_bytes_per_second(3) == 50e6


def test_node_state_keeps_one_preloader_across_frames(store):
    state = NodeState()
    first = state.preloader_for(store, 2, frozenset(), JobOptions(threads=1), rank=0)
    assert state.preloader_for(store, 3, frozenset(), JobOptions(threads=1), rank=0) is first
    assert not first.cache.drop_page_cache
    state.close()


def test_a_later_frame_holding_more_domains_keeps_them_all_resident(store):
    """An in-situ node whose later frame holds more domains than its first (another camera
    gives it more holdings) gets the capacity for them: none of the frame's is evicted."""
    ids = nonempty(store)[:4]
    state = NodeState()
    options = JobOptions(threads=1)
    preloader = state.preloader_for(store, 2, frozenset(), options, rank=0)
    assert preloader.capacity == 2
    assert state.preloader_for(store, 4, frozenset(), options, rank=0) is preloader
    assert preloader.capacity == 4
    for domain in ids:
        preloader.cache.get(domain)
    assert set(preloader.cache.resident()) == set(ids)
    assert preloader.cache.stats.evictions == 0
    state.preloader_for(store, 1, frozenset(), options, rank=0)  # never lowered
    assert preloader.capacity == 4
    state.close()


def test_a_node_reads_cold_when_the_job_says_so(store):
    state = NodeState()
    preloader = state.preloader_for(store, 2, frozenset(), JobOptions(cold_reads=True), rank=0)
    assert preloader.cache.drop_page_cache
    state.close()


def test_victim_names_the_domain_a_load_would_evict(store):
    ids = nonempty(store)[:3]
    cache = DomainCache(store, 2)
    assert cache.victim() is None  # room left: a load evicts nothing
    cache.get(ids[0])
    assert cache.victim() is None
    cache.get(ids[1])
    assert cache.victim() == ids[0]  # least recently used
    cache.get(ids[0])
    assert cache.victim() == ids[1]
    priority = np.zeros(len(store.domains))
    priority[ids[1]] = 1.0
    cache.prioritise(priority)
    assert cache.victim() == ids[0]  # lowest priority first
    cache.get(ids[2])
    assert set(cache.resident()) == {ids[1], ids[2]}  # what victim() named went


def test_a_finished_preload_counts_once_against_the_capacity(store):
    # A preloaded domain must leave the pending set in the same step that makes it resident:
    # in between, it counted twice against the capacity and another preload's room check
    # evicted a domain it did not need to. Observed when the preload is counted.
    from vastray.scene.cache import CacheStats

    ids = nonempty(store)[:2]
    cache = DomainCache(store, 2)
    seen = []

    class Watched(CacheStats):
        def __setattr__(self, name, value):
            if name == "preloads" and value:
                seen.append((len(cache._resident), len(cache._pending)))
            super().__setattr__(name, value)

    cache.stats = Watched()
    cache.get(ids[0])
    cache.prefetch(ids[1])
    cache.get(ids[1])  # waits for the preload
    cache.close()
    assert seen == [(2, 0)]


def test_a_load_holds_up_no_other_threads_hit_and_a_domain_loads_once(store):
    # Issue 42: DomainCache.get held its lock through the read, the bandwidth wait and the BVH
    # build, so a thread asking for a resident domain waited for another thread's whole load.
    import threading

    ids = nonempty(store)[:2]
    size = store.domains[ids[1]].nbytes
    cache = DomainCache(store, 4, load_bandwidth=size / 3.0)  # a load lasts at least 3 s
    cache.load_bandwidth = None
    cache.get(ids[0])  # resident, loaded at disk speed
    cache.load_bandwidth = size / 3.0
    loading = [threading.Thread(target=cache.get, args=(ids[1],)) for _ in range(2)]
    for thread in loading:
        thread.start()
    deadline = time.monotonic() + 30
    while ids[1] not in cache.resident_set() and time.monotonic() < deadline:
        time.sleep(0.01)  # the slow load is under way
    assert ids[1] in cache.resident_set() and ids[1] not in cache
    assert cache.get(ids[0]) is not None  # a hit, served while the load goes on
    assert ids[1] not in cache and any(t.is_alive() for t in loading)
    for thread in loading:
        thread.join(timeout=60)
    assert ids[1] in cache
    assert cache.load_count(ids[1]) == 1  # the second thread waited for the first's load
    cache.close()


def test_a_read_ahead_takes_no_slot_and_its_load_only_builds(store):
    ids = nonempty(store)[:3]
    cache = DomainCache(store, 1, load_bandwidth=store.domains[ids[1]].nbytes / 0.2)
    try:
        first = cache.get(ids[0])
        cache.read_ahead(ids[1])  # the cache is full: a preload would evict ids[0]
        assert cache.resident() == [ids[0]] and cache.stats.reads_ahead == 1
        time.sleep(0.4)  # the render traces meanwhile; the read (>= 0.2 s) runs on
        start = time.perf_counter()
        loaded = cache.get(ids[1])
        assert time.perf_counter() - start < 0.15  # the read was not waited for again
        assert cache.stats.reads_ahead_used == 1 and cache.stats.loads == 2
        assert cache.stats.read_seconds >= 0.2  # the read ahead counted as its load's read
        # the same BVH a load without reading ahead builds: the same hits
        fresh = DomainCache(store, 1).load(ids[1])
        origin = np.tile(store.domains[ids[1]].lo - 1.0, (64, 1)).astype(np.float32)
        target = np.random.default_rng(0).uniform(store.domains[ids[1]].lo,
                                                  store.domains[ids[1]].hi, (64, 3))
        direction = (target - origin).astype(np.float32)
        far = np.full(64, np.inf, np.float32)
        a, b = loaded.intersect(origin, direction, far), fresh.intersect(origin, direction, far)
        assert (a["primID"] >= 0).any()
        np.testing.assert_array_equal(a["primID"], b["primID"])
        np.testing.assert_array_equal(a["tfar"], b["tfar"])
        del first
    finally:
        cache.close()


def damaged_copy(store, tmp_path, count: int):
    """A copy of ``store`` and the first ``count`` non-empty domain ids of it, the last one's
    indices file overwritten with garbage."""
    import shutil

    from vastray.scene.store import Store

    copy = shutil.copytree(store.path, tmp_path / "copy.store")
    damaged = Store(copy)
    ids = nonempty(damaged)[:count]
    (copy / damaged.domains[ids[-1]].files["indices"]).write_bytes(b"garbage")
    return damaged, ids


def test_a_replaced_read_ahead_is_not_used_and_a_bad_file_fails_its_load(store, tmp_path):
    damaged, ids = damaged_copy(store, tmp_path, 3)
    cache = DomainCache(damaged, 1)
    try:
        cache.get(ids[0])
        cache.read_ahead(ids[1])
        cache.read_ahead(ids[2])  # replaces ids[1]'s read
        cache.get(ids[1])
        assert cache.stats.reads_ahead == 2 and cache.stats.reads_ahead_used == 0
        with pytest.raises(Exception, match="indices"):
            cache.get(ids[2])  # the read ahead's error, raised by the load that takes it
    finally:
        cache.close()


def test_a_cache_holding_every_domain_reads_ahead_too(store):
    # in core the preloader is one domain ahead: without a read ahead each of its loads read
    # and then built, and the render waited for every read
    ids = nonempty(store)[:2]
    cache = DomainCache(store, len(store.domains))
    try:
        cache.get(ids[0])
        cache.read_ahead(ids[1])
        cache.get(ids[1])
        assert cache.stats.reads_ahead == cache.stats.reads_ahead_used == 1
        assert cache.stats.loads == 2 and cache.stats.evictions == 0
    finally:
        cache.close()


def test_a_domain_built_ahead_holds_the_kept_slot_and_evicts_only_when_taken(store):
    ids = nonempty(store)[:5]
    assert len(store.domains) > 3
    cache = DomainCache(store, 3, build_ahead=True)
    try:
        assert cache.builds_ahead
        for d in ids[:3]:
            cache.get(d)
        # one slot of the three is kept for the domain built ahead: two stay resident
        assert len(cache.resident()) == 2 and cache.victim() == cache.resident()[0]
        resident = set(cache.resident())
        cache.build_ahead(ids[3])
        cache._built[ids[3]].result()  # built, and nothing evicted for it
        assert set(cache.resident()) == resident and cache.stats.loads == 3
        assert cache.stats.builds_ahead == 1 and cache.stats.builds_ahead_used == 0
        taken = cache.get(ids[3])  # taken: counted as a load now, evicting the victim
        assert taken.domain_id == ids[3] and cache.stats.builds_ahead_used == 1
        assert cache.stats.loads == 4 and len(cache.resident()) == 2
        assert ids[3] in cache.resident()
        assert cache.stats.peak_resident_domains <= 3  # never more built than the capacity
    finally:
        cache.close()


def test_a_replaced_build_ahead_is_no_load_and_a_failed_one_fails_the_get(store, tmp_path):
    damaged, ids = damaged_copy(store, tmp_path, 4)
    cache = DomainCache(damaged, 3, build_ahead=True)
    try:
        cache.get(ids[0])
        cache.build_ahead(ids[1])
        cache.build_ahead(ids[2])  # replaces ids[1]'s, finished or not
        cache.get(ids[1])
        assert cache.stats.builds_ahead == 2 and cache.stats.builds_ahead_used == 0
        assert cache.stats.loads == 2  # ids[0] and ids[1]'s own load; the replaced one none
        cache.build_ahead(ids[3])
        with pytest.raises(Exception, match="indices"):
            cache.get(ids[3])  # the build's error, raised by the get that takes it
        assert ids[3] not in cache.resident_set()
    finally:
        cache.close()


def test_build_ahead_is_off_where_it_has_no_slot_to_keep(store):
    assert not DomainCache(store, len(store.domains), build_ahead=True).builds_ahead  # in core
    assert not DomainCache(store, 2, build_ahead=True).builds_ahead  # no room for a preload
    assert not DomainCache(store, 3).builds_ahead  # not asked
    preloader = DomainPreloader(store, 3, build_ahead=True, preload=False)
    assert not preloader.builds_ahead  # preloading off: nothing is loaded ahead
    preloader.close()
    assert not JobOptions(scheduler="spec-ooc").build_ahead  # a switch, off by default
    with pytest.raises(JobOptionsError, match="'build_ahead' must be true or false"):
        JobOptions(scheduler="spec-ooc", build_ahead="yes")
