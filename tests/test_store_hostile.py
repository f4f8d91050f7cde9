"""Stores that cannot lie: hand-edited manifests and files are refused with the file named.

Each hostile case damages a copy of a sound two-domain store. Opening or loading it raises an
``InputError`` naming the file to fix; ``vastray render`` exits 2 with one line and writes no
image; ``vastray verify`` exits 2 naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.cli import main
from vastray.scene.errors import InputError
from vastray.scene.manifest import MAX_DOMAINS, MAX_MANIFEST_BYTES
from vastray.scene.store import DomainArrays, Store, StoreWriter, check_replaceable, is_store
from vastray.scene.verify import verify_store

from scenes import bumpy_scene, write_store

SMALL = ["--width", "32", "--height", "24", "--spp", "1", "--shadow-samples", "1", "--quiet"]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    """A sound store of two non-empty domains (written once, copied by each test)."""
    path = tmp_path_factory.mktemp("pristine") / "s.store"
    store = write_store(path, bumpy_scene(), grid=(2, 1, 1))
    assert len(store.domains) == 2 and all(d.n_triangles for d in store.domains)
    return path


@pytest.fixture
def store(pristine, tmp_path) -> Path:
    path = tmp_path / "s.store"
    shutil.copytree(pristine, path)
    (tmp_path / "outside").mkdir()
    return path


# --- how each case damages a store ------------------------------------------------------------


def edit(store: Path, change) -> None:
    """Apply ``change(manifest)`` to the store's manifest.json."""
    manifest = json.loads((store / "manifest.json").read_text())
    change(manifest)
    (store / "manifest.json").write_text(json.dumps(manifest))


def domain(store: Path, i: int = 0) -> Path:
    return store / "domains" / f"{i:05d}"


def copy_outside(store: Path, kind: str = "vertices") -> Path:
    """A valid copy of domain 0's ``kind`` file beside the store (what an escape would load)."""
    target = store.parent / "outside" / f"{kind}.npy"
    shutil.copy(domain(store) / f"{kind}.npy", target)
    return target


def set_file(store: Path, kind: str, rel: str) -> None:
    edit(store, lambda m: m["domains"][0]["files"].__setitem__(kind, rel))


def set_field(store: Path, key: str, value, i: int = 0) -> None:
    edit(store, lambda m: m["domains"][i].__setitem__(key, value))


def rewrite_array(store: Path, kind: str, change) -> None:
    """Replace domain 0's ``kind`` file by ``change(array)`` (a valid .npy, new data)."""
    path = domain(store) / f"{kind}.npy"
    arr = np.load(path)
    path.unlink()
    np.save(path, change(arr))


def absolute_path(store):
    set_file(store, "vertices", str(copy_outside(store)))


def dot_dot(store):
    copy_outside(store)
    set_file(store, "vertices", "../outside/vertices.npy")


def dot_dot_inside(store):
    copy_outside(store)
    set_file(store, "vertices", "domains/../../outside/vertices.npy")


def symlink_file(store):
    target = copy_outside(store)
    (domain(store) / "vertices.npy").unlink()
    (domain(store) / "vertices.npy").symlink_to(target)


def symlink_folder(store):
    outside = store.parent / "outside"
    for f in domain(store).iterdir():
        shutil.copy(f, outside / f.name)
    shutil.rmtree(domain(store))
    domain(store).symlink_to(outside, target_is_directory=True)


def symlink_manifest(store):
    target = store.parent / "outside" / "manifest.json"
    shutil.move(store / "manifest.json", target)
    (store / "manifest.json").symlink_to(target)


def wrong_name(store):
    set_file(store, "vertices", "domains/00000/indices.npy")


def unknown_kind(store):
    shutil.copy(domain(store) / "vertices.npy", domain(store) / "normals.npy")
    set_file(store, "normals", "domains/00000/normals.npy")


def not_a_regular_file(store):
    (domain(store) / "vertices.npy").unlink()
    os.mkfifo(domain(store) / "vertices.npy")  # reading it would block forever


def negative_triangles(store):
    set_field(store, "triangles", -5)


def fractional_count(store):
    set_field(store, "vertices", 12.5)


def zero_vertices(store):
    set_field(store, "vertices", 0)


def nan_bounds(store):
    edit(store, lambda m: m["domains"][0]["bounds"][0].__setitem__(1, float("nan")))


def inf_bounds(store):
    edit(store, lambda m: m["domains"][1]["bounds"][1].__setitem__(2, float("inf")))


def nan_scene_bounds(store):
    edit(store, lambda m: m["bounds"][0].__setitem__(0, float("nan")))


def lo_above_hi(store):
    edit(store, lambda m: m["domains"][0].__setitem__("bounds", m["domains"][0]["bounds"][::-1]))


def bounds_as_strings(store):
    edit(store, lambda m: m["domains"][0].__setitem__("bounds", [["0", "0", "0"], ["1", "1", "1"]]))


def triangle_count_mismatch(store):
    def change(m):
        m["domains"][0]["triangles"] += 1
        m["triangles"] += 1
    edit(store, change)


def wrong_dtype(store):
    rewrite_array(store, "vertices", lambda a: a.astype(np.float64))


def index_out_of_range(store):
    def change(indices):
        indices = indices.copy()
        indices[len(indices) // 2, 1] = len(np.load(domain(store) / "vertices.npy"))
        return indices
    rewrite_array(store, "indices", change)


def duplicate_ids(store):
    set_field(store, "id", 0, i=1)


def non_contiguous_ids(store):
    set_field(store, "id", 7, i=1)


def total_mismatch(store):
    edit(store, lambda m: m.__setitem__("triangles", m["triangles"] + 10))


def bytes_mismatch(store):
    edit(store, lambda m: m["domains"][1].__setitem__("bytes", m["domains"][1]["bytes"] + 4))


def missing_checksum(store):
    edit(store, lambda m: m["domains"][1].pop("sha256"))


def huge_manifest(store):
    with open(store / "manifest.json", "r+b") as fh:  # sparse: costs no disk
        fh.truncate(MAX_MANIFEST_BYTES + 1)


def too_many_domains(store):
    edit(store, lambda m: m.__setitem__("domains", [{}] * (MAX_DOMAINS + 1)))


def deeply_nested(store):
    (store / "manifest.json").write_text('{"format": "vastray-store", "version": 2, "x": '
                                         + "[" * 200_000 + "]" * 200_000 + "}")


D0 = "domains/00000/"
#: case -> (damage, file the error names, relative to the store; pattern of the problem)
CASES = {
    "absolute_path": (absolute_path, "manifest.json", "absolute path"),
    "dot_dot": (dot_dot, "manifest.json", r"climbs out with '\.\.'"),
    "dot_dot_inside": (dot_dot_inside, "manifest.json", r"climbs out with '\.\.'"),
    "symlink_file": (symlink_file, "manifest.json", "outside the store"),
    "symlink_folder": (symlink_folder, "manifest.json", "outside the store"),
    "symlink_manifest": (symlink_manifest, "manifest.json", "outside the store"),
    "wrong_name": (wrong_name, "manifest.json", "must be named 'vertices.npy'"),
    "unknown_kind": (unknown_kind, "manifest.json", "unknown file kind"),
    "not_a_regular_file": (not_a_regular_file, D0 + "vertices.npy", "not a regular file"),
    "negative_triangles": (negative_triangles, "manifest.json", "'triangles' must be a whole number >= 0"),
    "fractional_count": (fractional_count, "manifest.json", "'vertices' must be a whole number"),
    "zero_vertices": (zero_vertices, "manifest.json", "triangles but 0 vertices"),
    "nan_bounds": (nan_bounds, "manifest.json", "domain 0 bounds are not finite"),
    "inf_bounds": (inf_bounds, "manifest.json", "domain 1 bounds are not finite"),
    "nan_scene_bounds": (nan_scene_bounds, "manifest.json", "scene 'bounds' are not finite"),
    "lo_above_hi": (lo_above_hi, "manifest.json", "lo > hi"),
    "bounds_as_strings": (bounds_as_strings, "manifest.json", r"bounds must be \[\[xlo"),
    "triangle_count_mismatch": (triangle_count_mismatch, D0 + "indices.npy", "does not match the manifest"),
    "wrong_dtype": (wrong_dtype, D0 + "vertices.npy", "does not match the manifest.*float64"),
    "index_out_of_range": (index_out_of_range, D0 + "indices.npy", "out of range"),
    "duplicate_ids": (duplicate_ids, "manifest.json", "duplicate domain id 0"),
    "non_contiguous_ids": (non_contiguous_ids, "manifest.json", r"0\.\.N-1 in order: entry 1 has id 7"),
    "total_mismatch": (total_mismatch, "manifest.json", "'triangles' says"),
    "bytes_mismatch": (bytes_mismatch, "manifest.json", "domain 1 'bytes' says"),
    "missing_checksum": (missing_checksum, "manifest.json", "'sha256' must give a checksum"),
    "huge_manifest": (huge_manifest, "manifest.json", "more than the .* a store manifest may have"),
    "too_many_domains": (too_many_domains, "manifest.json", f"more than the {MAX_DOMAINS:,}"),
    "deeply_nested": (deeply_nested, "manifest.json", "nested too deeply"),
}


def open_and_load_all(path: Path) -> None:
    store = Store(path)
    for i in range(len(store.domains)):
        store.load_domain(i)
        store.load_domain(i, mmap=True)


@pytest.mark.parametrize("case", sorted(CASES))
def test_store_refuses_with_the_file_named(store, case):
    damage, culprit, pattern = CASES[case]
    damage(store)
    start = time.perf_counter()
    with pytest.raises(InputError, match=pattern) as err:
        open_and_load_all(store)
    assert time.perf_counter() - start < 2.0
    assert err.value.path == str(store / culprit)
    assert len(str(err.value).splitlines()) == 1


@pytest.mark.parametrize("case", sorted(CASES))
def test_render_exits_2_with_one_line_and_no_image(store, tmp_path, capsys, case):
    damage, culprit, pattern = CASES[case]
    damage(store)
    out, png = tmp_path / "never.exr", tmp_path / "never.png"
    capsys.readouterr()
    assert main(["render", str(store), "-o", str(out), "--png", str(png), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"vastray render: error: {store / culprit}: "), err
    assert not out.exists() and not png.exists()
    assert not list(tmp_path.glob(".never*"))


@pytest.mark.parametrize("case", sorted(CASES))
def test_verify_exits_2_naming_the_file(store, capsys, case):
    damage, culprit, pattern = CASES[case]
    damage(store)
    capsys.readouterr()
    assert main(["verify", str(store)]) == 2
    captured = capsys.readouterr()
    lines = (captured.out + captured.err).strip().splitlines()
    assert any(line.startswith(f"{store / culprit}: ") or
               line.startswith(f"vastray verify: error: {store / culprit}: ") for line in lines), lines


def test_out_of_core_render_refuses_an_index_out_of_range(store, tmp_path, capsys):
    index_out_of_range(store)
    out = tmp_path / "never.exr"
    capsys.readouterr()
    assert main(["render", str(store), "-o", str(out), "--cache", "1",
                 "--scheduler", "spec-ooc", *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "out of range" in err, err
    assert str(store / D0 / "indices.npy") in err
    assert not out.exists()


def test_huge_manifest_fails_fast_everywhere(store, capsys):
    huge_manifest(store)
    start = time.perf_counter()
    with pytest.raises(InputError, match="not read"):
        Store(store)
    assert not is_store(store)
    with pytest.raises(InputError, match="not a vastray store"):
        check_replaceable(store, force=True)  # and --force does not delete it
    capsys.readouterr()
    assert main(["info", str(store)]) == 2
    assert main(["verify", str(store)]) == 2
    assert time.perf_counter() - start < 2.0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("vastray ") and "manifest.json" in line for line in err)


def test_verify_detects_a_tampered_array_by_its_checksum(store, capsys):
    target = domain(store, 1) / "vertices.npy"
    data = bytearray(target.read_bytes())
    data[-5] ^= 0x01  # a plausible float, same shape: only the checksum can tell
    target.write_bytes(bytes(data))
    Store(store)  # opening (headers only) cannot see it; loading refuses it (test_store_changed)
    capsys.readouterr()
    assert main(["verify", str(store)]) == 2  # ... verify does
    out = capsys.readouterr().out.strip().splitlines()
    assert out[0].startswith(f"{target}: checksum mismatch"), out
    assert len(out) == 2 and "1 problem" in out[1]


def test_verify_reports_every_problem_and_reads_past_them(store, capsys):
    rewrite_array(store, "vertices", lambda a: a.astype(np.float64))   # domain 0
    target = domain(store, 1) / "indices.npy"                            # domain 1
    indices = np.load(target)
    indices[0, 0] = 10**6
    target.unlink()
    np.save(target, indices)
    result = verify_store(store)
    named = [p.path for p in result.problems]
    assert str(domain(store) / "vertices.npy") in named
    assert str(target) in named
    messages = " | ".join(str(p) for p in result.problems)
    assert "checksum mismatch" in messages and "out of range" in messages
    assert not result.ok


def test_verify_finds_vertices_outside_their_box(store, capsys):
    def shrink(m):
        lo, hi = np.array(m["domains"][0]["bounds"])
        m["domains"][0]["bounds"] = [lo.tolist(), ((lo + hi) / 2).tolist()]
    edit(store, shrink)
    Store(store)  # consistent on its face
    capsys.readouterr()
    assert main(["verify", str(store)]) == 2
    out = capsys.readouterr().out
    assert f"{domain(store) / 'vertices.npy'}: " in out and "outside the domain's bounds" in out


def test_verify_clean_store(store, capsys):
    capsys.readouterr()
    assert main(["verify", str(store)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "OK" in out[0] and "checksums checked" in out[0]
    manifest = json.loads((store / "manifest.json").read_text())
    for entry in manifest["domains"]:
        for kind, rel in entry["files"].items():
            assert entry["sha256"][kind] == hashlib.sha256((store / rel).read_bytes()).hexdigest()


def test_version_1_store_without_checksums_still_opens(store, capsys):
    def downgrade(m):
        m["version"] = 1
        for entry in m["domains"]:
            entry.pop("sha256")
    edit(store, downgrade)
    assert Store(store).n_triangles > 0
    capsys.readouterr()
    assert main(["verify", str(store)]) == 0
    assert "version 1 store has no checksums" in capsys.readouterr().out


def test_symlinks_inside_the_store_are_fine(store):
    moved = store / "shared" / "vertices.npy"
    moved.parent.mkdir()
    shutil.move(domain(store) / "vertices.npy", moved)
    (domain(store) / "vertices.npy").symlink_to(Path("..") / ".." / "shared" / "vertices.npy")
    open_and_load_all(store)
    assert verify_store(store).ok


def test_legitimately_empty_domain_is_kept(tmp_path, capsys):
    mesh = bumpy_scene()
    empty = DomainArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32))
    with StoreWriter(tmp_path / "e.store") as writer:
        writer.add_domain(mesh)
        writer.add_domain(empty)
    store = Store(tmp_path / "e.store")
    assert [d.n_triangles for d in store.domains] == [mesh.n_triangles, 0]
    assert store.load_domain(1).n_triangles == 0
    capsys.readouterr()
    assert main(["verify", str(tmp_path / "e.store")]) == 0


@pytest.mark.parametrize("bad", ["nan_vertex", "index_out_of_range"])
def test_writer_refuses_to_write_what_it_could_not_read(tmp_path, bad):
    mesh = bumpy_scene()
    vertices, indices = mesh.vertices.copy(), mesh.indices.copy()
    if bad == "nan_vertex":
        vertices[indices[0, 0]] = np.nan
    else:
        indices[3, 2] = len(vertices)
    with pytest.raises(InputError):
        with StoreWriter(tmp_path / "w.store") as writer:
            writer.add_domain(DomainArrays(vertices, indices))
    assert list(tmp_path.iterdir()) == []


def test_verify_help_has_a_runnable_example(tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit) as exc:
        main(["verify", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "example" in out and "exit status" in out
    lines = [line.split("#")[0].split() for line in out.splitlines()
             if line.strip().startswith("vastray ")]
    assert [w[1] for w in lines] == ["generate", "verify"]
    monkeypatch.chdir(tmp_path)
    for words in lines:
        assert main(words[1:]) == 0


def test_verify_reports_a_grown_file_without_reading_it(tmp_path, monkeypatch):
    """A domain file grown far past what its header promises (here sparse, 1 GiB) is reported
    from its size alone: verify once read it whole into memory (10 GB took over 30 s)."""
    store = write_store(tmp_path / "s.store", bumpy_scene(), grid=(2, 1, 1))
    grown = store.path / store.domains[1].files["vertices"]
    os.truncate(grown, 1 << 30)
    real_read = Path.read_bytes

    def read_bytes(path):
        assert Path(path) != grown, "verify read the grown file"
        return real_read(path)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    problems = verify_store(store.path).problems
    assert [p.path for p in problems] == [str(grown)]
    assert "1,073,741,824 bytes where its header promises" in str(problems[0])
