"""Distributed schedulers over frames of several tiles give the single-process image.

Under domain decomposition (``domain``, ``async``) a node can own none of the domains a tile's
camera rays of its share enter first: its whole share of the tile waits in the outbox for
other nodes. The scene here makes that certain rather than a matter of timing: two boxes, one
domain each (domain d belongs to node d mod 2), the first in the top rows of the image only,
the second in the bottom rows only, too far apart for an AO ray of one to reach the other. A
tile of bottom rows holds no ray for node 0's domain at all, one of top rows none for node 1's,
while a single tile of the whole frame holds work for both nodes.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render
from vastray.render.scene_config import load_scene_config
from vastray.scene.store import Store, StoreWriter

from scenes import mesh_arrays, settings

SCENE_TOML = """
[camera]
position = [0.0, 0.0, 6.0]
look_at = [0.0, 0.0, 0.0]
fov = 40.0
[[light]]
type = "point"
position = [0.0, 0.0, 4.0]
intensity = 20.0
[[light]]
type = "ambient"
radiance = 0.2
"""

SCHEDULERS = ["image", "spec-ooc", "domain", "async", "dynamic", "spec-insitu"]


@pytest.fixture(scope="module")
def two_boxes(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiles")
    top = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    top.apply_translation([-1.5, 1.2, 0.0])
    bottom = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    bottom.apply_translation([1.5, -1.2, 0.0])
    with StoreWriter(root / "store") as writer:
        writer.add_domain(mesh_arrays(top))     # domain 0: node 0 of 2
        writer.add_domain(mesh_arrays(bottom))  # domain 1: node 1 of 2
    (root / "scene.toml").write_text(SCENE_TOML)
    return Store(root / "store"), root / "scene.toml"


# Path tracing on every scheduler; ambient occlusion on one by default, on all with -m slow.
@pytest.mark.parametrize("scheduler, integrator", [
    pytest.param(s, i, marks=[pytest.mark.slow] if i == "ao" and s != "image" else [])
    for s in SCHEDULERS for i in ("ao", "pt")])
def test_multi_tile_frames_give_the_reference_image(two_boxes, scheduler, integrator):
    store, toml = two_boxes
    st = settings(width=16, height=16, spp=2, integrator=integrator)
    reference = render(store, load_scene_config(toml), st, progress=False).film
    # 512 paths in tiles of 64: two image rows per tile, eight tiles.
    for tile in (512, 64):
        result = render_distributed(store.path, toml, st, 2,
                                    options=JobOptions(scheduler=scheduler, cache=2,
                                                       max_samples_in_flight=tile), timeout=60)
        what = f"{scheduler} on 2 nodes, tiles of {tile} paths"
        np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6,
                                   atol=1e-6, err_msg=what)
        np.testing.assert_array_equal(result.film.count, reference.count, err_msg=what)
        np.testing.assert_array_equal(result.film.depth, reference.depth, err_msg=what)
        per_node = result.counters["per_node"]
        sent = sum(n["counters"].get("batches_sent", 0) for n in per_node)
        assert sent == sum(n["counters"].get("batches_received", 0) for n in per_node)


def test_the_scene_puts_each_node_alone_in_some_tiles(two_boxes):
    """The premise above: some tiles' camera rays enter only node 1's domain, some only node
    0's, and the whole frame's enter both."""
    from vastray.actors.render_setup import RenderSetup
    from vastray.render.driver import path_context
    from vastray.render.integrators import camera_rays

    store, toml = two_boxes
    st = settings(width=16, height=16, spp=2, integrator="ao")
    setup = RenderSetup.of(store, load_scene_config(toml), st)
    entered = []
    for first in range(0, setup.total_paths, 64):
        ctx = path_context(setup.shading, st, first, first + 64, setup.ao_distance)
        rays = camera_rays(setup.camera, ctx)
        ray, domain, _, _ = setup.geometry.crossings(rays.origin, rays.direction,
                                                     np.full(len(rays), np.inf, np.float32))
        entered.append(set(np.unique(domain).tolist()))
    assert {1} in entered and {0} in entered
    assert set().union(*entered) == {0, 1}
