"""The domain store: round trip, atomic writes, and damaged stores rejected with the file named."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vastray.scene.errors import InputError
from vastray.scene.store import DomainArrays, Store, StoreWriter


def _domain(rng, n_vert=30, n_tri=40, offset=0.0) -> DomainArrays:
    return DomainArrays(
        vertices=(rng.random((n_vert, 3)) + offset).astype(np.float32),
        indices=rng.integers(0, n_vert, (n_tri, 3)).astype(np.uint32),
        objects=rng.integers(0, 2, n_tri).astype(np.uint16),
        scalars=rng.random(n_vert).astype(np.float32),
        colors=rng.random((n_vert, 3)).astype(np.float32),
    )


@pytest.fixture
def two_domain_store(tmp_path):
    rng = np.random.default_rng(1)
    doms = [_domain(rng), _domain(rng, 50, 70, offset=2.0)]
    path = tmp_path / "s.store"
    with StoreWriter(path, objects=[{"name": "a"}, {"name": "b"}]) as writer:
        for d in doms:
            writer.add_domain(d)
    return path, doms


@pytest.mark.parametrize("mmap", [True, False])
def test_round_trip(two_domain_store, mmap):
    path, doms = two_domain_store
    store = Store(path)
    assert [d.id for d in store.domains] == [0, 1]
    assert store.n_triangles == 110
    assert [o["name"] for o in store.objects] == ["a", "b"]
    assert store.has_scalars and store.has_colors
    for i, dom in enumerate(doms):
        back = store.load_domain(i, mmap=mmap)
        for name in ("vertices", "indices", "objects", "scalars", "colors"):
            np.testing.assert_array_equal(getattr(back, name), getattr(dom, name))
        np.testing.assert_allclose(store.domains[i].lo, dom.bounds()[0])
        np.testing.assert_allclose(store.domains[i].hi, dom.bounds()[1])
    lo, hi = store.domain_boxes()
    np.testing.assert_allclose(store.bounds, [lo.min(axis=0), hi.max(axis=0)])
    lo_s = min(float(d.scalars.min()) for d in doms)
    assert store.scalar_range[0] == pytest.approx(lo_s)


def test_a_load_reads_only_the_attributes_the_render_shades_with(two_domain_store):
    # a store with per-vertex colours and scalars, rendered (colours win) without materials:
    # the scalars and object ids are never read, so their bytes are neither read nor counted
    from vastray.scene.cache import DomainCache

    path, doms = two_domain_store
    store = Store(path)
    info = store.domains[1]
    (path / info.files["scalars"]).unlink()  # gone: a load that opened it would fail
    (path / info.files["objects"]).write_bytes(b"not an array")
    back = store.load_domain(1, attributes={"colors"})
    np.testing.assert_array_equal(back.colors, doms[1].colors)
    assert back.scalars is None and back.objects is None
    with pytest.raises(InputError, match=r"(objects|scalars)\.npy"):
        store.load_domain(1)  # every file: a damaged one is named
    cache = DomainCache(store, 1, keep=frozenset({"colors"}))
    cache.load(1).close()
    read = info.read_bytes({"colors"})
    assert cache.stats.bytes_loaded == read == info.nbytes - 50 * 4 - 70 * 2
    assert info.read_bytes() == info.nbytes


def test_failed_write_leaves_nothing(tmp_path):
    path = tmp_path / "broken.store"
    with pytest.raises(RuntimeError):
        with StoreWriter(path) as writer:
            writer.add_domain(_domain(np.random.default_rng(0)))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_failed_overwrite_keeps_old_store(two_domain_store):
    path, _ = two_domain_store
    with pytest.raises(RuntimeError):
        with StoreWriter(path, overwrite=True):
            raise RuntimeError("boom")
    assert Store(path).n_triangles == 110
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


def test_existing_store_needs_overwrite(two_domain_store):
    path, _ = two_domain_store
    with pytest.raises(InputError, match="--force"):
        with StoreWriter(path, overwrite=False):
            pass


@pytest.mark.parametrize("mmap", [True, False])
def test_truncated_domain_file(two_domain_store, mmap):
    path, _ = two_domain_store
    target = path / "domains" / "00001" / "vertices.npy"
    data = target.read_bytes()
    target.write_bytes(data[: len(data) // 2])
    store = Store(path)
    store.load_domain(0)  # the intact domain still loads
    with pytest.raises(InputError) as err:
        store.load_domain(1, mmap=mmap)
    assert str(target) in str(err.value)


def test_manifest_not_matching_files(two_domain_store):
    path, _ = two_domain_store
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["domains"][0]["vertices"] += 1
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="does not match the manifest") as err:
        Store(path).load_domain(0)
    assert "00000" in str(err.value)


def test_missing_domain_file_and_bad_manifest(two_domain_store):
    path, _ = two_domain_store
    (path / "domains" / "00000" / "indices.npy").unlink()
    with pytest.raises(InputError, match="indices.npy"):
        Store(path).load_domain(0)
    (path / "manifest.json").write_text("{not json")
    with pytest.raises(InputError, match="manifest.json"):
        Store(path)
    with pytest.raises(InputError, match="no such store"):
        Store(path.parent / "nothing.store")
