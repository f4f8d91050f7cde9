"""Occupancy masks (scene/occupancy.py): conservative on random and boundary-lying triangles,
rays through a domain's empty corner are not queued there, the image is the same bit for bit
with and without them (and on an old version 4 store), and ``vastray verify`` checks them."""

from __future__ import annotations

import base64
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.cli import main
from vastray.render.scene_config import SceneConfig
from vastray.render.tracer import box_pad
from vastray.scene import occupancy
from vastray.scene.bvh import DomainBVH
from vastray.scene.errors import InputError
from vastray.scene.generate import generate
from vastray.scene.occupancy import Occupancy
from vastray.scene.store import DomainArrays, Store, StoreWriter
from vastray.scene.verify import verify_store
from vastray.schedule.geometry import DomainGeometry

from scenes import settings

UNIT = (np.zeros(3), np.ones(3))


def boundary_triangles(rng, n: int, cells: int = 8) -> np.ndarray:
    """(n, 3, 3) small triangles lying in a cell boundary plane (x, y or z = k / cells), some
    with an edge along a boundary line too."""
    tris = rng.uniform(0.05, 0.95, (n, 1, 3)) + rng.uniform(-0.04, 0.04, (n, 3, 3))
    axis = rng.integers(0, 3, n)
    tris[np.arange(n), :, axis] = (rng.integers(1, cells, n) / cells)[:, None]
    other = (axis + 1) % 3  # two vertices on a boundary line of the other axis
    line = rng.integers(1, cells, n) / cells
    tris[np.arange(n), 0, other] = line
    tris[np.arange(n), 1, other] = line
    return np.clip(tris, 0.0, 1.0)


def sparse_domain(seed: int = 0) -> DomainArrays:
    """Small random triangles, boundary-lying ones, and two axis-aligned ones on the box's own
    faces, in [0, 1]^3: most cells of an 8^3 grid stay empty."""
    rng = np.random.default_rng(seed)
    random = rng.uniform(0.1, 0.9, (25, 1, 3)) + rng.uniform(-0.06, 0.06, (25, 3, 3))
    faces = np.array([[[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]],
                      [[1, 1, 1], [0.9, 1, 1], [1, 0.9, 1]]], float)
    tris = np.concatenate([random, boundary_triangles(rng, 25), faces]).astype(np.float32)
    return DomainArrays(tris.reshape(-1, 3), np.arange(len(tris) * 3, dtype=np.uint32).reshape(-1, 3))


def occupancy_of(dom: DomainArrays, dims=(8, 8, 8)) -> tuple[np.ndarray, Occupancy]:
    mask = occupancy.compute(dom.vertices, dom.indices, *UNIT, dims)
    return mask, Occupancy(UNIT[0][None], UNIT[1][None], [mask])


def rays_at(points: np.ndarray, rng, axis_aligned: bool = False):
    """Rays from random origins around the box aimed at ``points`` (t = 1 there); with
    ``axis_aligned``, each along one axis (the two others held on the point's coordinates)."""
    n = len(points)
    if axis_aligned:
        axis = rng.integers(0, 3, n)
        origins = points.copy()
        origins[np.arange(n), axis] = rng.choice([-0.5, 1.5], n)
    else:
        origins = rng.uniform(-1.0, 2.0, (n, 3))
    return origins.astype(np.float32), (points - origins).astype(np.float32)


def surface_points(dom: DomainArrays, rng, per_triangle: int = 12) -> np.ndarray:
    """Points on every triangle: inside, on its edges and at its vertices."""
    tri = dom.vertices[dom.indices].astype(np.float64)  # (T, 3, 3)
    w = rng.dirichlet(np.ones(3), (len(tri), per_triangle))
    w[:, :3] = np.eye(3)  # the vertices
    w[:, 3:6, 2] = 0  # edge points
    w[:, 3:6] /= w[:, 3:6].sum(axis=2, keepdims=True)
    return np.einsum("tkv,tvc->tkc", w, tri).reshape(-1, 3)


def crosses(occ: Occupancy, origins, directions, limit) -> np.ndarray:
    n = len(origins)
    pad = box_pad(1.0, 2.0, origins)
    return occ.crosses(origins, directions, np.arange(n), np.zeros(n, np.int64),
                       np.broadcast_to(np.float32(limit), (n,)), pad)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_masks_are_conservative_for_rays_aimed_at_triangles(seed):
    rng = np.random.default_rng(seed)
    dom = sparse_domain(seed)
    mask, occ = occupancy_of(dom)
    assert 0.02 < mask.mean() < 0.6  # mostly empty: the test can fail
    points = surface_points(dom, rng)
    for axis_aligned in (False, True):
        origins, directions = rays_at(points, rng, axis_aligned)
        for limit in (np.inf, 1.0):  # the ray ends at the point it is aimed at
            assert crosses(occ, origins, directions, limit).all(), (axis_aligned, limit)


@pytest.mark.parametrize("seed", [3, 4])
def test_masks_keep_every_pair_embree_finds_a_hit_for(seed):
    rng = np.random.default_rng(seed)
    dom = sparse_domain(seed)
    _, occ = occupancy_of(dom)
    n = 200_000
    origins = rng.uniform(-1.0, 2.0, (n, 3)).astype(np.float32)
    directions = (rng.uniform(0.0, 1.0, (n, 3)) - origins).astype(np.float32)
    # grazing rays: along an axis, in a cell boundary plane
    k = n // 4
    directions[:k] = 0
    directions[np.arange(k), rng.integers(0, 3, k)] = rng.choice([-1.0, 1.0], k)
    origins[:k, 1] = rng.integers(1, 8, k) / 8
    hits = DomainBVH(0, dom).intersect(origins, directions, np.full(n, np.inf, np.float32))
    hit = hits["primID"] >= 0
    assert hit.sum() > 500
    keep = occ.crosses(origins, directions, np.nonzero(hit)[0],
                       np.zeros(int(hit.sum()), np.int64), hits["tfar"], box_pad(1.0, 2.0, origins))
    assert keep.all()
    missed = crosses(occ, origins, directions, np.inf)
    assert not missed[~hit].all()  # and the mask drops pairs


def test_a_ray_through_an_empty_corner_is_dropped_and_one_through_a_triangle_kept():
    dom = DomainArrays(np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0.1], [1, 1, 1]], np.float32),
                       np.array([[0, 1, 2], [3, 3, 3]], np.uint32))  # + a point at (1, 1, 1)
    _, occ = occupancy_of(dom)
    origins = np.array([[-1, 0.9, 0.5], [0.05, 0.05, -1]], np.float32)
    directions = np.array([[1, 0, 0], [0, 0, 1]], np.float32)
    assert crosses(occ, origins, directions, np.inf).tolist() == [False, True]


def test_grid_sizes_stay_within_one_percent_of_a_domain():
    lo, hi = np.zeros(3), np.array([4.0, 2.0, 0.0])
    assert occupancy.grid_dims(lo, hi, 10**6) == (16, 8, 1)
    assert occupancy.grid_dims(lo, hi, 1000) == (8, 4, 1)  # 4 bytes <= 10
    assert occupancy.grid_dims(lo, hi, 100) == (4, 2, 1)
    assert occupancy.grid_dims(lo, hi, 40) == (1, 1, 1)
    assert occupancy.grid_dims(lo, lo, 10**6) == (1, 1, 1)
    for nbytes in (500, 5_000, 51_200, 10**7):
        dims = occupancy.grid_dims(np.zeros(3), np.ones(3), nbytes)
        assert (np.prod(dims) + 7) // 8 <= max(0.01 * nbytes, 1)


def test_encoding_round_trips_and_refuses_damage():
    bits = np.random.default_rng(0).random((5, 3, 7)) < 0.3
    value = occupancy.encode(bits)
    assert np.array_equal(occupancy.decode(json.loads(json.dumps(value))), bits)
    for bad in ({"grid": [5, 3], "bits": value["bits"]},
                {"grid": [5, 3, 7], "bits": "not base64!"},
                {"grid": [5, 3, 8], "bits": value["bits"] + "AA=="},
                {"grid": [0, 3, 7], "bits": ""},
                {"grid": [5, 3, 7], "bits": base64.b64encode(b"\xff" * 14).decode()}):
        with pytest.raises(ValueError):
            occupancy.decode(bad)


# --- stores ------------------------------------------------------------------------------------


def corner_store(path: Path) -> Store:
    """Domain 0: 500 small triangles in the low corner of [0, 1]^3 and one in the high corner;
    domain 1: a wall at x = 2."""
    rng = np.random.default_rng(0)
    tris = np.concatenate([rng.uniform(0, 0.2, (500, 3, 3)),
                           1.0 - rng.uniform(0, 0.05, (1, 3, 3))])
    tris[-1, 0] = 1.0
    tris[0, 0] = 0.0
    a = DomainArrays(tris.reshape(-1, 3).astype(np.float32),
                     np.arange(3 * len(tris), dtype=np.uint32).reshape(-1, 3))
    b = DomainArrays(np.array([[2, 0, 0], [2, 1, 0], [2, 0, 1], [2, 1, 1]], np.float32),
                     np.array([[0, 1, 2], [1, 3, 2]], np.uint32))
    with StoreWriter(path) as writer:
        writer.add_domain(a)
        writer.add_domain(b)
    return Store(path)


def geometry_of(store: Store, masks: bool = True) -> DomainGeometry:
    lo, hi = store.domain_boxes()
    return DomainGeometry(lo, hi, np.ones(len(lo), bool), 4.0,
                          store.occupancy() if masks else None)


def test_a_ray_through_an_empty_corner_is_not_queued(tmp_path, monkeypatch):
    store = corner_store(tmp_path / "s")
    assert store.manifest["version"] == 5 and store.domains[0].occupancy.shape == (8, 8, 8)
    origins = np.array([[-1, 0.9, 0.5], [-1, 0.1, 0.1]], np.float32)  # corner, triangles
    directions = np.array([[1, 0, 0], [1, 0, 0]], np.float32)
    limit = np.full(2, np.inf, np.float32)
    start = np.full(2, -np.inf, np.float32), np.full(2, -1)
    ray, dom, entry, rank = geometry_of(store).crossings(origins, directions, limit)
    assert list(zip(ray.tolist(), dom.tolist(), rank.tolist(), strict=True)) == [
        (0, 1, 0), (1, 0, 0), (1, 1, 1)]
    _, _, box_entry, _ = geometry_of(store, False).crossings(origins, directions, limit)
    assert entry.tolist() == box_entry[1:].tolist()  # the boxes' entries, as without masks
    assert geometry_of(store).next_domain(origins, directions, *start, limit)[0].tolist() == [1, 0]
    assert geometry_of(store, False).next_domain(origins, directions, *start,
                                                 limit)[0].tolist() == [0, 0]
    monkeypatch.setenv(occupancy.ENV, "0")
    assert store.occupancy() is None


def walk(geometry: DomainGeometry, origins, directions, limit) -> list[list[int]]:
    """Each ray's domains, by ``next_domain`` from the start until none is left."""
    n = len(origins)
    at_t, at_d = np.full(n, -np.inf, np.float32), np.full(n, -1, np.int64)
    seen = [[] for _ in range(n)]
    while (at_d >= -1).any():
        live = np.nonzero(at_d >= -1)[0]
        d, e = geometry.next_domain(origins[live], directions[live], at_t[live], at_d[live],
                                    limit[live])
        for r, x in zip(live, d, strict=True):
            if x >= 0:
                seen[r].append(int(x))
        at_t[live], at_d[live] = e, np.where(d >= 0, d, -2)
    return seen


def rm_and_rays(tmp_path, n: int, seed: int):
    """An rm store in 3x3x2 domains and ``n`` random rays through it: (store, (n, 3) origins,
    (n, 3) directions, (n,) limits, half of them infinite), all float32."""
    generate("rm", tmp_path / "rm", 24, grid=(3, 3, 2), seed=0)
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-0.5, 1.5, (n, 3)).astype(np.float32)
    directions = (rng.uniform(0, 1, (n, 3)) - origins).astype(np.float32)
    limit = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0.2, 1.5, n)).astype(np.float32)
    return Store(tmp_path / "rm"), origins, directions, limit


def test_next_domain_walks_the_domains_crossings_lists(tmp_path):
    n = 3000
    store, origins, directions, limit = rm_and_rays(tmp_path, n, seed=1)
    geometry = geometry_of(store)
    ray, dom, _, rank = geometry.crossings(origins, directions, limit)
    listed = [[] for _ in range(n)]
    for r, d in zip(ray, dom, strict=True):
        listed[r].append(int(d))
    assert walk(geometry, origins, directions, limit) == listed
    assert rank.tolist() == [i for lst in listed for i in range(len(lst))]
    unmasked = geometry_of(store, masks=False).crossings(origins, directions, limit)[0]
    assert len(ray) < 0.9 * len(unmasked)


def test_crossings_among_some_domains_are_the_pairs_of_those_domains(tmp_path):
    n = 2000
    store, origins, directions, limit = rm_and_rays(tmp_path, n, seed=2)
    geometry = geometry_of(store)
    ray, dom, entry, _ = geometry.crossings(origins, directions, limit)
    among = np.zeros(18, bool)
    among[[0, 4, 5, 11, 17]] = True
    got = geometry.crossings(origins, directions, limit, among=among)
    asked = among[dom]
    assert asked.any() and not asked.all()
    for expected, value in zip((ray[asked], dom[asked], entry[asked]), got[:3], strict=True):
        assert value.tolist() == expected.tolist()
    per_ray = np.bincount(got[0], minlength=n)
    assert got[3].tolist() == [i for count in per_ray for i in range(count)]


# --- stores on disk: versions and verify -------------------------------------------------------


def downgrade_to_version_4(store: Path) -> None:
    manifest = json.loads((store / "manifest.json").read_text())
    manifest["version"] = 4
    for entry in manifest["domains"]:
        del entry["occupancy"]
    (store / "manifest.json").write_text(json.dumps(manifest))


def edit_mask(store: Path, domain: int, change) -> None:
    manifest = json.loads((store / "manifest.json").read_text())
    entry = manifest["domains"][domain]
    bits = occupancy.decode(entry["occupancy"])
    entry["occupancy"] = occupancy.encode(change(bits.copy()))
    (store / "manifest.json").write_text(json.dumps(manifest))


@pytest.fixture(scope="module")
def rm_store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("occ") / "rm"
    generate("rm", path, 40, grid=(3, 3, 3), seed=0)
    return path


def render(store: Store, scheduler: str, cache: int):
    st = settings(width=32, height=24, spp=2, integrator="pt", bounces=3)
    return render_out_of_core(store, SceneConfig(), st,
                              options=JobOptions(scheduler=scheduler, cache=cache),
                              progress=False)


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_masks_keep_the_image_and_queue_fewer_rays(rm_store, scheduler, monkeypatch):
    store = Store(rm_store)
    cache = max(1, len(store.domains) // 4)
    masked = render(store, scheduler, cache)
    monkeypatch.setenv(occupancy.ENV, "0")
    plain = render(store, scheduler, cache)
    assert np.array_equal(masked.film.image(), plain.film.image())
    assert masked.film.depth.tolist() == plain.film.depth.tolist()
    queued = {name: r.counters["radiance_tests"] + r.counters["shadow_tests"]
              for name, r in (("masked", masked), ("plain", plain))}
    assert queued["masked"] < queued["plain"], queued
    assert masked.counters["loads"] <= plain.counters["loads"]


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_a_cache_of_every_domain_renders_without_consulting_the_masks(rm_store, scheduler,
                                                                      monkeypatch):
    # every domain resident: the masks can save no load, only cost their test
    store = Store(rm_store)
    tests = []
    real = occupancy.Occupancy.crosses

    def counted(self, *args, **kwargs):
        tests.append(1)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(occupancy.Occupancy, "crosses", counted)
    whole = render(store, scheduler, len(store.domains))
    assert tests == []
    quarter = render(store, scheduler, max(1, len(store.domains) // 4))
    assert tests  # out of core the masks are asked
    assert np.array_equal(whole.film.image(), quarter.film.image())
    assert whole.counters["loads"] <= len(store.domains)


def test_a_version_4_store_opens_and_renders_the_same_image(rm_store, tmp_path):
    old = copy_store(rm_store, tmp_path / "v4")
    downgrade_to_version_4(old)
    store = Store(old)
    assert store.manifest["version"] == 4
    assert all(d.occupancy is None for d in store.domains) and store.occupancy() is None
    assert verify_store(old).ok
    for scheduler in ("image", "spec-ooc"):
        assert np.array_equal(render(store, scheduler, 7).film.image(),
                              render(Store(rm_store), scheduler, 7).film.image()), scheduler


def copy_store(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_verify_catches_a_mask_that_drops_occupied_cells(rm_store, tmp_path, capsys):
    store = copy_store(rm_store, tmp_path / "s")
    assert verify_store(store).ok

    def clear_one(bits):
        bits.flat[np.flatnonzero(bits)[0]] = False
        return bits

    edit_mask(store, 2, clear_one)
    problems = verify_store(store).problems
    assert len(problems) == 1
    assert problems[0].path == str(store / "manifest.json")
    assert "domain 2 occupancy mask is not conservative: 1 of its" in str(problems[0])
    capsys.readouterr()
    assert main(["verify", str(store)]) == 2
    assert "domain 2 occupancy mask is not conservative" in capsys.readouterr().out


def test_verify_catches_a_mask_that_marks_empty_cells(rm_store, tmp_path):
    store = copy_store(rm_store, tmp_path / "s")

    def set_empty(bits):
        empty = np.flatnonzero(~bits)
        bits.flat[empty[:3]] = True
        return bits

    edit_mask(store, 4, set_empty)
    problems = verify_store(store).problems
    assert len(problems) == 1
    assert "domain 4 occupancy mask does not match its triangles: 3 of its" in str(problems[0])


def test_a_malformed_mask_is_refused_on_opening(rm_store, tmp_path):
    store = copy_store(rm_store, tmp_path / "s")
    manifest = json.loads((store / "manifest.json").read_text())
    manifest["domains"][1]["occupancy"]["bits"] = "AAAA"
    (store / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="domain 1 'occupancy' 'bits' holds 3 bytes"):
        Store(store)
    del manifest["domains"][1]["occupancy"]
    (store / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="domain 1 'occupancy' must be"):
        Store(store)
    assert not verify_store(store).ok


def test_a_query_split_over_threads_answers_as_one_thread(monkeypatch):
    from vastray.scene import cpus

    rng = np.random.default_rng(5)
    _, occ = occupancy_of(sparse_domain(5))
    n = 5 * occupancy._SPLIT_MIN_PAIRS + 17  # several pieces, uneven
    origins = rng.uniform(-1.0, 2.0, (n, 3)).astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    monkeypatch.setattr(cpus, "available_cpus", lambda: 4)
    split = crosses(occ, origins, directions, 3.0)
    monkeypatch.setattr(cpus, "available_cpus", lambda: 1)
    whole = crosses(occ, origins, directions, 3.0)
    assert 0.05 < whole.mean() < 0.95  # both answers occur: the comparison can fail
    assert np.array_equal(split, whole)


def test_dilated_marks_the_cells_next_to_an_occupied_one():
    rng = np.random.default_rng(6)
    mask = rng.random((5, 4, 3)) < 0.08
    expected = np.zeros_like(mask)
    for i, j, k in np.argwhere(mask):
        expected[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2, max(k - 1, 0):k + 2] = True
    assert mask.any() and not expected.all()
    assert np.array_equal(occupancy.dilated(mask), expected)


@pytest.mark.parametrize("seed", [7, 8])
def test_skipping_cells_with_no_occupied_neighbour_changes_no_answer(seed):
    """The query passes over a cell none of whose 27 (itself and around) is occupied without
    testing its piece: every answer is the full test's, grazing rays and rays aimed at
    triangles on cell boundaries included."""
    rng = np.random.default_rng(seed)
    dom = sparse_domain(seed)
    _, occ = occupancy_of(dom, (16, 16, 16))
    assert 0.05 < occ.near.mean() < 0.95  # cells are skipped, and some are not
    points = surface_points(dom, rng)
    aimed = [rays_at(points, rng, axis_aligned) for axis_aligned in (False, True)]
    n = 100_000
    origins = rng.uniform(-1.0, 2.0, (n, 3)).astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    k = n // 4  # grazing: along an axis, in a cell boundary plane
    directions[:k] = 0
    directions[np.arange(k), rng.integers(0, 3, k)] = rng.choice([-1.0, 1.0], k)
    origins[:k, 2] = rng.integers(1, 8, k) / 8
    odd_o, odd_d = origins.copy(), directions.copy()  # degenerate rays, kept or dropped alike
    pick = rng.random((n, 3))
    odd_o[pick < 0.02] = np.nan
    odd_d[(pick > 0.02) & (pick < 0.04)] = np.inf
    odd_d[(pick > 0.04) & (pick < 0.3)] = 0.0  # some directions entirely zero
    for o, d in [*aimed, (origins, directions), (odd_o, odd_d)]:
        for limit in (np.inf, 1.0, np.nan):
            skipping = crosses(occ, o, d, limit)
            _, occ_full = occupancy_of(dom, (16, 16, 16))
            occ_full.min_cell[:] = 0.0  # every piece tested
            assert np.array_equal(skipping, crosses(occ_full, o, d, limit))
    assert 0.05 < crosses(occ, origins, directions, 1.0).mean() < 0.95
