"""A store changed after it was written (issue 37, item 6): each load checks the domain's files
against the manifest's checksums, so ``vastray render`` refuses a changed file with one line
naming it (in core, out of core, on nodes) instead of rendering a wrong picture with exit 0;
and a domain file truncated under a running render no longer kills it with SIGBUS: domains are
read into memory, never mapped, so the render finishes with the data it checked or refuses a
later load, with one line."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.cli import main
from vastray.render.imageio import read_image
from vastray.scene.errors import InputError
from vastray.scene.manifest import parse_npy_header
from vastray.scene.store import Store
from vastray.scene.verify import verify_store

from scenes import bumpy_scene, write_store

SMALL = ["--width", "32", "--height", "24", "--spp", "1", "--shadow-samples", "1", "--quiet"]
HOW = {"in-core": [], "out-of-core": ["--cache", "1", "--scheduler", "spec-ooc"],
       "nodes": ["--nodes", "2"]}
CHANGED = "changed since the store was written"


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
    return path


def vertices_file(store: Path, domain: int = 1) -> Path:
    return store / "domains" / f"{domain:05d}" / "vertices.npy"


def edit_in_place(path: Path, change) -> None:
    """Overwrite the data of the ``.npy`` file ``path`` with ``change(array)`` (same shape and
    dtype): a valid file of the same size and inode, its header untouched."""
    with open(path, "r+b") as fh:
        header = parse_npy_header(fh)
        arr = np.frombuffer(fh.read(), header.dtype).reshape(header.shape)
        new = np.ascontiguousarray(change(arr.copy()), header.dtype)
        assert new.shape == arr.shape and new.nbytes == arr.nbytes
        fh.seek(header.offset)
        fh.write(new.tobytes())


def shrink_inside(v: np.ndarray) -> np.ndarray:
    """Every vertex moved 2 % towards the centre of its domain: still inside its box."""
    center = (v.min(axis=0) + v.max(axis=0)) / 2
    return center + 0.98 * (v - center)


def move_out_of_box(v: np.ndarray) -> np.ndarray:
    """The domain's vertices shifted by half its width in x: out of its box."""
    v[:, 0] += (v[:, 0].max() - v[:, 0].min()) / 2
    return v


def render_fails(store: Path, out: Path, how: str, capsys) -> str:
    """Render with ``vastray render`` in this process: not 0, no image; the last line."""
    capsys.readouterr()
    code = main(["render", str(store), "-o", str(out), *HOW[how], *SMALL])
    err = capsys.readouterr().err.strip().splitlines()
    # an input error, on nodes too: not a node loss survived by rendering the frame again on
    # the others, which read the same store (each met it in turn, once)
    assert code == 2 and err, (code, err)
    assert not any("again on the" in line for line in err), err
    assert not out.exists() and not list(out.parent.glob(f".{out.name}*"))
    if how != "nodes":  # the nodes' own start-up lines may come first
        assert len(err) == 1, err
    return err[-1]


@pytest.mark.parametrize("how", sorted(HOW))
@pytest.mark.parametrize("change", [shrink_inside, move_out_of_box], ids=["inside", "outside"])
def test_a_file_edited_in_place_is_refused_naming_it(store, tmp_path, capsys, how, change):
    target = vertices_file(store)
    size, inode = target.stat().st_size, target.stat().st_ino
    edit_in_place(target, change)
    assert (target.stat().st_size, target.stat().st_ino) == (size, inode)
    Store(store)  # opening reads headers only: the store is consistent on its face
    line = render_fails(store, tmp_path / "never.exr", how, capsys)
    assert f"{target}: domain 1 {CHANGED} (CRC-32 " in line, line
    if how != "nodes":  # a node's report of its failure is cut at 300 characters
        assert line.endswith(f"`vastray verify {store}` lists every changed file"), line
    assert verify_store(store).problems[0].path == str(target)


def test_an_untouched_store_renders(store, tmp_path, capsys):
    out = tmp_path / "ok.exr"
    assert main(["render", str(store), "-o", str(out), *SMALL]) == 0
    assert np.isfinite(read_image(out)).all()


def downgrade_to_version_3(store: Path) -> None:
    """The manifest as a version 3 vastray wrote it: SHA-256s, no CRC-32s."""
    manifest = json.loads((store / "manifest.json").read_text())
    manifest["version"] = 3
    for entry in manifest["domains"]:
        del entry["crc32"]
    (store / "manifest.json").write_text(json.dumps(manifest))


def test_a_version_3_store_is_checked_by_its_sha256(store):
    downgrade_to_version_3(store)
    for d in range(2):
        Store(store).load_domain(d)  # untouched: loads
    edit_in_place(vertices_file(store), shrink_inside)
    with pytest.raises(InputError, match=f"domain 1 {CHANGED} \\(SHA-256 "):
        Store(store).load_domain(1)


@pytest.mark.parametrize("mmap", [False, True])
def test_every_kind_of_load_checks(store, mmap):
    target = store / "domains" / "00000" / "indices.npy"
    edit_in_place(target, lambda i: i[:, ::-1])  # the triangles flipped: same indices
    with pytest.raises(InputError, match=CHANGED) as err:
        Store(store).load_domain(0, mmap=mmap)
    assert err.value.path == str(target)


def test_a_malformed_crc32_is_refused_naming_the_manifest(store):
    manifest = json.loads((store / "manifest.json").read_text())
    manifest["domains"][0]["crc32"]["vertices"] = "xyz"
    (store / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="'crc32' of vertices is not 8 lowercase hex") as err:
        Store(store)
    assert err.value.path == str(store / "manifest.json")


# --- a domain file truncated under a running render -------------------------------------------

AFTER_LOAD = textwrap.dedent("""
    import os, sys
    import numpy as np
    from vastray.scene.cache import DomainCache
    from vastray.scene.store import Store

    store = Store(sys.argv[1])
    cache = DomainCache(store, len(store.domains))
    domains = [cache.get(d) for d in range(len(store.domains))]  # every domain loaded
    rng = np.random.default_rng(1)
    origins = rng.uniform(-3, 3, (4000, 3)).astype(np.float32)
    dirs = rng.normal(size=(4000, 3)).astype(np.float32)
    far = np.full(4000, np.inf, np.float32)


    def hits():  # Embree's hits, and the triangles' corners as shading reads them
        out = [d.intersect(origins, dirs, far)["primID"] for d in domains]
        return out, [d.vertices[d.indices[np.maximum(h, 0)]] for d, h in zip(domains, out)]

    before = hits()
    for info in store.domains:  # every file cut to its header, as a careless copy would
        for rel in info.files.values():
            os.truncate(store.path / rel, 128)
    after = hits()
    assert all((a == b).all() for a, b in zip(after[0] + after[1], before[0] + before[1]))
    assert sum(int((h >= 0).sum()) for h in before[0]) > 100  # the rays did hit triangles
    print("unchanged")
""")


def test_files_truncated_after_loading_change_nothing_loaded(store):
    """Loaded domains hold their own copy of the data: truncating every file afterwards (on
    mapped files: SIGBUS when shading next reads a vertex) changes no hit."""
    run = subprocess.run([sys.executable, "-c", AFTER_LOAD, str(store)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])
    assert run.stdout.strip() == "unchanged"


def mapped(pid: int, store: Path) -> bool:
    """Whether process ``pid`` has a file of ``store`` mapped."""
    try:
        return str(store.resolve()) in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.timeout(2400)  # a reference render and the render, each allowed 900 s
@pytest.mark.slow
def test_truncating_the_store_during_an_in_core_render(store, tmp_path):
    """``vastray render`` in its own process; once it renders (its progress bar shows paths
    done, or, as before, it maps the store's files), every domain file is cut to its header.
    It either finishes with the picture of the data it loaded (the same as an untouched
    store's) or refuses a domain it loads afterwards in one line naming the file, with no
    image; it never dies of SIGBUS."""
    # long enough (seconds) for the progress bar, shown after two
    args = ["--width", "256", "--height", "192", "--spp", "48", "--integrator", "pt",
            "--bounces", "3", "--threads", "2"]
    reference = tmp_path / "reference.exr"
    shutil.copytree(store, tmp_path / "copy.store")
    subprocess.run([sys.executable, "-m", "vastray", "render", str(tmp_path / "copy.store"),
                    "-o", str(reference), *args, "--quiet"], check=True, timeout=900)
    out = tmp_path / "out.exr"
    proc = subprocess.Popen([sys.executable, "-m", "vastray", "render", str(store), "-o", str(out),
                             *args], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL)
    err = bytearray()

    def read() -> None:
        for chunk in iter(lambda: proc.stderr.read1(4096), b""):
            err.extend(chunk)

    reader = threading.Thread(target=read)
    reader.start()
    deadline = time.monotonic() + 600
    while proc.poll() is None and time.monotonic() < deadline:
        if mapped(proc.pid, store) or re.search(rb"render:\s+\d+%\|[^|]*\|\s*[1-9]", bytes(err)):
            break
        time.sleep(0.02)
    assert proc.poll() is None, "the render ended before any of it could be truncated"
    for rel in (f for info in Store(store).domains for f in info.files.values()):
        os.truncate(store / rel, 128)
    code = proc.wait(timeout=900)
    reader.join(timeout=60)
    proc.stderr.close()
    assert code not in (-signal.SIGBUS, 128 + signal.SIGBUS), f"killed by SIGBUS: {bytes(err)}"
    if code == 0:
        np.testing.assert_array_equal(read_image(out), read_image(reference))
    else:
        last = bytes(err).decode(errors="replace").replace("\r", "\n").strip().splitlines()[-1]
        assert re.fullmatch(rf"vastray render: error: {re.escape(str(store))}/domains/\d+/"
                            r"\w+\.npy: .*", last), last
        assert not out.exists()


@pytest.mark.parametrize("version", [4, 3], ids=["crc32", "sha256"])
def test_a_file_read_in_pieces_is_checked_whole(store, monkeypatch, version):
    """Loads read a file in pieces of ``READ_PIECE`` bytes and checksum each as it is read:
    in small pieces the arrays are the file's, and one byte changed in the file's last piece
    is caught by either checksum."""
    monkeypatch.setattr("vastray.scene.store.READ_PIECE", 100)
    if version == 3:
        downgrade_to_version_3(store)
    target = vertices_file(store)
    loaded = Store(store).load_domain(1)
    assert np.array_equal(loaded.vertices, np.load(target))
    assert target.stat().st_size > 50 * 100  # many pieces
    edit_in_place(target, lambda v: np.concatenate([v[:-1], v[-1:] * 1.5]))
    name = "CRC-32" if version == 4 else "SHA-256"
    with pytest.raises(InputError, match=f"domain 1 {CHANGED} \\({name} "):
        Store(store).load_domain(1)
