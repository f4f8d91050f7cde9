"""Out-of-core schedules (image baseline, SpRay spec-ooc) reproduce the reference image."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vastray.actors.local import render_out_of_core
from vastray.cli import main
from vastray.render.driver import render
from vastray.render.lights import AmbientLight, PointLight, QuadLight
from vastray.render.scene_config import SceneConfig
from vastray.scene.generate import generate
from vastray.scene.partition import partition_kd
from vastray.scene.readers import read_mesh
from vastray.scene.store import Store, StoreWriter

from scenes import bumpy_scene, camera_config, settings, write_store

LIGHTS = [PointLight(np.array([2.0, 3.0, 1.0]), np.full(3, 12.0)),
          QuadLight(np.array([-1.0, 3.0, -1.0]), np.array([0.0, 0.0, 0.8]),
                    np.array([0.8, 0.0, 0.0]), np.full(3, 4.0)),
          AmbientLight(np.full(3, 0.2))]


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("ooc") / "kd27", bumpy_scene(), kd=27)


@pytest.fixture(scope="module")
def config():
    return camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0], lights=LIGHTS)


def assert_same(image, reference, what):
    np.testing.assert_allclose(image, reference, rtol=1e-6, atol=1e-6, err_msg=what)


@pytest.mark.parametrize("integrator", ["ao", "pt"])
@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_schedules_match_reference_for_any_cache_and_tile(bumpy, config, integrator, scheduler):
    st = settings(width=40, height=30, spp=2, integrator=integrator, bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    for cache, in_flight in [(None, None), (7, None), (1, 700)]:
        result = render_out_of_core(bumpy, config, st, scheduler=scheduler, cache_capacity=cache,
                                    max_samples_in_flight=in_flight, progress=False)
        assert_same(result.film.image(), reference, f"{scheduler} cache={cache} tile={in_flight}")
        assert result.film.depth.tolist() == render(bumpy, config, st, progress=False
                                                    ).film.depth.tolist()


@pytest.mark.parametrize("history_depth", [0, 1, 2, 3])
def test_spec_ooc_any_history_depth_matches_reference(bumpy, config, history_depth):
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    reference = render(bumpy, config, st, progress=False).film.image()
    result = render_out_of_core(bumpy, config, st, scheduler="spec-ooc", cache_capacity=5,
                                history_depth=history_depth, progress=False)
    assert_same(result.film.image(), reference, f"H={history_depth}")
    windows = result.counters["windows"]
    assert windows == -(-4 // (1 + min(history_depth, 3)))  # ceil(vertices / window)


def test_speculation_loads_fewer_domains_and_reports_its_waste(bumpy, config):
    st = settings(width=48, height=36, spp=2, integrator="pt", bounces=3)
    base = render_out_of_core(bumpy, config, st, scheduler="image", cache_capacity=7,
                              progress=False).counters
    spec = render_out_of_core(bumpy, config, st, scheduler="spec-ooc", cache_capacity=7,
                              progress=False).counters
    assert spec["loads"] * 1.5 < base["loads"]
    assert spec["speculative_rays"] > 0 and 0 < spec["wasted_rays"] < spec["speculative_rays"]
    assert spec["filtered_rays"] > 0
    for counters in (base, spec):
        for key in ("loads", "cache_hits", "load_s", "rays_in_flight_peak", "preloads"):
            assert key in counters


def test_samples_in_flight_bound_peak_rays(bumpy, config):
    # SpRay's memory explosion (sections 5.1.2, 6) must not happen: with a tile of 500 paths
    # the peak number of queued rays does not grow with the samples per pixel.
    def peak(spp, tile):
        st = settings(width=24, height=18, spp=spp, integrator="pt", bounces=3)
        return render_out_of_core(bumpy, config, st, scheduler="spec-ooc", cache_capacity=7,
                                  max_samples_in_flight=tile, progress=False
                                  ).counters["rays_in_flight_peak"]

    bounded = [peak(spp, 500) for spp in (2, 8)]
    unbounded = peak(8, None)
    assert bounded[1] <= 2 * bounded[0]
    assert bounded[1] * 3 < unbounded


def test_generated_rm_scene(tmp_path):
    generate("rm", tmp_path / "rm", 40, grid=(3, 3, 2), seed=1)
    store = Store(tmp_path / "rm")
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=2, shadow_samples=2)
    reference = render(store, SceneConfig(), st, progress=False).film.image()
    for scheduler in ("image", "spec-ooc"):
        result = render_out_of_core(store, SceneConfig(), st, scheduler=scheduler,
                                    cache_capacity=4, progress=False)
        assert_same(result.film.image(), reference, scheduler)


@pytest.mark.shared_data
def test_real_mesh_bunny(shared_data, tmp_path):
    mesh = read_mesh(shared_data / "meshes" / "stanford_bunny.ply")
    with StoreWriter(tmp_path / "bunny") as writer:
        for dom in partition_kd(mesh, 8).domains:
            writer.add_domain(dom)
    store = Store(tmp_path / "bunny")
    for integrator in ("ao", "pt"):
        st = settings(width=32, height=32, spp=2, integrator=integrator, bounces=2,
                      shadow_samples=2)
        reference = render(store, SceneConfig(), st, progress=False).film.image()
        assert reference.max() > 0
        for scheduler in ("image", "spec-ooc"):
            result = render_out_of_core(store, SceneConfig(), st, scheduler=scheduler,
                                        cache_capacity=2, progress=False)
            assert_same(result.film.image(), reference, f"{scheduler} {integrator}")


def test_cli_cache_percentage_and_report(bumpy, tmp_path):
    out, report = tmp_path / "o.exr", tmp_path / "r.json"
    assert main(["render", str(bumpy.path), "-o", str(out), "--cache", "25%", "--width", "24",
                 "--height", "18", "--spp", "1", "--shadow-samples", "2", "--report",
                 str(report), "--quiet"]) == 0
    doc = json.loads(report.read_text())
    assert doc["scheduler"] == "spec-ooc"  # auto picks speculation when domains do not fit
    assert doc["counters"]["cache_capacity"] == 7  # ceil(25% of 27)
    assert doc["counters"]["max_samples_in_flight"] == 24 * 18
    for key in ("load", "render", "total"):
        assert doc["seconds"][key] >= 0
    with pytest.raises(SystemExit):
        main(["render", str(bumpy.path), "-o", str(tmp_path / "x.exr"), "--cache", "150%"])
    assert not (tmp_path / "x.exr").exists()
