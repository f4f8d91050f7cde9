"""SpRay's speculative in-situ decisions (``schedule/spec_insitu.py``) on one node, without
sockets: the t-buffer keys, shadow slots, which copies a node sends, and the resolution after
the all-reductions."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.render_setup import RenderSetup
from vastray.render.driver import path_context
from vastray.scene.bvh import DomainBVH
from vastray.schedule.ownership import interleaved_paths, zorder_owners
from vastray.schedule.spec_insitu import InSituSchedule, hit_keys, shadow_slots

from scenes import bumpy_config, bumpy_scene, settings, write_store


def test_hit_keys_order_by_t_then_domain():
    t = np.array([1.0, 1.0, 0.5, np.inf], np.float32)
    d = np.array([3, 2, 9, -1])
    keys = hit_keys(t, d)
    assert np.argsort(keys, kind="stable").tolist() == [2, 1, 0, 3]
    assert keys[0] > keys[1]  # same t: the lower domain wins the MIN


def test_shadow_slots_number_each_paths_rays_in_order():
    assert shadow_slots(np.array([4, 2, 4, 4, 2])).tolist() == [0, 0, 1, 2, 1]


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    """Node 0 of 2 over a bumpy store, with its own domains loaded."""
    store = write_store(tmp_path_factory.mktemp("insitu") / "s.store", bumpy_scene(),
                        grid=(2, 2, 2))
    st = settings(width=16, height=12, spp=1, integrator="pt", bounces=2)
    setup = RenderSetup.of(store, bumpy_config(), st)
    owner = zorder_owners(*store.domain_boxes(), 2)
    local = [d for d in np.nonzero(owner == 0)[0] if store.domains[d].n_triangles]
    bvhs = {int(d): DomainBVH(int(d), store.load_domain(int(d)), setup.keep) for d in local}
    ctx = path_context(setup.shading, st, 0, setup.total_paths, setup.ao_distance)
    return setup, ctx, owner, bvhs


def schedule_of(node, stats):
    setup, ctx, owner, bvhs = node
    mine = interleaved_paths(len(ctx.pixel), 0, 2)
    return InSituSchedule(ctx, setup.camera, mine, owner, 0, bvhs, setup.geometry,
                          setup.color_source, setup.scalar_range, stats)


def test_camera_rays_are_copied_into_every_domain_they_cross(node):
    setup = node[0]
    schedule = schedule_of(node, {})
    radiance = schedule.speculative_copies()["radiance"]
    dom, copies = radiance.domain, radiance.take(np.arange(len(radiance.domain)))
    assert len(dom) > len(schedule.rays)  # speculation: rays go to several domains at once
    # every copy's domain is one its ray crosses (no hit known yet: the whole ray)
    ray, crossed, _, _ = setup.geometry.crossings(schedule.rays["origin"],
                                                  schedule.rays["direction"],
                                                  schedule.rays["cand_t"])
    pairs = set(zip(schedule.rays["path"][ray].tolist(), crossed.tolist(), strict=True))
    assert set(zip(copies["path"].tolist(), dom.tolist(), strict=True)) == pairs
    assert schedule.speculative_copies()["shadow"].domain.size == 0  # none before first hits


def first_iteration(node):
    """A fresh schedule after its first local trace (only this node's own copies: no peer
    sent any), with its counters and what it hands the all-reductions."""
    stats = {"shade_s": 0.0, "speculative_rays": 0, "wasted_rays": 0,
             "intersection_cache_hits": 0}
    schedule = schedule_of(node, stats)
    copies = schedule.speculative_copies()["radiance"]
    here = np.nonzero(np.isin(copies.domain, list(node[3])))[0]
    keys, obuf = schedule.trace_locally((copies.domain[here], copies.take(here)), None)
    return schedule, stats, keys, obuf


def test_a_node_that_loses_every_hit_keeps_no_child_and_counts_them_wasted(node):
    schedule, stats, keys, obuf = first_iteration(node)
    t = (keys >> np.uint64(32)).astype(np.uint32).view(np.float32)
    assert np.isfinite(t).any() and stats["speculative_rays"] > 0
    assert obuf.shape == (len(keys), schedule.slots)
    zero = hit_keys(np.zeros(len(keys), np.float32), np.zeros(len(keys)))  # beats every hit
    schedule.resolve(zero, np.zeros_like(obuf))
    assert len(schedule.rays) == 0 and len(schedule.shadows) == 0
    assert stats["wasted_rays"] == stats["speculative_rays"]
    assert schedule.depth == 1


def test_a_node_that_wins_every_hit_it_found_keeps_their_children(node):
    schedule, stats, keys, obuf = first_iteration(node)
    schedule.resolve(keys, np.zeros_like(obuf))  # the MIN over one node: its own keys
    assert stats["wasted_rays"] == 0
    assert len(schedule.rays) > 0 and bool(schedule.rays["local_done"].all())


def test_a_copy_carries_what_its_receiver_uses_not_the_holders_candidate(node):
    from vastray.schedule.paths import RADIANCE_FIELDS
    from vastray.schedule.spec_insitu import COPY_FIELDS

    schedule = schedule_of(node, {})
    radiance = schedule.speculative_copies()["radiance"]
    rows = np.arange(len(radiance.domain))
    sent = radiance.take(rows, COPY_FIELDS["radiance"])
    whole = radiance.take(rows)
    assert "cand_t" in whole.fields and not any(f.startswith("cand_") for f in sent.fields)
    assert set(sent.fields) == set(RADIANCE_FIELDS)
    for f in sent.fields:  # the same rows of the same rays
        np.testing.assert_array_equal(sent[f], whole[f])
    assert sent.nbytes() < 0.75 * whole.nbytes()
