"""`vastray render` / `vastray compare` end to end: outputs, reports, bad input, leaving out."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import OpenEXR
import pytest
import trimesh

from vastray.cli import main
from vastray.render.driver import render
from vastray.render.imageio import read_exr, write_exr

from scenes import bumpy_scene, camera_config, mesh_arrays, settings, write_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("cli") / "s.store", bumpy_scene(), grid=(2, 2, 2))


SMALL = ["--width", "32", "--height", "24", "--spp", "2", "--shadow-samples", "2", "--quiet"]


def test_render_writes_exr_layers_png_and_report(store, tmp_path):
    out, png, report = tmp_path / "a.exr", tmp_path / "a.png", tmp_path / "a.json"
    assert main(["render", str(store.path), "-o", str(out), "--png", str(png),
                 "--report", str(report), *SMALL]) == 0
    with OpenEXR.File(str(out)) as f:
        channels = f.channels()
        assert {"RGB", "depth.Z", "normal.X", "normal.Y", "normal.Z"} <= set(channels)
        assert channels["RGB"].pixels.shape == (24, 32, 3)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads(report.read_text())
    for key in ("total", "load", "trace_and_shade"):
        assert doc["seconds"][key] >= 0
    # every path's camera ray, traced or left out for missing the scene's box
    assert doc["counters"]["rays"]["camera"] + doc["counters"]["camera_rays_escaped"] == 32 * 24 * 2
    assert doc["counters"]["loads"] >= 1
    assert "error" not in doc
    # how the render queried Embree: the compiled binding, packets where the CPU has AVX
    assert doc["embree"]["binding"] == "compiled" and doc["embree"]["version"].startswith("4.")
    assert doc["embree"]["queries"] in ("8-ray packets", "1 ray a call")


def test_report_says_one_ray_a_call_where_packets_are_not_native(store, tmp_path):
    # an SSE-only CPU, emulated: Embree traces 8-ray packets ray by ray there (the CLI as
    # users run it, without --quiet: its last line names what it wrote)
    report = tmp_path / "sse.json"
    env = {**os.environ, "VASTRAY_EMBREE_CONFIG": "max_isa=sse4.2"}
    loud = [a for a in SMALL if a != "--quiet"]
    done = subprocess.run([sys.executable, "-m", "vastray", "render", str(store.path), "-o",
                           str(tmp_path / "sse.exr"), "--report", str(report), *loud],
                          env=env, check=True, capture_output=True, text=True)
    last = (done.stdout + done.stderr).strip().splitlines()[-1]
    assert last.startswith("wrote ") and "sse.exr, " in last and "sse.json (32x24" in last, last
    embree = json.loads(report.read_text())["embree"]
    assert embree == {"binding": "compiled", "version": embree["version"],
                      "queries": "1 ray a call"}


def test_report_has_error_against_reference_beside_time(store, tmp_path, capsys):
    ref = tmp_path / "ref.exr"
    assert main(["render", str(store.path), "-o", str(ref), *SMALL, "--spp", "8"]) == 0
    out, report = tmp_path / "b.exr", tmp_path / "b.json"
    assert main(["render", str(store.path), "-o", str(out), "--report", str(report),
                 "--reference", str(ref), *SMALL]) == 0
    doc = json.loads(report.read_text())
    assert doc["error"]["mse"] > 0 and np.isfinite(doc["error"]["psnr_db"])
    assert doc["error_vs_time"][0]["seconds"] == doc["seconds"]["total"]
    capsys.readouterr()
    assert main(["compare", str(out), str(ref)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("mse=") and "psnr_db=" in printed
    assert main(["compare", str(ref), str(ref)]) == 0
    assert "mse=0 " in capsys.readouterr().out


@pytest.mark.parametrize("case", ["missing_store", "bad_toml", "unknown_light", "bad_reference",
                                  "reference_size", "truncated_domain", "png_reference"])
def test_bad_input_fails_with_one_line_and_no_output(store, tmp_path, capsys, case):
    out = tmp_path / "never.exr"
    args = ["render", str(store.path), "-o", str(out), *SMALL]
    if case == "missing_store":
        args[1] = str(tmp_path / "nope.store")
    elif case == "bad_toml":
        (tmp_path / "s.toml").write_text("[camera\nfov = 3")
        args += ["--scene", str(tmp_path / "s.toml")]
    elif case == "unknown_light":
        (tmp_path / "s.toml").write_text('[[light]]\ntype = "laser"\n')
        args += ["--scene", str(tmp_path / "s.toml")]
    elif case == "bad_reference":
        (tmp_path / "r.exr").write_bytes(b"not an exr")
        args += ["--reference", str(tmp_path / "r.exr")]
    elif case == "reference_size":
        write_exr(tmp_path / "r.exr", np.zeros((5, 5, 3), np.float32))
        args += ["--reference", str(tmp_path / "r.exr")]
    elif case == "png_reference":
        (tmp_path / "r.png").write_bytes(b"\x89PNG\r\n\x1a\n")
        args += ["--reference", str(tmp_path / "r.png")]
    elif case == "truncated_domain":
        broken = write_store(tmp_path / "broken.store", bumpy_scene(), grid=(2, 1, 1))
        victim = broken.path / broken.domains[1].files["vertices"]
        victim.write_bytes(victim.read_bytes()[:200])
        args[1] = str(broken.path)
    capsys.readouterr()
    assert main(args) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray render: error:") and len(err.splitlines()) == 1, err
    if case == "png_reference":
        assert "r.png: a PNG is an 8-bit preview, not radiance: give the .exr" in err
    assert not out.exists()
    assert not list(tmp_path.glob(".never*"))  # no temporary left behind


def test_no_lights_means_no_shadow_rays(store):
    cfg = camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0], lights=[])
    result = render(store, cfg, settings(), progress=False)
    assert result.counters["rays"]["shadow"] == 0
    assert result.film.image().max() == 0.0


def test_domains_no_ray_enters_are_never_loaded(tmp_path):
    # Two spheres far apart in separate domains; the camera looks at one only.
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    b.apply_translation([100.0, 0.0, 0.0])
    store = write_store(tmp_path / "two", mesh_arrays(trimesh.util.concatenate([a, b])),
                        grid=(2, 1, 1))
    cfg = camera_config([0.0, 0.0, 4.0], [0.0, 0.0, 0.0], fov=30)
    for integrator in ("ao", "pt"):
        result = render(store, cfg, settings(integrator=integrator, ao_distance=0.5),
                        progress=False)
        assert result.counters["domains"] == 2
        assert result.counters["domains_entered"] == 1
        assert result.counters["distinct_domains_loaded"] == 1


def test_exr_round_trip(tmp_path):
    rgb = np.random.default_rng(0).random((7, 9, 3)).astype(np.float32)
    write_exr(tmp_path / "x.exr", rgb, np.ones((7, 9)), np.zeros((7, 9, 3)))
    np.testing.assert_array_equal(read_exr(tmp_path / "x.exr"), rgb)


def test_compare_refuses_a_png_naming_what_it_reads(store, tmp_path, capsys):
    png = tmp_path / "a.png"
    assert main(["render", str(store.path), "-o", str(png), *SMALL, "--quiet"]) == 0
    assert main(["compare", str(png), str(png)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"vastray compare: error: {png}: a PNG is an 8-bit preview, not radiance: "
                   "give the .exr, .pfm or .npy image")


def test_more_local_nodes_than_cores_is_warned_of(store, tmp_path, monkeypatch, caplog):
    # this machine, as one whose process may use a single core
    monkeypatch.setattr("vastray.planning.available_cpus", lambda: 1)
    assert main(["render", str(store.path), "-o", str(tmp_path / "o.exr"), *SMALL, "--nodes",
                 "2", "--quiet"]) == 0
    assert "--nodes 2 on 1 core(s): the nodes share them" in caplog.text


def test_progress_bar_says_compiling_instead_of_an_eta_until_the_first_paths():
    import io

    from vastray.render.progress import COMPILING, RenderBar

    out = io.StringIO()
    with RenderBar(total=1000, unit="path", file=out, compiled=False, mininterval=0,
                   delay=2.0) as bar:
        assert COMPILING in out.getvalue()  # at once, not after the delay
        bar.update(100)  # the first paths: the kernels are compiled
        shown = out.getvalue().split("\r")[-1]
        assert COMPILING not in shown and "<" not in shown  # no ETA from the compile's rate
        time.sleep(0.05)
        bar.update(100)
        assert "<" in out.getvalue().split("\r")[-1]  # an ETA from the paths since
    out = io.StringIO()
    with RenderBar(total=1000, file=out, compiled=True, mininterval=0, delay=0) as bar:
        bar.update(100)
    assert COMPILING not in out.getvalue()


def test_kernels_compiled_is_false_only_before_numba_has_cached_them(store, tmp_path):
    from vastray.render.progress import kernels_compiled

    render(store, camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0]), settings(), progress=False)
    assert kernels_compiled()  # this process's cache: the render above compiled or loaded them
    ask = [sys.executable, "-c", "from vastray.render.progress import kernels_compiled; "
                                 "print(kernels_compiled())"]
    fresh = subprocess.run(ask, env=dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba")),
                           capture_output=True, text=True, timeout=60)
    assert fresh.stdout.strip() == "False", fresh.stderr


@pytest.mark.slow
def test_first_render_after_install_says_it_compiles(store, tmp_path):
    run = subprocess.run([sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o",
                          str(tmp_path / "o.exr"), "--width", "32", "--height", "24", "--spp",
                          "1"], env=dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba")),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "compiling kernels (first run only)" in run.stderr


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc", "domain", "dynamic", "async",
                                       "temporal", "spec-insitu"])
def test_every_node_scheduler_from_the_cli_as_a_user_runs_it(store, tmp_path, capsys,
                                                              scheduler):
    # No --quiet: the progress bar and the summary line are printed (a crash there once hid
    # behind --quiet). Each node's report carries the domain loop's spans, named the same for
    # every scheduler that activates domains (spec-insitu traces its resident domains in its
    # own iterations: only its loads go through the loop).
    out, report = tmp_path / "o.exr", tmp_path / "r.json"
    small = [a for a in SMALL if a != "--quiet"]
    assert main(["render", str(store.path), "-o", str(out), *small, "--nodes", "2",
                 "--scheduler", scheduler, "--report", str(report), "--cold-reads"]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"wrote {out}") and "domain loads" in last, last
    doc = json.loads(report.read_text())
    assert doc["scheduler"] == scheduler and doc["counters"]["nodes"] == 2
    assert doc["options"]["cold_reads"] is True  # handed to every node's domain cache
    nodes = [node["counters"] for node in doc["counters"]["per_node"]]
    if scheduler == "spec-insitu":
        assert not any("trace_s" in c for c in nodes)
        assert sum(c["bytes_sent"] for c in nodes) > 0
    elif scheduler in ("image", "spec-ooc"):  # the one-process runtime on each node
        assert sum(c["radiance_tests"] for c in nodes) > 0
    else:
        assert sum(c["trace_s"] for c in nodes) > 0 and sum(c["schedule_s"] for c in nodes) > 0
        assert sum(c["bytes_sent"] for c in nodes) > 0  # rays moved between the nodes
