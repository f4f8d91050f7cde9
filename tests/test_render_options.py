"""Every `vastray render` option reaches the code it names: each changes what its help says it
changes (in the report or the outputs), or is refused with an error naming it where it does
not apply. The options are read from the parser itself: an option added without a check here
fails ``test_every_render_option_has_a_check``.

Tiny images (16 x 12, 1 spp) on a tiny store keep the in-process part fast; the checks that
need node processes are marked slow."""

from __future__ import annotations

import argparse
import gc
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from vastray.cli import build_parser, main
from vastray.preflight import (
    LIMIT_BASE_MARGIN,
    domain_build_bytes,
    domain_footprints,
    estimate_memory,
)
from vastray.render.imageio import read_image
from vastray.scene.simplify import build_simplified

from scenes import bumpy_scene, free_port, write_store

#: One point light: the memory estimate's light count is then known (--memory-limit's check).
SCENE_TOML = """\
[camera]
position = [3.0, 2.2, 4.5]
look_at = [0.0, -0.5, 0.0]
up = [0, 1, 0]
fov = 40

[[light]]
type = "point"
position = [2.0, 3.0, 1.0]
intensity = 12.0
"""
#: A second camera, for --scene and --frames (a camera that moves).
OTHER_SCENE_TOML = SCENE_TOML.replace("[3.0, 2.2, 4.5]", "[-3.0, 2.5, 4.0]")
ORBIT_TOML = SCENE_TOML.replace("[[light]]", "[camera.orbit]\ndegrees_per_frame = 20\n\n"
                                             "[[light]]")


def render_options() -> list[str]:
    """Every option of `vastray render` (argparse dests), read from the parser."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return [a.dest for a in sub.choices["render"]._actions if a.dest != "help"]


@dataclass
class Run:
    code: int
    err: str
    report: dict | None
    output: Path

    def image(self) -> np.ndarray:
        return read_image(self.output)

    @property
    def counters(self) -> dict:
        return self.report["counters"]


class Renders:
    """Runs `vastray render` in this process on the tiny store, baseline options first."""

    BASE = ["--width", "16", "--height", "12", "--spp", "1", "--bounces", "1"]

    def __init__(self, store, folder: Path, capsys):
        self.store, self.folder, self.capsys = store, folder, capsys
        self.scene = folder / "scene.toml"
        self.scene.write_text(SCENE_TOML)
        self.count = 0
        self._baseline = None

    def __call__(self, *args: str, base: list[str] | None = None, quiet: bool = False,
                 scene: bool = True, output: str = "o.exr", store: bool = True) -> Run:
        self.count += 1
        run_dir = self.folder / f"run{self.count}"
        run_dir.mkdir()
        out, report = run_dir / output, run_dir / "r.json"
        argv = ["render", *([str(self.store.path)] if store else []), "-o", str(out),
                "--report", str(report), *(self.BASE if base is None else base),
                *(["--scene", str(self.scene)] if scene else []),
                *(["--quiet"] if quiet else []), *args]
        self.capsys.readouterr()
        code = main(argv)
        err = self.capsys.readouterr().err
        if code == 0 and not quiet:
            # every option's path as users run it, summary line included (a crash in the
            # summary once hid behind --quiet)
            assert "wrote " in err, err
        doc = json.loads(report.read_text()) if report.exists() else None
        return Run(code, err, doc, out)

    @property
    def baseline(self) -> Run:
        """The render every check changes one option of (in core: ``reference``)."""
        if self._baseline is None:
            self._baseline = self()
            assert self._baseline.code == 0, self._baseline.err
            assert self._baseline.report["scheduler"] == "reference"
        return self._baseline

    def refused(self, *args: str, naming: str, **kw) -> None:
        """The run is refused (exit 2, no output) with an error that names ``naming``."""
        run = self(*args, **kw)
        assert run.code == 2, run.err
        assert naming in run.err and "error:" in run.err, run.err
        assert not run.output.exists()


@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory):
    store = write_store(tmp_path_factory.mktemp("options") / "tiny.store", bumpy_scene(),
                        grid=(2, 2, 2))
    build_simplified(store, 0.3)  # for --simplified
    return store


@pytest.fixture
def renders(tiny_store, tmp_path, capsys):
    return Renders(tiny_store, tmp_path, capsys)


# -- the checks: one per option; each asserts the option's effect or its refusal -------------

def check_store(r: Renders):
    other = write_store(r.folder / "other.store", bumpy_scene(seed=9), grid=(1, 1, 2))
    run = r(str(other.path), store=False)
    assert run.code == 0 and run.report["store"] == str(other.path)
    assert run.counters["domains"] == 2 != r.baseline.counters["domains"]


def check_output(r: Renders):
    run = r(output="o.pfm")
    assert run.code == 0 and run.output.read_bytes()[:2] == b"PF"
    np.testing.assert_array_equal(run.image(), r.baseline.image())
    r.refused(output="o.tiff", naming="o.tiff")


def check_png(r: Renders):
    png = r.folder / "p.png"
    assert r("--png", str(png)).code == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def check_scene(r: Renders):
    run = r("--scene", str(_write(r.folder / "other.toml", OTHER_SCENE_TOML)), scene=False)
    assert run.code == 0 and not np.array_equal(run.image(), r.baseline.image())


def check_integrator(r: Renders):
    run = r("--integrator", "ao", base=r.BASE[:6] + ["--shadow-samples", "1"])
    assert run.code == 0 and run.report["settings"]["integrator"] == "ao"
    assert not np.array_equal(run.image(), r.baseline.image())


def check_spp(r: Renders):
    run = r("--spp", "2")
    assert run.report["settings"]["spp"] == 2
    def camera_rays(counters):  # traced or left out for missing the scene's box
        return counters["rays"]["camera"] + counters["camera_rays_escaped"]

    assert camera_rays(run.counters) == 2 * camera_rays(r.baseline.counters)


def check_bounces(r: Renders):
    run = r("--bounces", "0")
    assert run.report["settings"]["bounces"] == 0
    assert run.counters["rays"]["total"] < r.baseline.counters["rays"]["total"]
    r.refused("--integrator", "ao", naming="--bounces")  # BASE gives --bounces


def check_shadow_samples(r: Renders):
    ao = r.BASE[:6]
    one, four = (r("--integrator", "ao", "--shadow-samples", n, base=ao) for n in ("1", "4"))
    assert four.report["settings"]["shadow_samples"] == 4
    assert four.counters["rays"]["total"] > one.counters["rays"]["total"]
    # path tracing with only a point light: one shadow ray per hit whatever the count
    r.refused("--shadow-samples", "4", naming="--shadow-samples")


def check_ao_distance(r: Renders):
    ao = r.BASE[:6]
    short = r("--integrator", "ao", "--ao-distance", "0.01", base=ao)
    assert short.report["settings"]["ao_distance"] == 0.01
    assert not np.array_equal(short.image(), r("--integrator", "ao", base=ao).image())
    r.refused("--ao-distance", "0.01", naming="--ao-distance")  # with pt


def check_width(r: Renders):
    assert r("--width", "20").image().shape == (12, 20, 3)


def check_height(r: Renders):
    assert r("--height", "10").image().shape == (10, 16, 3)


def check_seed(r: Renders):
    run = r("--seed", "5")
    assert run.report["settings"]["seed"] == 5
    assert not np.array_equal(run.image(), r.baseline.image())


def check_bvh(r: Renders):
    fast = r("--bvh", "fast")
    assert fast.report["settings"]["bvh"] == "fast"
    assert fast.report["settings"]["bvh_built"] == "fast"
    assert r.baseline.report["settings"]["bvh_built"].startswith("quality (auto: ")
    quality = r("--bvh", "quality")  # what auto chose for this small store: the same image
    assert quality.report["settings"]["bvh_built"] == "quality"
    assert np.array_equal(quality.image(), r.baseline.image())


def check_cache(r: Renders):
    run = r("--cache", "2")
    assert run.report["scheduler"] == "spec-ooc"  # auto: the domains no longer all fit
    assert run.counters["cache_capacity"] == 2 and run.report["options"]["cache"] == 2
    assert run.counters["loads"] > r.baseline.counters["loads"]
    np.testing.assert_allclose(run.image(), r.baseline.image(), rtol=1e-6, atol=1e-6)


def check_scheduler(r: Renders):
    run = r("--scheduler", "image", "--cache", "2")
    assert run.code == 0 and run.report["scheduler"] == "image"
    assert "windows" not in run.counters  # spec-ooc's speculation windows
    r.refused("--scheduler", "async", naming="--nodes")


def check_memory_limit(r: Renders):
    # image, 64 paths in flight and one light: the film and paths need `fixed`; the limit
    # leaves room for the two largest domains exactly (and for building them)
    fixed = (estimate_memory(16, 12, 64, 1).total + LIMIT_BASE_MARGIN
             + domain_build_bytes(r.store.domains, reads_ahead=True))
    largest = sorted(domain_footprints(r.store.domains), reverse=True)
    args = ["--scheduler", "image", "--max-samples-in-flight", "64", "--memory-limit"]
    run = r(*args, str(fixed + largest[0] + largest[1] + 1))
    assert run.code == 0, run.err
    assert run.counters["cache_capacity"] == 2 and run.report["options"]["cache"] == 2
    summary = run.err.strip().splitlines()[-1]
    assert f"({run.counters['peak_resident_domains']} of {len(largest)} domains held at most)" \
        in summary, summary
    # on nodes the limit bounds each node (its busiest peak is on the line, not a node's cache)
    nodes = r("--nodes", "2", *args, str(fixed + largest[0] + largest[1] + 1))
    assert nodes.code == 0, nodes.err
    summary = nodes.err.strip().splitlines()[-1]
    assert "peak RSS" in summary and "domains held" not in summary, summary
    r.refused(*args, str(fixed + largest[0] - 1), naming="--memory-limit")  # not one domain
    # in situ a node keeps every domain it owns: a limit that fits two domains, not a node's
    # share of them, is refused before any node starts
    r.refused("--nodes", "2", "--scheduler", "spec-insitu", "--max-samples-in-flight", "128",
              "--memory-limit", str(fixed + largest[0] + largest[1] + 1),
              naming="--scheduler spec-insitu")


def check_max_samples_in_flight(r: Renders):
    run = r("--scheduler", "image", "--max-samples-in-flight", "50")
    assert run.counters["max_samples_in_flight"] == 50
    assert run.report["options"]["max_samples_in_flight"] == 50
    r.refused("--max-samples-in-flight", "50", naming="--max-samples-in-flight")  # reference


def check_history_depth(r: Renders):
    spec = ["--scheduler", "spec-ooc", "--cache", "2", "--bounces", "2"]
    deep, shallow = r(*spec), r(*spec, "--history-depth", "0")
    assert shallow.report["options"]["history_depth"] == 0
    assert shallow.counters["windows"] > deep.counters["windows"]
    r.refused("--scheduler", "image", "--history-depth", "1", naming="--history-depth")


def check_no_preload(r: Renders):
    image = ["--scheduler", "image", "--cache", "2"]
    assert r(*image).counters["preloads"] > 0
    run = r(*image, "--no-preload")
    assert run.counters["preloads"] == 0 and run.report["options"]["preload"] is False
    r.refused("--no-preload", naming="--no-preload")  # the in-core reference


def check_passes_alone(r: Renders):
    apart = ["--scheduler", "image", "--cache", "2", "--spp", "4", "--time-limit", "600"]
    ahead, alone = r(*apart), r(*apart, "--passes-alone")
    assert ahead.counters["ahead_queries"] > 0 and ahead.report["options"]["trace_ahead"]
    assert "ahead_queries" not in alone.counters
    assert alone.report["options"]["trace_ahead"] is False
    assert "each sweeping the domains alone (--passes-alone)" in alone.err, alone.err
    np.testing.assert_array_equal(ahead.image(), alone.image())
    r.refused("--passes-alone", "--time-limit", "600", naming="--passes-alone")  # in core
    r.refused("--scheduler", "image", "--cache", "2", "--passes-alone",
              naming="--passes-alone")  # one pass: nothing apart


def check_load_bandwidth(r: Renders):
    for scheduler in ("image", "spec-ooc"):
        run = r("--scheduler", scheduler, "--cache", "2", "--load-bandwidth", "5")
        c = run.counters
        assert c["load_bandwidth_mb_s"] == 5.0 and run.report["options"]["load_bandwidth"] == 5.0
        assert c["read_s"] >= c["bytes_loaded"] / 5e6 - 1e-3  # every load held to 5 MB/s
        assert c["load_throttle_s"] > 0
    run = r("--load-bandwidth", "5")  # in core too: each domain loaded once, held back
    assert run.counters["load_throttle_s"] > 0 and run.counters["load_bandwidth_mb_s"] == 5.0
    assert r.baseline.counters["load_throttle_s"] == 0


def check_cold_reads(r: Renders):
    # on a copy of the store that no earlier render of this module has mapped: the kernel
    # drops no page a live mapping holds, nor a dirty one (hence the sync)
    copy = shutil.copytree(r.store.path, r.folder / "cold.store")
    os.sync()
    gc.collect()
    image = ["--scheduler", "image", "--cache", "2"]
    run = r(*image, "--cold-reads", store=False, base=[str(copy), *r.BASE])
    warm = r(*image, store=False, base=[str(copy), *r.BASE])
    c = run.counters
    assert run.report["options"]["cold_reads"] is True
    assert c["loads"] == warm.counters["loads"] and c["loads"] > c["distinct_domains_loaded"]
    np.testing.assert_array_equal(run.image(), warm.image())
    if c["disk_read_bytes"] is not None and not _in_memory_filesystem(copy):
        # the reloads came from the disk (a first load may have found its pages cached)
        reloads = c["bytes_loaded"] - sum(d.nbytes for d in r.store.domains if d.n_triangles)
        assert c["disk_read_bytes"] >= 0.5 * reloads > 0, (c["disk_read_bytes"], reloads)
        # without cold reads, at most the first load of each domain reads the disk
        assert warm.counters["disk_read_bytes"] < 0.5 * c["disk_read_bytes"], warm.counters
    r.refused("--cold-reads", naming="--cold-reads")  # the in-core reference


def _in_memory_filesystem(path: Path) -> bool:
    """Whether ``path`` is on tmpfs or ramfs, where nothing is ever read from a disk."""
    mounts = [line.split()[1:3] for line in Path("/proc/mounts").read_text().splitlines()]
    resolved = str(path.resolve())
    best = max((m for m in mounts if resolved.startswith(m[0].rstrip("/") + "/")),
               key=lambda m: len(m[0]), default=None)
    return best is not None and best[1] in ("tmpfs", "ramfs")


def check_eviction(r: Renders):
    image = ["--scheduler", "image", "--cache", "2"]
    run = r(*image, "--eviction", "demand", quiet=False)  # the summary line, as users see it
    assert run.code == 0, run.err
    last = run.err.strip().splitlines()[-1]
    assert last.startswith("wrote ") and "domain loads" in last and "GB read" in last, last
    assert run.report["options"]["eviction"] == "demand"
    assert run.counters["belady_loads"] <= run.counters["loads"]
    np.testing.assert_allclose(run.image(), r.baseline.image(), rtol=1e-6, atol=1e-6)
    r.refused("--eviction", "demand", naming="--eviction")  # the in-core reference


def check_batch_size(r: Renders):
    run = r("--batch-size", "40")
    assert run.report["settings"]["batch_size"] == 40
    np.testing.assert_array_equal(run.image(), r.baseline.image())
    r.refused("--scheduler", "image", "--batch-size", "40", naming="--batch-size")


def check_threads(r: Renders):
    assert r("--threads", "1").counters["threads"] == 1
    assert r("--threads", "2").counters["threads"] == 2


def check_report(r: Renders):
    report = r.baseline.report
    assert report["settings"]["width"] == 16 and report["seconds"]["total"] > 0


def check_reference(r: Renders):
    run = r("--reference", str(r.baseline.output))
    assert run.report["error"]["mse"] == 0
    assert r("--reference", str(r.baseline.output), "--seed", "3").report["error"]["mse"] > 0


def check_frames(r: Renders):
    r.scene.write_text(ORBIT_TOML)
    run = r("--frames", "2")
    first, second = (run.output.with_name(f"o_{f:04d}.exr") for f in (0, 1))
    assert run.code == 0 and first.exists() and second.exists() and not run.output.exists()
    assert not np.array_equal(read_image(first), read_image(second))


def check_first_frame(r: Renders):
    r.scene.write_text(ORBIT_TOML)
    run = r("--first-frame", "3")
    assert run.code == 0 and run.output.with_name("o_0003.exr").exists()


def check_exposure(r: Renders):
    dim, bright = r.folder / "dim.png", r.folder / "bright.png"
    assert r("--png", str(dim)).code == 0
    assert r("--png", str(bright), "--exposure", "4").code == 0
    assert dim.read_bytes() != bright.read_bytes()
    r.refused("--exposure", "4", naming="--exposure")  # no PNG written


def check_colormap(r: Renders):
    # its effect on a store with scalars: test_scene_vtkxml (halves coloured red and yellow)
    r.refused("--colormap", "viridis", naming="--colormap")  # the tiny store has no scalars
    r.refused("--colormap", "virdis", "--png", str(r.folder / "c.png"), naming="viridis")


def check_legend(r: Renders):
    # its effect on a store with scalars: test_scene_vtkxml (the colour bar in the PNG)
    r.refused("--legend", "--png", str(r.folder / "l.png"), naming="--legend")  # no scalars
    r.refused("--legend", naming="--legend")  # no PNG written


def check_color_range(r: Renders):
    # its effect on stores with scalars: test_user_polish (one scale for two data ranges, and
    # on the nodes)
    r.refused("--color-range", "0", "1", naming="--color-range")  # the tiny store has no scalars
    r.refused("--color-range", "1", "0", naming="--color-range")


def check_time_limit(r: Renders):
    # the rule that stops a long render: tests/test_progressive.py (stops near the limit)
    run = r("--time-limit", "600", "--spp", "4")
    assert run.code == 0 and run.report["stopped_by"] == "spp"  # reached --spp first
    assert run.report["time_limit_s"] == 600


def check_target_error(r: Renders):
    run = r("--target-error", "1e9", "--spp", "64")
    assert run.report["stopped_by"] == "target-error"
    assert run.report["passes"][-1]["spp"] == 2  # the first pass with an estimate meets it
    assert run.report["target_error"] == 1e9 and run.report["target_error_against"] == "estimate"
    assert "stopped by --target-error at 2 spp" in run.err
    missed = r("--target-error", "1e-12", "--spp", "2")
    assert missed.report["stopped_by"] == "spp"
    assert "--target-error 1e-12 not reached by --spp 2" in missed.err.strip().splitlines()[-1]


def check_max_pass_spp(r: Renders):
    run = r("--max-pass-spp", "1", "--spp", "4")
    assert [p["spp"] for p in run.report["passes"]] == [1, 2, 3, 4]
    np.testing.assert_array_equal(run.image(), r("--spp", "4").image())


def check_checkpoint_every(r: Renders):
    # written at every pass and removed once the render completes; SIGUSR1, Ctrl-C and
    # resume bit for bit: tests/test_progressive.py
    run = r("--checkpoint-every", "0.001", "--spp", "4")
    assert run.code == 0 and not Path(f"{run.output}.checkpoint.npz").exists()
    r.refused("--checkpoint-every", "1", "--frames", "2", naming="--checkpoint-every")


def check_checkpoint(r: Renders):
    r.refused("--checkpoint", str(r.folder / "c.npz"), "--frames", "2", naming="--checkpoint")
    run = r("--checkpoint", str(r.folder / "c.npz"), "--spp", "2")
    assert run.code == 0 and not (r.folder / "c.npz").exists()  # nothing asked one


def check_resume(r: Renders):
    r.refused("--resume", str(r.folder / "none.npz"), naming="none.npz")
    r.refused("--resume", str(r.folder / "none.npz"), "--frames", "2", naming="--resume")


def check_quiet(r: Renders):
    assert "wrote " in r(quiet=False).err
    assert r(quiet=True).err == ""


def check_nodes(r: Renders):
    r.refused("--scheduler", "domain", naming="--nodes N")


def check_node_timeout(r: Renders):
    r.refused("--node-timeout", "5", naming="--node-timeout")
    run = r("--nodes", "1", "--listen", f"127.0.0.1:{free_port()}", "--node-timeout", "1")
    assert run.code == 3 and "within 1 s" in run.err, run.err  # nobody came: 1 s, not 120


def check_heartbeat_timeout(r: Renders):
    r.refused("--heartbeat-timeout", "5", naming="--heartbeat-timeout")


def check_log_dir(r: Renders):
    logs = r.folder / "logs"
    r.refused("--log-dir", str(logs), naming="--log-dir")
    r.refused("--nodes", "1", "--listen", "127.0.0.1:0", "--log-dir", str(logs),
              naming="--log-dir")
    run = r("--nodes", "2", "--log-dir", str(logs), quiet=False)  # as a user runs it
    assert run.code == 0, run.err
    assert "wrote" in run.err.strip().splitlines()[-1], run.err
    assert run.counters["node_logs"] == str(logs)  # the report says where they are
    for rank in range(2):
        assert "joined" in (logs / f"node{rank}.log").read_text()
    beside = r("--nodes", "1")  # no --log-dir: kept beside --report
    kept = Path(beside.counters["node_logs"])
    assert kept.name == "r.json.nodes" and "joined" in (kept / "node0.log").read_text()


def check_listen(r: Renders):
    r.refused("--listen", "127.0.0.1:0", naming="--listen")
    port = free_port()
    run = r("--nodes", "1", "--listen", f"127.0.0.1:{port}", "--node-timeout", "1")
    assert run.code == 3 and f"tcp://127.0.0.1:{port}" in run.err, run.err  # waited there


def check_rendezvous(r: Renders):
    address = r.folder / "job.addr"
    r.refused("--nodes", "1", "--rendezvous", str(address), naming="--rendezvous")
    run = r("--nodes", "1", "--listen", "127.0.0.1:0", "--rendezvous", str(address),
            "--node-timeout", "1", quiet=False)
    assert run.code == 3 and f"(address in {address})" in run.err, run.err
    assert not address.exists()  # written for the wait, removed after


def check_keys(r: Renders):
    r.refused("--keys", str(r.folder), naming="--keys")
    beyond = ["--nodes", "1", "--listen", "0.0.0.0:0", "--node-timeout", "1"]
    no_keys = r(*beyond)
    assert no_keys.code == 2 and "--keys" in no_keys.err, no_keys.err  # loopback only
    assert main(["keys", "-o", str(r.folder / "keys")]) == 0
    keyed = r(*beyond, "--keys", str(r.folder / "keys"))
    assert keyed.code == 3 and "joined within 1 s" in keyed.err, keyed.err  # it listened


def check_assignment(r: Renders):
    r.refused("--scheduler", "image", "--assignment", "spatial", naming="--assignment")


def check_priority(r: Renders):
    r.refused("--scheduler", "image", "--priority", "queue", naming="--priority")


def check_simplified(r: Renders):
    r.refused("--scheduler", "image", "--simplified", "depth>0", naming="--simplified")


def check_portal_interval(r: Renders):
    r.refused("--portal-interval", "2", naming="--portal-interval")


def check_portal_resolution(r: Renders):
    r.refused("--portal-resolution", "8", naming="--portal-resolution")


def check_portal_threshold(r: Renders):
    r.refused("--portal-threshold", "2", naming="--portal-threshold")


def check_portal_accuracy(r: Renders):
    r.refused("--portal-accuracy", naming="--portal-accuracy")


def check_portal_memory(r: Renders):
    # what it changes (a predicting frame records): test_temporal_and_simplified_options_...
    r.refused("--portal-memory", "3", naming="--portal-memory")


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


CHECKS = {name.removeprefix("check_"): fn for name, fn in dict(globals()).items()
          if name.startswith("check_")}


def test_every_render_option_has_a_check():
    options = render_options()
    missing = sorted(set(options) - set(CHECKS))
    assert not missing, (f"options without a check in {Path(__file__).name}: {missing}; add "
                         "check_<dest> asserting what the option changes, or its refusal")
    assert not set(CHECKS) - set(options), "checks of options that no longer exist"


@pytest.mark.parametrize("option", render_options())
def test_option_changes_what_it_says_or_is_refused(option, renders):
    CHECKS[option](renders)


# -- with node processes: the effects only a distributed render shows ----------------------

@pytest.mark.slow
def test_node_options_reach_the_nodes(renders):
    tiny = ["--width", "16", "--height", "12", "--spp", "1", "--bounces", "1"]
    run = renders("--nodes", "2", "--scheduler", "async", "--cache", "2", "--heartbeat-timeout",
                  "7", "--load-bandwidth", "5,10", "--max-samples-in-flight", "64", base=tiny)
    assert run.code == 0, run.err
    c = run.counters
    assert c["nodes"] == 2 and len(c["per_node"]) == 2
    assert run.report["options"]["heartbeat_timeout_s"] == 7
    assert [n["counters"]["load_bandwidth_mb_s"] for n in c["per_node"]] == [5.0, 10.0]
    assert [n["counters"]["cache_capacity"] for n in c["per_node"]] == [2, 2]
    assert c["load_throttle_s"] > 0
    np.testing.assert_allclose(run.image(), renders.baseline.image(), rtol=1e-6, atol=1e-6)
    for scheduler in ("image", "spec-ooc"):  # sort-first tiles: the throttle reaches them too
        tiles = renders("--nodes", "2", "--scheduler", scheduler, "--cache", "2",
                        "--load-bandwidth", "5", "--max-samples-in-flight", "64", base=tiny)
        assert tiles.code == 0, tiles.err
        assert tiles.counters["load_throttle_s"] > 0
        assert all(n["counters"]["load_bandwidth_mb_s"] == 5.0
                   for n in tiles.counters["per_node"])


@pytest.mark.slow
def test_temporal_and_simplified_options_reach_the_nodes(renders):
    renders.scene.write_text(ORBIT_TOML)
    tiny = ["--width", "16", "--height", "12", "--spp", "1", "--bounces", "1"]
    run = renders("--nodes", "2", "--scheduler", "temporal", "--assignment", "spatial",
                  "--priority", "queue", base=tiny)
    assert run.code == 0, run.err
    per_node = run.counters["per_node"]
    assert {(n["counters"]["assignment"], n["counters"]["priority"]) for n in per_node} == {
        ("spatial", "queue")}
    for assignment in ("paper", "affinity", None):  # None: temporal's default, affinity
        chosen = ["--assignment", assignment] if assignment else []
        run = renders("--nodes", "2", "--scheduler", "temporal", "--frames", "2", *chosen,
                      base=tiny, quiet=False)
        assert run.code == 0, run.err
        frame1 = json.loads(run.output.with_name("r_0001.json").read_text())["counters"]
        assert {n["counters"]["assignment"] for n in frame1["per_node"]} == {
            assignment or "affinity"}
    portal = ["--nodes", "2", "--scheduler", "async", "--simplified", "portal", "--frames", "2",
              "--portal-resolution", "8"]
    frames = {}
    for name, extra in {"every": ["--portal-interval", "1"], "low": ["--portal-threshold", "-1"],
                        "high": ["--portal-threshold", "1e9"],
                        "acc": ["--portal-accuracy"],
                        "memory": ["--portal-memory", "3"]}.items():
        run = renders(*portal, *extra, base=tiny, quiet=name == "memory")
        assert run.code == 0, run.err
        frames[name] = json.loads(run.output.with_name("r_0001.json").read_text())["counters"]
    assert frames["low"]["portal_resolution"] == 8
    # frame 1 records again only with --portal-interval 1
    assert all(n["counters"]["portal_recording"] == 1 for n in frames["every"]["per_node"])
    assert all(n["counters"]["portal_recording"] == 0 for n in frames["low"]["per_node"])
    # nothing is predicted at or below -1; everything at or below 1e9
    assert frames["low"]["simplified_share"] == 0 < frames["high"]["simplified_share"]
    assert frames["acc"]["acc"] is not None and "acc" not in frames["low"]
    # with --portal-memory the predicting frame 1 records what it traces fine
    assert sum(n["counters"]["portal_records"] for n in frames["memory"]["per_node"]) > 0
    assert sum(n["counters"]["portal_records"] for n in frames["low"]["per_node"]) == 0


def test_launch_shares_the_render_options():
    """`vastray launch` takes the render options too: the checks above cover both."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    launch = {a.dest for a in sub.choices["launch"]._actions}
    assert set(render_options()) <= launch


if __name__ == "__main__":  # pragma: no cover - list the options and their checks
    for dest in render_options():
        print(dest, "->", CHECKS.get(dest, "MISSING"))
    sys.exit(subprocess.call([sys.executable, "-m", "pytest", "-q", __file__]))
