"""The simplified whole-scene model (paper §6.1, §7.3.2; notes §6, acceptance A15): building it,
storing it in the manifest like a domain, checking it, and the commands that make it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vastray.cli import main
from vastray.scene import store as store_module
from vastray.scene.errors import InputError
from vastray.scene.simplify import simplify_domains, simplify_piece
from vastray.scene.store import DomainArrays, Store, StoreWriter, write_simplified
from vastray.scene.verify import verify_store

from scenes import write_store


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> dict[str, Path]:
    """Generated test scenes (``vastray generate``), written once; tests copy them."""
    root = tmp_path_factory.mktemp("generated")
    paths = {}
    for scene in ("rm", "cosmo"):
        paths[scene] = root / f"{scene}.store"
        assert main(["generate", scene, "-o", str(paths[scene]), "--resolution", "64",
                     "--grid", "2x2x2", "--quiet"]) == 0
    return paths


@pytest.fixture
def rm_store(generated, tmp_path) -> Path:
    path = tmp_path / "rm.store"
    shutil.copytree(generated["rm"], path)
    return path


def bumpy_sphere(subdivisions=4, centre=(0.0, 0.0, 0.0), radius=1.0) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    bump = 1.0 + 0.15 * np.sin(4 * sphere.vertices[:, 0]) * np.cos(5 * sphere.vertices[:, 1])
    sphere.vertices *= bump[:, None]
    sphere.apply_translation(centre)
    return sphere


def two_object_store(path: Path, grid=(1, 1, 1)) -> Store:
    """A big bumpy sphere (object 0, 5,120 triangles) and a small box (object 1, 12), with
    per-vertex scalars (= z) and colours (= position mapped into [0, 1])."""
    big = bumpy_sphere()
    small = trimesh.creation.box(extents=[0.4, 0.4, 0.4])
    small.apply_translation([3.0, 0.0, 0.0])
    vertices = np.concatenate([big.vertices, small.vertices]).astype(np.float32)
    indices = np.concatenate([big.faces, small.faces + len(big.vertices)]).astype(np.uint32)
    objects = np.repeat(np.array([0, 1], np.uint16), [len(big.faces), len(small.faces)])
    colors = ((vertices - vertices.min(0)) / np.ptp(vertices, axis=0)).astype(np.float32)
    mesh = DomainArrays(vertices, indices, objects, vertices[:, 2].copy(), colors)
    from vastray.scene.partition import partition_grid

    with StoreWriter(path, objects=[{"name": "ball"}, {"name": "box"}]) as writer:
        for dom in partition_grid(mesh, grid).domains:
            writer.add_domain(dom)
    return Store(path)


# --- A15: rates and bounds --------------------------------------------------------------------


@pytest.mark.parametrize("scene, ratio", [("rm", 0.1), ("rm", 0.02), ("cosmo", 0.1),
                                          ("cosmo", 0.05)])
def test_a15_rates_within_10_percent_and_inside_the_scene(generated, tmp_path, scene, ratio,
                                                          capsys):
    path = tmp_path / "s.store"
    shutil.copytree(generated[scene], path)
    capsys.readouterr()
    assert main(["simplify", str(path), "--ratio", str(ratio)]) == 0  # as a user runs it
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"{path}: simplified model of ") and "triangle rate" in line
    assert "memory rate" in line and "built in" in line
    store = Store(path)
    info = store.simplified
    assert info is not None and info.ratio == ratio
    assert abs(info.rate - ratio) <= 0.1 * ratio, info.rate
    assert abs(info.memory_rate - ratio) <= 0.1 * ratio, info.memory_rate
    model = store.load_simplified()
    assert info.rate == pytest.approx(model.n_triangles / store.n_triangles)
    assert info.memory_rate == pytest.approx(model.nbytes() / sum(d.nbytes for d in store.domains))
    eps = 1e-6
    box = model.bounds()
    assert (box[0] >= store.bounds[0] - eps).all() and (box[1] <= store.bounds[1] + eps).all()
    # and inside the union of the domain boxes it came from (each piece is clamped to its own)
    lo, hi = store.domain_boxes()
    v = np.asarray(model.vertices, np.float64)[np.unique(model.indices)]
    inside_some = ((v[:, None] >= lo[None] - eps) & (v[:, None] <= hi[None] + eps)).all(2).any(1)
    assert inside_some.all()
    assert verify_store(path).ok


def test_ratio_one_is_the_scene_itself(rm_store):
    store = Store(rm_store)
    model = simplify_domains(store, 1.0)
    assert model.n_triangles == store.n_triangles

    def triangles(dom):
        return np.sort(np.asarray(dom.vertices)[np.asarray(dom.indices)].reshape(-1, 9), axis=0)

    whole = np.concatenate([triangles(store.load_domain(d.id)) for d in store.domains])
    np.testing.assert_array_equal(np.sort(whole, axis=0), triangles(model))


def test_generate_and_partition_build_it_in_one_go(tmp_path, capsys):
    out = tmp_path / "rm.store"
    assert main(["generate", "rm", "-o", str(out), "--resolution", "32", "--simplify",
                 "0.25"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith(f"{out}: simplified model of ")
    assert Store(out).simplified.ratio == 0.25


# --- pieces, small objects, attributes ----------------------------------------------------------


def test_min_faces_keeps_small_objects_whole(tmp_path):
    store = two_object_store(tmp_path / "two.store")
    model = simplify_domains(store, 0.1, min_faces=100)
    objects = np.asarray(model.objects)
    assert np.count_nonzero(objects == 1) == 12  # the box: kept whole
    assert abs(np.count_nonzero(objects == 0) - 512) <= 2  # the sphere: 10 %
    box_tris = np.asarray(model.vertices)[np.asarray(model.indices)[objects == 1]]
    dom = store.load_domain(0)
    original = np.asarray(dom.vertices)[np.asarray(dom.indices)[np.asarray(dom.objects) == 1]]
    np.testing.assert_array_equal(np.sort(box_tris.reshape(-1, 9), 0),
                                  np.sort(original.reshape(-1, 9), 0))
    # a floor above every piece keeps the whole scene
    assert simplify_domains(store, 0.1, min_faces=10**6).n_triangles == store.n_triangles


def test_pieces_are_per_domain_and_per_object(tmp_path):
    store = two_object_store(tmp_path / "grid.store", grid=(2, 2, 1))
    model = simplify_domains(store, 0.2, min_faces=50)
    objects = np.asarray(model.objects)
    assert set(np.unique(objects)) == {0, 1}
    # every slot-0 triangle lies on the sphere, every slot-1 triangle on the box
    centroids = np.asarray(model.vertices)[np.asarray(model.indices)].mean(axis=1)
    assert (np.abs(centroids[objects == 1, 0] - 3.0) <= 0.2 + 1e-6).all()
    assert (np.linalg.norm(centroids[objects == 0], axis=1) < 1.3).all()
    expected = 0
    for d in store.domains:
        slot = np.asarray(store.load_domain(d.id).objects)
        for s in np.unique(slot):
            n = int(np.count_nonzero(slot == s))
            expected += n if n < 50 else int((1 - (1 - 0.2)) * n)
    assert abs(model.n_triangles - expected) <= 2 * len(store.domains)


def test_attributes_come_from_the_nearest_merged_vertex(tmp_path):
    store = two_object_store(tmp_path / "attr.store")
    model = simplify_domains(store, 0.1, min_faces=100)
    dom = store.load_domain(0)
    v = np.asarray(model.vertices, np.float64)
    edge = np.linalg.norm(np.diff(np.asarray(dom.vertices)[np.asarray(dom.indices)], axis=1),
                          axis=2).mean()
    # scalars are z and colours are positions of input vertices: within a collapse cluster
    np.testing.assert_array_less(np.abs(np.asarray(model.scalars) - v[:, 2]), 1.5 * edge)
    scale = np.ptp(np.asarray(dom.vertices), axis=0)
    position = np.asarray(model.colors) * scale + np.asarray(dom.vertices).min(0)
    np.testing.assert_array_less(np.linalg.norm(position - v, axis=1), 1.5 * edge)
    # every value is exactly one input vertex's (no interpolation), of the same object
    pairs = {(float(s), *map(float, c)) for s, c in zip(dom.scalars, dom.colors, strict=True)}
    assert all((float(s), *map(float, c)) in pairs
               for s, c in zip(model.scalars, model.colors, strict=True))
    assert model.scalars.dtype == np.float32 and model.colors.dtype == np.float32
    assert model.objects.dtype == np.uint16


def test_source_vertex_is_nearly_always_the_global_nearest():
    sphere = bumpy_sphere(subdivisions=3)
    vertices = sphere.vertices.astype(np.float32)
    for ratio in (0.5, 0.1):
        piece = simplify_piece(vertices, sphere.faces, ratio, min_faces=10)
        dist = np.linalg.norm(piece.vertices[:, None].astype(np.float64) - vertices[None], axis=2)
        agree = np.mean(dist.argmin(axis=1) == piece.source)
        assert agree > 0.9, agree
        assert len(piece.source) == len(piece.vertices)
        assert piece.indices.max() < len(piece.vertices)


def test_bad_ratio_is_refused(rm_store, capsys):
    for bad in ("0", "1.5", "-0.1", "nan", "x"):
        with pytest.raises(SystemExit) as exit_:
            main(["simplify", str(rm_store), "--ratio", bad])
        assert exit_.value.code == 2
        assert "(0, 1]" in capsys.readouterr().err
    with pytest.raises(InputError, match=r"\(0, 1\]"):
        simplify_domains(Store(rm_store), 0.0)


# --- the store entry, the commands ----------------------------------------------------------------


@pytest.fixture
def mesh_file(tmp_path) -> Path:
    path = tmp_path / "ball.ply"
    bumpy_sphere(subdivisions=5).export(path)  # 20,480 triangles
    return path


def test_partition_simplify_info_verify_and_a_corrupted_file(mesh_file, tmp_path, capsys):
    out = tmp_path / "ball.store"
    assert main(["partition", str(mesh_file), "-o", str(out), "--grid", "2x2x1",
                 "--simplify", "0.2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith(f"{out}: 20,480 triangles")
    assert lines[1].startswith(f"{out}: simplified model of ") and "triangle rate" in lines[1]
    store = Store(out)
    assert abs(store.simplified.rate - 0.2) <= 0.02
    assert sorted(p.name for p in (out / "simplified").iterdir()) == ["indices.npy",
                                                                      "vertices.npy"]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left

    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert f"simplified: {store.simplified.n_triangles:,} triangles" in info
    assert "triangle rate" in info and "memory rate" in info

    assert main(["verify", str(out)]) == 0
    summary = capsys.readouterr().out.strip()
    assert "OK" in summary and f"a simplified model of {store.simplified.n_triangles:,}" in summary

    victim = out / "simplified" / "vertices.npy"
    data = bytearray(victim.read_bytes())
    data[-5] ^= 0x40
    victim.write_bytes(bytes(data))
    assert main(["verify", str(out)]) == 2
    captured = capsys.readouterr()
    lines = (captured.out + captured.err).strip().splitlines()
    assert any(line.startswith(f"{victim}: checksum mismatch") for line in lines), lines


def test_simplify_refuses_to_replace_without_force(rm_store, capsys):
    assert main(["simplify", str(rm_store), "--ratio", "0.1", "--quiet"]) == 0
    first = json.loads((rm_store / "manifest.json").read_text())["simplified"]
    capsys.readouterr()
    assert main(["simplify", str(rm_store), "--ratio", "0.05"]) == 2
    err = capsys.readouterr().err
    assert "already has a simplified model" in err and "--force" in err
    assert json.loads((rm_store / "manifest.json").read_text())["simplified"] == first
    assert main(["simplify", str(rm_store), "--ratio", "0.05", "--force", "--quiet"]) == 0
    store = Store(rm_store)
    assert store.simplified.ratio == 0.05 and store.simplified.n_triangles < first["triangles"]
    assert verify_store(rm_store).ok
    assert not [p for p in rm_store.iterdir() if p.name.startswith(".")]


def test_a_failed_write_leaves_the_store_as_it_was(rm_store, monkeypatch):
    assert main(["simplify", str(rm_store), "--ratio", "0.1", "--quiet"]) == 0
    before = (rm_store / "manifest.json").read_bytes()
    files = {p.name: p.read_bytes() for p in (rm_store / "simplified").iterdir()}
    calls = []

    def failing(path, arr):
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        return original(path, arr)

    original = store_module._save_hashed
    monkeypatch.setattr(store_module, "_save_hashed", failing)
    store = Store(rm_store)
    with pytest.raises(OSError, match="disk full"):
        write_simplified(store, simplify_domains(store, 0.05), 0.05, force=True)
    assert (rm_store / "manifest.json").read_bytes() == before
    assert {p.name: p.read_bytes() for p in (rm_store / "simplified").iterdir()} == files
    assert not [p for p in rm_store.iterdir() if p.name.startswith(".")]
    assert verify_store(rm_store).ok


def test_a_store_without_the_entry_still_opens(generated, tmp_path, capsys):
    store = Store(generated["rm"])
    assert store.simplified is None
    with pytest.raises(InputError, match="no simplified model"):
        store.load_simplified()
    assert main(["info", str(generated["rm"])]) == 0
    assert "simplified" not in capsys.readouterr().out
    old = write_store(tmp_path / "old.store", DomainArrays(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]], np.uint32)))
    assert old.simplified is None and verify_store(old.path).ok


# --- hostile entries: refused like a domain's, with the file named -------------------------------


def _edit(path: Path, change) -> None:
    manifest = json.loads((path / "manifest.json").read_text())
    change(manifest["simplified"])
    (path / "manifest.json").write_text(json.dumps(manifest))


def _escape(path: Path) -> None:
    outside = path.parent / "outside"
    outside.mkdir()
    shutil.copy(path / "simplified" / "vertices.npy", outside / "vertices.npy")
    _edit(path, lambda e: e["files"].__setitem__("vertices", "../outside/vertices.npy"))


def _count_mismatch(path: Path) -> None:
    _edit(path, lambda e: e.__setitem__("triangles", e["triangles"] + 1))


def _ratio_zero(path: Path) -> None:
    _edit(path, lambda e: e.__setitem__("ratio", 0))


def _no_checksum(path: Path) -> None:
    _edit(path, lambda e: e.pop("sha256"))


def _sticks_out(path: Path) -> None:
    _edit(path, lambda e: e["bounds"][1].__setitem__(0, 50.0))


def _lacks_scalars(path: Path) -> None:
    def change(e):
        e["files"].pop("scalars")
        e["sha256"].pop("scalars")
    _edit(path, change)


def _not_an_object(path: Path) -> None:
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["simplified"] = [1, 2]
    (path / "manifest.json").write_text(json.dumps(manifest))


def _bytes_mismatch(path: Path) -> None:
    _edit(path, lambda e: e.__setitem__("bytes", e["bytes"] + 4))


HOSTILE = {  # case -> (damage, file named (relative to the store), pattern)
    "escape": (_escape, "manifest.json", r"climbs out with '\.\.'"),
    "count_mismatch": (_count_mismatch, "simplified/indices.npy", "does not match the manifest"),
    "ratio_zero": (_ratio_zero, "manifest.json", r"'ratio' must be a number in \(0, 1\]"),
    "no_checksum": (_no_checksum, "manifest.json", "'sha256' must give a checksum"),
    "sticks_out": (_sticks_out, "manifest.json", "stick out of the scene"),
    "lacks_scalars": (_lacks_scalars, "manifest.json", "has no scalars file"),
    "not_an_object": (_not_an_object, "manifest.json", "'simplified' must be an object"),
    "bytes_mismatch": (_bytes_mismatch, "manifest.json", "simplified model 'bytes' says"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_a_damaged_entry_is_refused_naming_the_file(rm_store, capsys, case):
    assert main(["simplify", str(rm_store), "--ratio", "0.1", "--quiet"]) == 0
    damage, culprit, pattern = HOSTILE[case]
    damage(rm_store)
    with pytest.raises(InputError, match=pattern) as err:
        Store(rm_store)
    assert err.value.path == str(rm_store / culprit)
    capsys.readouterr()
    assert main(["verify", str(rm_store)]) == 2
    captured = capsys.readouterr()
    lines = (captured.out + captured.err).strip().splitlines()
    assert any(line.startswith(f"{rm_store / culprit}: ") for line in lines), lines


def test_help_has_an_example(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["simplify", "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "vastray simplify " in out and "example" in out and "--min-faces" in out
