"""``vastray partition | generate | info`` through ``vastray.cli.main``."""

from __future__ import annotations

import json
import sys
import types

import numpy as np
import pytest
import trimesh

from vastray.scene.store import Store


@pytest.fixture
def main(monkeypatch):
    """``vastray.cli.main``; works even before the render commands exist."""
    try:
        import vastray.commands_render  # noqa: F401
    except ImportError:
        stub = types.ModuleType("vastray.commands_render")
        stub.register = lambda sub: None
        monkeypatch.setitem(sys.modules, "vastray.commands_render", stub)
    from vastray.cli import main as cli_main

    return cli_main


@pytest.fixture
def meshes(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=3)
    sphere.export(tmp_path / "ball.ply")
    box = trimesh.creation.box(extents=[1, 2, 3])
    box.apply_translation([3, 0, 0])
    box.export(tmp_path / "brick.obj")
    return tmp_path / "ball.ply", tmp_path / "brick.obj", len(sphere.faces), len(box.faces)


def no_store_left(tmp_path, name):
    return not any(p.name == name or p.name.startswith(f".{name}.") for p in tmp_path.iterdir())


def test_partition_two_inputs_into_objects(main, meshes, tmp_path, capsys):
    ball, brick, n_ball, n_brick = meshes
    out = tmp_path / "two.store"
    assert main(["partition", str(ball), str(brick), "-o", str(out), "--grid", "3x1x1"]) == 0
    store = Store(out)
    assert store.objects == [{"name": "ball.ply", "source": str(ball.resolve())},
                             {"name": "brick.obj", "source": str(brick.resolve())}]
    assert store.n_triangles == n_ball + n_brick
    objects = np.concatenate([store.load_domain(i).objects for i in range(len(store.domains))])
    assert np.bincount(objects).tolist() == [n_ball, n_brick]
    assert "2 input(s)" in capsys.readouterr().out


def test_partition_single_input_kd(main, meshes, tmp_path, capsys):
    ball, _, n_ball, _ = meshes
    out = tmp_path / "kd.store"
    # without --quiet, as a user runs it: the k-d path's summary is printed too
    assert main(["partition", str(ball), "-o", str(out), "--domains", "5"]) == 0
    assert str(out.name) in capsys.readouterr().out
    store = Store(out)
    assert len(store.domains) == 5 and store.n_triangles == n_ball
    assert "objects" not in store.domains[0].files
    assert store.manifest["partition"]["method"] == "kd"
    # default split is a 2x2x2 grid
    assert main(["partition", str(ball), "-o", str(tmp_path / "g"), "--quiet"]) == 0
    assert Store(tmp_path / "g").manifest["partition"]["grid"] == [2, 2, 2]


def test_partition_volume_with_iso(main, tmp_path, capsys):
    axes = np.linspace(-1, 1, 30, dtype=np.float32)
    vol = np.sqrt(axes[:, None, None] ** 2 + axes[None, :, None] ** 2 + axes[None, None, :] ** 2)
    np.save(tmp_path / "v.npy", vol)
    out = tmp_path / "v.store"
    assert main(["partition", str(tmp_path / "v.npy"), "-o", str(out), "--iso", "0.7",
                 "--brick", "8"]) == 0  # without --quiet: the volume path's summary too
    assert Store(out).n_triangles > 1000
    assert str(out.name) in capsys.readouterr().out


def test_generate_and_info(main, tmp_path, capsys):
    out = tmp_path / "rm.store"
    assert main(["generate", "rm", "-o", str(out), "--resolution", "24", "--grid", "2x1x2",
                 "--seed", "3", "--quiet"]) == 0
    store = Store(out)
    assert store.manifest["generator"]["seed"] == 3
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{store.n_triangles:,} triangles" in text
    assert "scene bounds" in text and "partition: grid 2x1x2" in text


def test_existing_store_needs_force(main, meshes, tmp_path, capsys):
    ball = str(meshes[0])
    out = tmp_path / "s.store"
    assert main(["partition", ball, "-o", str(out), "--quiet"]) == 0
    before = json.loads((out / "manifest.json").read_text())
    assert main(["partition", ball, "-o", str(out), "--grid", "1x1x1", "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err
    assert json.loads((out / "manifest.json").read_text()) == before
    assert main(["partition", ball, "-o", str(out), "--grid", "1x1x1", "--force",
                 "--quiet"]) == 0
    assert len(Store(out).domains) == 1


@pytest.mark.parametrize("case", ["missing", "unsupported", "no-iso", "nan", "degenerate",
                                  "kd-without-domains", "folder", "store", "too-many-domains"])
def test_bad_input_fails_cleanly(main, tmp_path, capsys, meshes, case):
    ball = str(meshes[0])
    args = {
        "missing": [str(tmp_path / "missing.ply")],
        "unsupported": [str(tmp_path / "scene.blend")],
        "no-iso": [str(tmp_path / "v.npy")],
        "nan": [ball, str(tmp_path / "nan.obj")],
        "degenerate": [str(tmp_path / "flat.obj")],
        "kd-without-domains": [ball, "--split", "kd"],
        "folder": [str(tmp_path / "adir")],
        "store": [str(tmp_path / "old.store")],
        "too-many-domains": [ball, "--domains", "100000"],
    }[case]
    (tmp_path / "adir").mkdir()
    assert main(["partition", ball, "-o", str(tmp_path / "old.store"), "--quiet"]) == 0
    (tmp_path / "scene.blend").write_text("x")
    np.save(tmp_path / "v.npy", np.zeros((3, 3, 3)))
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    capsys.readouterr()
    assert main(["partition", *args, "-o", str(tmp_path / "out.store"), "--quiet"]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray partition: error: ") and "\n" not in err
    if case not in ("kd-without-domains", "too-many-domains"):
        assert args[-1].rsplit("/", 1)[-1] in err  # names the file
    says = {"folder": "is a folder; give the mesh or volume files in it",
            "store": "is a store already; render it with `vastray render",
            "too-many-domains": "--domains 100,000 is more than the "}.get(case, "")
    assert says in err
    assert no_store_left(tmp_path, "out.store")


def test_generate_bad_grid_fails_cleanly(main, tmp_path, capsys):
    assert main(["generate", "cosmo", "-o", str(tmp_path / "c"), "--resolution", "3",
                 "--grid", "4x1x1"]) == 2
    assert "--grid" in capsys.readouterr().err
    assert no_store_left(tmp_path, "c")


def test_info_on_damaged_store(main, tmp_path, capsys):
    assert main(["info", str(tmp_path / "nothing")]) == 2
    assert "no such store" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["partition", "generate", "info"])
def test_help_has_an_example(main, command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert f"vastray {command} " in out and "example" in out


def test_domains_holding_a_few_triangles_each_are_warned_of(main, meshes, tmp_path, caplog):
    domains = meshes[2] // 8
    assert main(["partition", str(meshes[0]), "-o", str(tmp_path / "s.store"), "--domains",
                 str(domains), "--quiet"]) == 0
    assert f"--domains {domains:,} leaves about 8 triangles per domain" in caplog.text


@pytest.mark.parametrize("case", ["huge-grid", "truncated-ply", "file-in-the-way"])
def test_partition_refuses_before_any_work(main, tmp_path, capsys, meshes, case):
    """A grid of a billion cells (it once took 24 GB before the kernel killed it), an ASCII
    PLY cut short (trimesh read its first faces without a word) and an output under a file
    (a traceback) are each refused on one line, and no store is left."""
    ball = str(meshes[0])
    (tmp_path / "cut.ply").write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.load(ball, process=False), encoding="ascii")[:-40])
    (tmp_path / "afile").write_text("x")
    args, out = {
        "huge-grid": ([ball, "--grid", "1000x1000x1000"], tmp_path / "out.store"),
        "truncated-ply": ([str(tmp_path / "cut.ply")], tmp_path / "out.store"),
        "file-in-the-way": ([ball], tmp_path / "afile" / "out.store"),
    }[case]
    assert main(["partition", *args, "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray partition: error: ") and "\n" not in err, err
    says = {"huge-grid": "1,000,000,000 cells; a partition grid may have at most",
            "truncated-ply": "truncated or damaged",
            "file-in-the-way": "afile is not a folder"}[case]
    assert says in err
    assert no_store_left(tmp_path, "out.store")
    assert (tmp_path / "afile").read_text() == "x"


def test_generate_under_a_file_fails_cleanly(main, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    assert main(["generate", "rm", "-o", str(tmp_path / "afile" / "x.store"),
                 "--resolution", "16", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray generate: error: ") and "is not a folder" in err, err


def test_force_keeps_a_store_holding_other_files(main, meshes, tmp_path, capsys, monkeypatch):
    """``--force`` replaces a store, never a user's file put inside it (here the very mesh
    being partitioned), nor the folder the command runs in."""
    ball = str(meshes[0])
    out = tmp_path / "s.store"
    assert main(["partition", ball, "-o", str(out), "--quiet"]) == 0
    mine = out / "mesh.ply"
    mine.write_bytes((tmp_path / "ball.ply").read_bytes())
    assert main(["partition", str(mine), "-o", str(out), "--force", "--quiet"]) == 2
    assert "'mesh.ply', which is not part of the store" in capsys.readouterr().err
    assert mine.is_file() and Store(out).n_triangles
    mine.unlink()
    (out / ".simplified.x1y2").mkdir()  # a killed simplify's temporary is the store's own
    monkeypatch.chdir(out / "domains")
    assert main(["partition", ball, "-o", str(out), "--force", "--quiet"]) == 2
    assert "is the current folder or holds it" in capsys.readouterr().err
    monkeypatch.chdir(tmp_path)
    assert main(["partition", ball, "-o", str(out), "--force", "--grid", "1x1x1",
                 "--quiet"]) == 0
    assert len(Store(out).domains) == 1
