"""What a recording frame writes into the virtual portals, on real stores and Embree (notes §5,
acceptance A11 known value and A12 replay), with the node's own schedule (``ImageSchedule``
with ``SimplifiedRouting``) driven in one process over every domain."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from vastray.actors.render_setup import RenderSetup
from vastray.render.driver import path_context
from vastray.render.integrators import camera_rays
from vastray.render.scene_config import parse_scene_config
from vastray.scene.bvh import DomainBVH
from vastray.scene.cache import DomainCache
from vastray.scene.simplify import build_simplified
from vastray.scene.store import Store, StoreWriter
from vastray.schedule.image import ImageSchedule
from vastray.schedule.portals import CrossingLog, Portals, luminance, prediction_accuracy
from vastray.schedule.simplified import SimplifiedRouting

from scenes import POINT_AND_SKY_TOML, bumpy_scene, mesh_arrays, settings, write_store


def run_frame(store: Store, config, frame_settings, recording: bool = True,
              portals: Portals | None = None, simplified: DomainBVH | None = None,
              threshold: float = 0.5, log: bool = True):
    """One frame of the portal policy through the node's schedule on one process: every
    domain local and loaded.

    Returns
    -------
    (schedule, routing): the routing holds the portals (recorded, or predicted with), its
    counters and, when recording with ``log``, the crossing log.
    """
    setup = RenderSetup.of(store, config, frame_settings)
    lo, hi = store.domain_boxes()
    portals = Portals(len(store.domains)) if portals is None else portals
    routing = SimplifiedRouting(simplified, len(store.domains), "portal", lo, hi,
                                portals=portals, recording=recording, threshold=threshold)
    if recording and log:
        routing.log = CrossingLog(setup.total_paths)
    ctx = path_context(setup.shading, frame_settings, 0, setup.total_paths, setup.ao_distance)
    schedule = ImageSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range,
                             simple=routing)
    schedule.start(camera_rays(setup.camera, ctx))
    cache = DomainCache(store, len(store.domains), setup.keep)
    try:
        while (domain := schedule.next_domain(cache.resident_set())) is not None:
            schedule.process(domain, cache.get(domain))
    finally:
        cache.close()
    return schedule, routing


# --- A11: a known value -----------------------------------------------------------------------

WALL_AND_FLOOR_TOML = """
[camera]
position = [0.0, 2.0, 6.0]
look_at = [0.0, 2.0, 0.0]
fov = 20.0
[[light]]
type = "directional"
direction = [0.0, -1.0, 0.0]
irradiance = {irradiance}
[material]
diffuse = {albedo}
specular = 0.0
"""


@pytest.fixture(scope="module")
def wall_and_floor(tmp_path_factory) -> Store:
    """Domain 0: a thin wall facing the camera (+z), filling its view, lit edge-on (cos 0);
    domain 1: a large thin floor below it, its top lit at normal incidence. Depth-1 rays
    from the wall leave the wall's box through its portal and either come down on the floor
    or escape to the empty sky."""
    wall = trimesh.creation.box(extents=[6.0, 3.0, 0.1])
    wall.apply_translation([0.0, 2.0, 0.0])  # y in [0.5, 3.5], front face at z = 0.05
    floor = trimesh.creation.box(extents=[200.0, 0.1, 200.0])
    floor.apply_translation([0.0, -0.05, 0.0])  # top face at y = 0
    path = tmp_path_factory.mktemp("a11") / "wall.store"
    with StoreWriter(path) as writer:
        writer.add_domain(mesh_arrays(wall))
        writer.add_domain(mesh_arrays(floor))
    return Store(path)


@pytest.mark.parametrize("albedo,irradiance", [(0.5, 2.0), ([0.2, 0.5, 0.8], 3.0)])
def test_a11_diffuse_plane_at_normal_incidence_records_albedo_irradiance_over_pi(
        wall_and_floor, albedo, irradiance):
    # The recorded value is the luminance of the direct light at the crossing ray's hit over
    # its throughput (notes §5; schedule.image: k * contribution / beta per lit shadow ray, k
    # = 1 for a directional light): for a Lambertian floor of albedo rho lit at normal
    # incidence by irradiance E, contribution / beta = rho / pi * E * cos(0) = rho E / pi.
    store = wall_and_floor
    config = parse_scene_config(WALL_AND_FLOOR_TOML.format(
        albedo=json.dumps(albedo), irradiance=json.dumps(irradiance)), "a11.toml")
    rho = np.broadcast_to(np.asarray(albedo, float), 3)  # a number or [r, g, b]
    expected = float(luminance(rho[None] * irradiance / np.pi)[0])
    _, routing = run_frame(store, config, settings(width=24, height=16, spp=2, bounces=1))
    portals = routing.portals
    assert routing.counters["portal_crossings"] > 300  # most wall paths bounce out of its box

    domain, face, i, j, angle = np.nonzero(portals.recorded)
    values = portals.values[portals.recorded]
    # only the wall's +z face is crossed (camera rays hit the wall's front only)
    assert set(domain) == {0} and set(face) == {5}
    # up-going directions (phi quadrants 0, 1: +y side of the face's v = y axis) escape to
    # the sky and record 0; down-going ones come down on the floor: rho E / pi, and at most a
    # few grazing ones escape past its edge
    up, down = angle % 4 < 2, angle % 4 >= 2
    assert up.sum() > 20 and down.sum() > 20
    np.testing.assert_array_equal(values[up], 0.0)
    lit = down & (values > 0)
    np.testing.assert_allclose(values[lit], expected, rtol=1e-6)
    assert lit.sum() >= 0.9 * down.sum()
    np.testing.assert_array_equal(values[down & ~lit], 0.0)
    # unrecorded cells: value 0, predict +inf (traced fine); the floor's portal is untouched
    assert not portals.values[~portals.recorded].any()
    assert not portals.recorded[1].any()
    assert np.isinf(portals.predict(np.flatnonzero(~portals.recorded)[::97])).all()
    # the crossing log saw the same crossings and the same values
    cells, actual = routing.log.crossings()
    assert len(cells) == routing.counters["portal_crossings"]
    assert set(np.unique(cells)) == set(np.flatnonzero(portals.recorded))
    hit = actual > 0
    np.testing.assert_allclose(actual[hit], expected, rtol=1e-6)
    assert hit.mean() > 0.3


# --- A12: replay ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    store = write_store(tmp_path_factory.mktemp("a12") / "grid", bumpy_scene(), grid=(3, 2, 3))
    build_simplified(store, 0.2, min_faces=50)
    store = Store(store.path)
    config = parse_scene_config(POINT_AND_SKY_TOML, "scene.toml")
    frame = settings(width=32, height=24, spp=2, bounces=2)
    model = DomainBVH(len(store.domains), store.load_simplified())  # depth >= 2 goes there
    schedule, routing = run_frame(store, config, frame, simplified=model)
    return store, config, frame, model, schedule, routing


def test_a12_replaying_the_recorded_frame_has_no_false_lows(bumpy):
    routing = bumpy[-1]
    cells, actual = routing.log.crossings()
    assert len(cells) == routing.counters["portal_crossings"] > 500
    predicted = routing.portals.predict(cells)
    assert np.all(predicted >= actual)  # cells keep maxima
    false_highs = 0
    for tau in [0.0, *np.quantile(actual[actual > 0], [0.1, 0.5, 0.9])]:
        acc = prediction_accuracy(predicted, actual, tau)
        assert acc.crossings == len(cells)
        assert acc.false_low == 0
        assert acc.agree == acc.crossings - acc.false_high  # below 100 % only by false highs
        assert 0 < acc.predicted_low < acc.crossings
        false_highs += acc.false_high
    assert false_highs > 0  # shared cells do mispredict: crossings darker than their cell's max


def test_a12_predicting_with_the_portal_routes_as_the_classification_says(bumpy):
    # The same frame and seed predicted with its own portals: the routing diverts exactly the
    # crossings the pure classification calls low (at two thresholds), so Simple/total of a
    # timed run is what the instrumented classification measures.
    store, config, frame, model, _, recorded = bumpy
    cells, actual = recorded.log.crossings()
    for tau in (0.5, float(np.median(actual))):
        _, routing = run_frame(store, config, frame, recording=False,
                               portals=recorded.portals.copy(), simplified=model, threshold=tau)
        acc = prediction_accuracy(recorded.portals.predict(cells), actual, tau)
        assert routing.counters["portal_crossings"] == acc.crossings
        assert routing.counters["predicted_low"] == acc.predicted_low > 0
        assert routing.counters["simplified_rays"] > acc.predicted_low  # and depth >= 2
        assert routing.counters["portal_records"] == 0
        assert routing.portals == recorded.portals  # predicting records nothing


def test_recording_images_do_not_depend_on_the_log(bumpy):
    # The instrumented hook only watches: the same frame without a log gives the same image
    # and the same portals.
    store, config, frame, model, logged, recorded = bumpy
    plain, routing = run_frame(store, config, frame, simplified=model, log=False)
    assert routing.log is None
    np.testing.assert_array_equal(plain.result.radiance, logged.result.radiance)
    assert routing.portals == recorded.portals
