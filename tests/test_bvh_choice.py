"""``--bvh``: the fast (Morton) BVH is the render's choice, made from the store alone, so a
render's image is the same whatever the cache and the node count (``scene.bvh_choice``)."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from test_build_quality import rays

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.cli import main
from vastray.render.driver import render
from vastray.scene.bvh import DomainBVH
from vastray.scene.bvh_choice import FAST_TRIANGLES, describe, fast_builds
from vastray.scene.cache import DomainCache
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW, RTC_SCENE_FLAG_COMPACT, binding
from vastray.scene.embree.scenes import Scene
from vastray.scene.footprint import resident_bytes

from scenes import bumpy_scene, camera_config, settings, terrain_scene, write_store

needs_binding = pytest.mark.skipif(binding() is None, reason="the compiled Embree binding is "
                                                             "unavailable (embreex fallback)")


def test_auto_builds_fast_for_large_stores_only():
    assert not fast_builds("auto", FAST_TRIANGLES - 1)
    assert fast_builds("auto", FAST_TRIANGLES)
    assert fast_builds("fast", 10) and not fast_builds("quality", 10 * FAST_TRIANGLES)
    assert describe("auto", 30_300_000) == "fast (auto: 30.3 M triangles)"
    assert describe("quality", 30_300_000) == "quality"
    assert describe("auto", 5_204) == "quality (auto: 5,204 triangles)"
    with pytest.raises(ValueError, match="--bvh must be one of auto, fast, quality"):
        fast_builds("morton", 10)


def test_the_cache_builds_what_the_render_chose(tmp_path):
    store = write_store(tmp_path / "kd8", bumpy_scene(), kd=8)
    for capacity in (2, len(store.domains)):
        fast = DomainCache(store, capacity, fast_builds=True)
        assert fast.mesh_quality == RTC_BUILD_QUALITY_LOW
        assert fast.build_quality == RTC_BUILD_QUALITY_LOW  # (Embree reads the mesh's only so)
        assert DomainCache(store, capacity).mesh_quality is None
    # the fast BVH's bytes are the footprint's
    bvh = DomainCache(store, 2, fast_builds=True).get(0)
    assert bvh.nbytes() == resident_bytes(bvh.n_triangles, bvh._array_bytes, bvh.compiled,
                                          fast=True)


@needs_binding
@pytest.mark.parametrize("mesh", [bumpy_scene, terrain_scene])
def test_fast_builds_give_the_same_hits_build_after_build(mesh):
    """A domain is built again at every reload out of core: the Morton builder must give the
    same BVH each time, also while another build runs beside it (Embree's threads split
    both), or an out-of-core image would not be the in-core one."""
    arrays = mesh()
    origins, directions = rays(arrays, 20_000, seed=3)
    far = np.full(len(origins), np.inf, np.float32)

    def hits(bvh):
        r = bvh.intersect(origins, directions, far)
        return [r[k].tobytes() for k in ("primID", "tfar", "u", "v", "Ng")]

    first = hits(DomainBVH(0, arrays, mesh_quality=RTC_BUILD_QUALITY_LOW))
    assert (np.frombuffer(first[0], np.int32) >= 0).mean() > 0.5
    for _ in range(3):
        beside = threading.Thread(target=lambda: DomainBVH(1, terrain_scene(),
                                                           mesh_quality=RTC_BUILD_QUALITY_LOW))
        beside.start()
        again = DomainBVH(0, arrays, mesh_quality=RTC_BUILD_QUALITY_LOW)
        beside.join()
        assert hits(again) == first


@needs_binding
@pytest.mark.parametrize("mesh", [bumpy_scene, terrain_scene])
def test_the_fast_bvh_lays_its_leaves_out_compactly(mesh):
    """The fast BVH's leaves index the vertex buffer (Embree's compact layout, about 55 % of
    the memory of leaves holding copies of the vertices: ``scene.footprint``). Its triangle
    test rounds differently from the copied-vertex layout's, so a ray passing within float
    rounding of an edge may take the neighbouring triangle: the layout belongs to the
    render's choice of BVH, made from the store alone (``scene.bvh_choice``), like the
    builder. Rays aimed at vertices, where ties between triangles are decided, and
    axis-aligned rays (Embree's zero direction components) agree but for a few."""
    arrays = mesh()
    origins, directions = rays(arrays, 50_000, seed=5)
    axes = np.zeros((3_000, 3), np.float32)
    axes[np.arange(3_000), np.arange(3_000) % 3] = np.where(np.arange(3_000) % 2, 1.0, -1.0)
    centre = arrays.vertices.mean(axis=0)
    origins = np.concatenate([origins, centre - 3.0 * axes + 0.01 * np.random.default_rng(
        0).standard_normal((3_000, 3)).astype(np.float32)])
    directions = np.concatenate([directions, axes])
    far = np.full(len(origins), np.inf, np.float32)
    fast = DomainBVH(0, arrays, mesh_quality=RTC_BUILD_QUALITY_LOW)
    assert fast._scene.flags & RTC_SCENE_FLAG_COMPACT
    assert not DomainBVH(0, arrays)._scene.flags & RTC_SCENE_FLAG_COMPACT  # quality: copies
    copied = Scene(arrays.vertices, arrays.indices, mesh_quality=RTC_BUILD_QUALITY_LOW)
    a, b = fast.intersect(origins, directions, far), copied.intersect(origins, directions, far)
    assert (a["primID"] >= 0).mean() > 0.5  # the comparison is about hits
    other = a["primID"] != b["primID"]
    assert other.sum() <= 5, other.sum()  # 0-2 in 53,000 on these meshes
    np.testing.assert_allclose(a["tfar"], b["tfar"], rtol=1e-5)


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("bvh") / "kd12", bumpy_scene(), kd=12)


@pytest.fixture(scope="module")
def config():
    return camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0])


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_out_of_core_with_the_fast_bvh_is_the_in_core_fast_image(bumpy, config, scheduler):
    st = settings(integrator="pt", bvh="fast")
    reference = render(bumpy, config, st, progress=False)
    assert reference.counters["loads"] == len(bumpy.domains)
    result = render_out_of_core(bumpy, config, st, options=JobOptions(scheduler=scheduler,
                                                                      cache=3),
                                progress=False)
    assert result.counters["loads"] > len(bumpy.domains)  # it reloaded: built again
    np.testing.assert_allclose(result.film.image(), reference.film.image(), rtol=1e-6,
                               atol=1e-6)
    assert result.film.depth.tolist() == reference.film.depth.tolist()


def test_the_cli_builds_what_bvh_asks_on_nodes_too(bumpy, tmp_path):
    """``--bvh fast`` reaches every node (the settings travel with the job), and the report
    says which BVH was built."""
    common = [str(bumpy.path), "--width", "32", "--height", "24", "--spp", "2", "--bvh", "fast"]
    single, nodes = tmp_path / "single.exr", tmp_path / "nodes.exr"
    assert main(["render", *common, "-o", str(single), "--report",
                 str(tmp_path / "single.json")]) == 0
    assert main(["render", *common, "-o", str(nodes), "--nodes", "2", "--scheduler", "image",
                 "--cache", "3"]) == 0
    from vastray.render.imageio import read_exr

    np.testing.assert_allclose(read_exr(nodes), read_exr(single), rtol=1e-6, atol=1e-6)
    report = json.loads((tmp_path / "single.json").read_text())
    assert report["settings"]["bvh"] == "fast"
    assert report["settings"]["bvh_built"] == "fast"
    auto = tmp_path / "auto.json"
    assert main(["render", *common[:-2], "-o", str(tmp_path / "auto.exr"), "--report",
                 str(auto), "--quiet"]) == 0
    assert json.loads(auto.read_text())["settings"]["bvh_built"].startswith("quality (auto: ")
