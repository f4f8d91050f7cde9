"""Under a memory limit a domain cache gives the C heap's free memory back before a build
whenever the process's RSS is above ``TRIM_ABOVE`` of the limit (``scene.heap``): the fast
BVH's pieces leave freed build memory in the heap for the next builds, which the caches'
memory model does not charge."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions, JobOptionsError
from vastray.actors.local import render_out_of_core
from vastray.planning import job_options
from vastray.processes import rss_bytes
from vastray.request import RenderRequest
from vastray.scene.cache import DomainCache
from vastray.scene.heap import TRIM_ABOVE, rss_ceiling, trim_heap

from scenes import bumpy_scene, camera_config, settings, write_store


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("heap") / "kd8", bumpy_scene(), kd=8)


def test_rss_bytes_sees_memory_this_process_touches():
    before = rss_bytes()
    block = np.ones(50_000_000, np.uint8)  # 50 MB, every page written
    assert rss_bytes() - before > 40_000_000
    del block
    assert trim_heap() in (True, False)  # False only without glibc's malloc_trim


@pytest.mark.parametrize("ceiling, trims", [(1, True), (None, False), (1 << 60, False)])
def test_a_cache_trims_before_each_build_only_above_its_ceiling(bumpy, ceiling, trims):
    cache = DomainCache(bumpy, 2, rss_ceiling=ceiling)
    for domain in range(5):
        cache.get(domain)
    assert cache.stats.loads == 5
    assert cache.stats.heap_trims == (5 if trims and trim_heap() else 0)
    assert cache.stats.as_dict()["heap_trims"] == cache.stats.heap_trims


def test_the_ceiling_is_a_share_of_the_limit():
    assert rss_ceiling(None) is None
    assert rss_ceiling(6 << 30) == int(TRIM_ABOVE * (6 << 30))
    assert job_options(RenderRequest(memory_limit=6 << 30), "spec-ooc", 3).memory_limit == 6 << 30
    assert job_options(RenderRequest(), "spec-ooc", 3).memory_limit is None


def test_an_out_of_core_render_under_a_limit_trims_and_gives_the_same_image(bumpy):
    """A limit every RSS exceeds (1 byte): each build trims first, and the image is the
    unlimited render's bit for bit (the trim frees only memory nothing holds)."""
    config = camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0])
    st = settings(integrator="pt", bvh="fast")
    limited, unlimited = (render_out_of_core(
        bumpy, config, st, options=JobOptions(scheduler="spec-ooc", cache=3,
                                              memory_limit=memory_limit), progress=False)
        for memory_limit in (1, None))
    counters = limited.counters
    assert counters["loads"] > len(bumpy.domains)  # out of core: it reloaded
    assert counters["heap_trims"] == (counters["loads"] if trim_heap() else 0)
    assert unlimited.counters["heap_trims"] == 0
    np.testing.assert_array_equal(limited.film.image(), unlimited.film.image())


def test_the_limit_travels_to_the_nodes():
    options = JobOptions(scheduler="image", cache=4, memory_limit=3 << 30)
    assert JobOptions.from_wire(options.to_wire()).memory_limit == 3 << 30
    with pytest.raises(JobOptionsError, match="memory_limit"):
        JobOptions(scheduler="image", memory_limit=0)
