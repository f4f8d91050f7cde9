"""``--threads`` is honoured by every runtime, and the image does not depend on it."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.driver import render
from vastray.render.scene_config import SceneConfig, load_scene_config

from scenes import bumpy_scene, settings, write_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("threads") / "s", bumpy_scene(), grid=(2, 2, 2))


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_out_of_core_schedules_split_queries_over_threads(store, scheduler, monkeypatch):
    import vastray.scene.bvh as bvh

    monkeypatch.setattr(bvh, "_SPLIT_MIN", 64)  # small batches split too, so threads work here
    st = settings(width=40, height=30, spp=4, integrator="pt")
    reference = render(store, SceneConfig(text=""), st, progress=False).film.image()
    for threads in (1, 2, 3):
        result = render_out_of_core(store, SceneConfig(text=""), st,
                                    options=JobOptions(scheduler=scheduler, cache=3, threads=threads),
                                    progress=False)
        assert result.counters["threads"] == threads
        np.testing.assert_array_equal(result.film.image(), reference)


def test_in_core_render_workers_trace_side_by_side_with_the_same_image(store):
    # one worker per thread, each tracing on its own thread; a frame of few batches is cut
    # finer so each worker has some (the image does not depend on how paths are batched)
    st = settings(width=40, height=30, spp=4, integrator="pt")
    reference = render(store, SceneConfig(text=""), st, threads=1, progress=False)
    assert reference.counters["render_workers"] == 1
    for threads in (2, 3):
        result = render(store, SceneConfig(text=""), st, threads=threads, progress=False)
        assert result.counters["threads"] == threads
        assert result.counters["render_workers"] == threads
        np.testing.assert_array_equal(result.film.image(), reference.film.image())
    bounded = render(store, SceneConfig(text=""), st, threads=2, cache_capacity=3,
                     progress=False)  # a bounded cache: one worker, queries split over threads
    assert bounded.counters["render_workers"] == 1
    np.testing.assert_array_equal(bounded.film.image(), reference.film.image())


@pytest.mark.parametrize("scheduler", ["image", "async", "spec-insitu"])
def test_nodes_get_their_share_of_the_cores(store, scheduler, tmp_path):
    toml = tmp_path / "scene.toml"
    toml.write_text("")
    st = settings(width=24, height=18, spp=2, integrator="ao")
    result = render_distributed(store.path, toml, st, 2,
                                options=JobOptions(scheduler=scheduler, threads=2,
                                                   max_samples_in_flight=300), timeout=60)
    assert [r["counters"]["threads"] for r in result.counters["per_node"]] == [2, 2]
    reference = render(store, load_scene_config(toml), st, progress=False).film.image()
    np.testing.assert_allclose(result.film.image(), reference, rtol=1e-6, atol=1e-6)
