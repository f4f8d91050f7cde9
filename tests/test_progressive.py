"""Progressive passes: pass bounds, the film after every pass the same whatever the scheduler,
the error series in the report, the stopping rules, checkpoints and resume bit for bit."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.cli import main
from vastray.render.driver import render
from vastray.render.film import Film
from vastray.render.imageio import read_image
from vastray.render.progressive import Progression, StopRules, pass_bounds
from vastray.render.scene_config import SceneConfig, load_scene_config

from scenes import POINT_AND_SKY_TOML, bumpy_scene, settings, write_store


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("progressive")
    store = write_store(root / "kd8", bumpy_scene(), kd=8)
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    return store, root / "scene.toml"


def test_pass_bounds_double_then_step_and_cover_every_sample_once():
    assert pass_bounds(1) == [(0, 1)]
    assert pass_bounds(16) == [(0, 1), (1, 2), (2, 4), (4, 8), (8, 16)]
    assert pass_bounds(40, 16) == [(0, 1), (1, 2), (2, 4), (4, 8), (8, 16), (16, 32), (32, 40)]
    assert pass_bounds(5, 1) == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]
    for spp in (1, 7, 100):
        bounds = pass_bounds(spp, 8)
        assert bounds[0][0] == 0 and bounds[-1][1] == spp
        assert all(a[1] == b[0] for a, b in zip(bounds, bounds[1:], strict=False))
    # The bounds depend on the sample numbers only: a larger spp extends, never re-cuts.
    assert pass_bounds(64)[:6] == pass_bounds(32)[:6]


class Recorder(Progression):
    """A progression that keeps the image after every pass."""

    def add_pass(self, index, pass_film, **kw):
        point = super().add_pass(index, pass_film, **kw)
        self.__dict__.setdefault("images", []).append(self.film.image().copy())
        return point


def test_the_film_after_every_pass_is_the_same_whatever_the_scheduler(scene):
    # DESIGN.md's invariance at every pass boundary: in core, out of core (spec-ooc on a
    # small cache), and on 2 nodes (async, spec-insitu): the same images pass after pass.
    store, toml = scene
    config = load_scene_config(toml)
    st = settings(width=32, height=24, spp=6)
    runs = {}
    for name in ("reference", "reference 1 thread", "spec-ooc", "spec-ooc tiles",
                 "image paced", "async", "spec-insitu", "temporal"):
        progression = Recorder(32, 24, StopRules(6, max_pass_spp=2))
        if name.startswith("reference"):
            render(store, config, st, progress=False, progression=progression,
                   threads=1 if name.endswith("thread") else None)
        elif name.startswith("spec-ooc"):
            # tiles of 500 paths run on from one pass into the next (passes of 768 and
            # 1536 paths), each pass merged when its last tile is done
            tile = 500 if name.endswith("tiles") else None
            render_out_of_core(store, config, st, JobOptions(scheduler="spec-ooc", cache=2,
                                                             max_samples_in_flight=tile),
                               progress=False, progression=progression)
        elif name == "image paced":  # a rule that may stop early: pass after pass
            progression = Recorder(32, 24, StopRules(6, max_pass_spp=2, time_limit=600))
            render_out_of_core(store, config, st, JobOptions(scheduler="image", cache=2,
                                                             max_samples_in_flight=500),
                               progress=False, progression=progression)
        else:
            render_distributed(store.path, toml, st, 2, JobOptions(scheduler=name),
                               timeout=60, progression_of=lambda frame, p=progression: p)
        runs[name] = progression
    want = runs["reference"]
    assert [p["spp"] for p in want.series] == [1, 2, 4, 6]
    assert len(want.images) == 4
    for name, progression in runs.items():
        assert len(progression.images) == 4, name
        for k, (got, ref) in enumerate(zip(progression.images, want.images, strict=False)):
            np.testing.assert_array_equal(got, ref, err_msg=f"{name}, after pass {k}")
    # The passes are sample-major: each pass's image is the whole image at fewer samples.
    assert want.film.count.min() == want.film.count.max() == 6


def test_passes_end_with_the_image_of_one_pass(scene):
    store, toml = scene
    config = load_scene_config(toml)
    st = settings(width=32, height=24, spp=8)
    whole = render(store, config, st, progress=False).film
    passes = Progression(32, 24, StopRules(8))
    film = render(store, config, st, progress=False, progression=passes).film
    np.testing.assert_array_equal(film.image(), whole.image())
    np.testing.assert_array_equal(film.count, whole.count)
    np.testing.assert_array_equal(film.depth, whole.depth)
    assert passes.stopped_by == "spp"


def test_the_variance_estimate_is_unbiased_on_known_noise():
    # Samples of known variance: the batch estimate of each channel's mean's variance
    # averages to s2 / n over pixels, that of the image mean (over pixels and three
    # independent channels) to s2 / 3 / n / P, and the confidence interval of the mean
    # covers the truth.
    rng = np.random.default_rng(1)
    film = Film(100, 50)
    pixels = np.arange(100 * 50)
    for s in range(10):
        film.add(pixels, rng.normal(2.0, 3.0, (len(pixels), 3)), sample=np.full(len(pixels), s))
    assert film.variance_of_mean().shape == (50, 100, 3)
    assert np.nanmean(film.variance_of_mean()) == pytest.approx(9.0 / 10, rel=0.05)
    assert film.variance_of_mean_radiance() == pytest.approx(3.0 / 10 / len(pixels), rel=0.1)
    one = Film(2, 1)
    one.add(np.arange(2), np.ones((2, 3)), sample=np.zeros(2, int))
    assert np.isnan(one.variance_of_mean()).all()  # one sample: no estimate


def _render(tmp: Path, store, toml, *extra: str, name: str = "run", check=True) -> dict:
    report = tmp / f"{name}.json"
    code = main(["render", str(store.path), "-o", str(tmp / f"{name}.exr"), "--scene", str(toml),
                 "--width", "32", "--height", "24", "--report", str(report), "--quiet", *extra])
    if check:
        assert code == 0
    return json.loads(report.read_text(), parse_constant=_no_constants)


def _no_constants(name):
    raise AssertionError(f"the report holds {name}: not strict JSON")


def test_report_holds_a_strict_json_series_per_pass(scene, tmp_path):
    store, toml = scene
    _render(tmp_path, store, toml, "--spp", "32", name="ref")
    report = _render(tmp_path, store, toml, "--spp", "32", "--reference",
                     str(tmp_path / "ref.exr"))
    passes = report["passes"]
    assert report["stopped_by"] == "spp"
    assert [p["spp"] for p in passes] == [1, 2, 4, 8, 16, 32]
    assert all(b["seconds"] >= a["seconds"] for a, b in zip(passes, passes[1:], strict=False))
    assert passes[0]["variance_of_mean"] is None and passes[0]["ci95"] is None
    rel = [p["rel_mse"] for p in passes]
    assert rel[0] > rel[3] > rel[4] > 0 and rel[-1] == 0  # against itself at the end
    assert passes[-1]["psnr_db"] is None  # identical images: null, never Infinity
    est = [p["estimated_rel_mse"] for p in passes[1:]]
    assert est[0] > est[-1] > 0
    lo, hi = passes[-1]["ci95"]
    assert lo < passes[-1]["mean_radiance"] < hi
    # The estimate alone tracks the measured error (against a reference of 32 spp, which is
    # not converged: compare while the run has far fewer samples than the reference).
    assert 0.3 < passes[2]["estimated_rel_mse"] / passes[2]["rel_mse"] < 3.0
    assert report["error"]["rel_mse"] == 0 and report["error"]["rel_mse_global"] == 0


def test_target_error_stops_at_the_first_pass_that_meets_it(scene, tmp_path):
    store, toml = scene
    _render(tmp_path, store, toml, "--spp", "64", name="ref")
    report = _render(tmp_path, store, toml, "--spp", "64", "--target-error", "0.05",
                     "--reference", str(tmp_path / "ref.exr"))
    rel = [p["rel_mse"] for p in report["passes"]]
    assert report["stopped_by"] == "target-error"
    assert rel[-1] <= 0.05 and all(r > 0.05 for r in rel[:-1])
    assert report["passes"][-1]["spp"] < 64
    # Without a reference the film's own estimate decides.
    alone = _render(tmp_path, store, toml, "--spp", "256", "--target-error", "0.02",
                    name="alone")
    bound = [p.get("stop_bound") for p in alone["passes"]]
    assert alone["stopped_by"] == "target-error" and alone["target_error_against"] == "estimate"
    assert bound[-1] <= 0.02 and all(b is None or b > 0.02 for b in bound[:-1])
    assert alone["stop_bound"] == bound[-1] and "Bonferroni" in alone["stop_rule"]
    assert alone["passes"][-1]["estimated_rel_mse"] < bound[-1]


def test_time_limit_stops_before_the_pass_that_would_overrun(scene, tmp_path):
    store, toml = scene
    report = _render(tmp_path, store, toml, "--spp", "100000", "--time-limit", "2")
    assert report["stopped_by"] == "time-limit"
    assert 16 <= report["passes"][-1]["spp"] < 100000
    # it stops at a pass boundary near the limit, never long after it
    assert report["passes"][-1]["seconds"] < 2 * 2.0
    capped = _render(tmp_path, store, toml, "--spp", "8", "--time-limit", "600", name="capped")
    assert capped["stopped_by"] == "spp" and capped["passes"][-1]["spp"] == 8


def test_stopping_rules_stop_nodes_too(scene, tmp_path):
    store, toml = scene
    report = _render(tmp_path, store, toml, "--spp", "256", "--target-error", "0.05",
                     "--nodes", "2", "--scheduler", "async")
    assert report["stopped_by"] == "target-error"
    assert report["passes"][-1]["spp"] < 256
    _render(tmp_path, store, toml, "--spp", str(report["passes"][-1]["spp"]),
                    name="same-spp")
    image = read_image(tmp_path / "run.exr")
    np.testing.assert_array_equal(image, read_image(tmp_path / "same-spp.exr"))


@pytest.mark.parametrize("rule, nodes", [(("--target-error", "0.05"), None),
                                         (("--target-error", "0.05"), "2"),
                                         (("--time-limit", "1"), None)])
def test_the_summary_line_says_which_rule_stopped_the_render(scene, tmp_path, capsys, rule,
                                                             nodes):
    # the stopping rules' summary line, as users see it (no --quiet; the other tests of the
    # rules pass it): which rule stopped the render and at how many samples, in one process
    # and on nodes, one line, and the report agrees
    store, toml = scene
    report = tmp_path / "run.json"
    code = main(["render", str(store.path), "-o", str(tmp_path / "run.exr"), "--scene",
                 str(toml), "--width", "32", "--height", "24", "--report", str(report),
                 "--spp", "100000" if rule[0] == "--time-limit" else "256", *rule]
                + ([] if nodes is None else ["--nodes", nodes, "--scheduler", "async"]))
    assert code == 0
    done = json.loads(report.read_text())
    printed = capsys.readouterr()
    lines = [line for line in (printed.out + printed.err).splitlines()
             if line.startswith("wrote ")]
    assert len(lines) == 1, printed
    assert done["stopped_by"] == rule[0].removeprefix("--")
    assert (f"; stopped by {rule[0]} at {done['passes'][-1]['spp']} spp" in lines[0]), lines[0]
    assert "Traceback" not in printed.err


def _cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vastray", *args], stderr=subprocess.PIPE,
                            text=True, **kw)


def _catches(pid: int, signum: int) -> bool:
    """Whether process ``pid`` has a handler for ``signum`` (Linux's /proc status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    return False


def _checkpoint_with_sigusr1(proc: subprocess.Popen, checkpoint: Path,
                             timeout: float = 120.0) -> None:
    """Wait until the render ``proc`` listens for SIGUSR1, then send it until a pass has
    finished and ``checkpoint`` is written (the render must go on meanwhile)."""
    deadline = time.monotonic() + timeout
    while not _catches(proc.pid, signal.SIGUSR1):  # until the render listens for it
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    while not checkpoint.exists():
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline
        proc.send_signal(signal.SIGUSR1)
        time.sleep(0.2)


@pytest.mark.slow
@pytest.mark.parametrize("nodes", [None, 2])
def test_interrupt_checkpoint_and_resume_give_the_uninterrupted_image(scene, tmp_path, nodes,
                                                                       capsys):
    # SIGUSR1 writes a checkpoint at once, Ctrl-C writes one and exits 130; --resume goes on
    # to the image an uninterrupted run gives, bit for bit (on one process, or 2 nodes).
    store, toml = scene
    common = [str(store.path), "--scene", str(toml), "--width", "24", "--height", "16",
              "--spp", "2048", "--max-pass-spp", "64"]
    where = ["--nodes", str(nodes), "--scheduler", "async"] if nodes else []
    assert main(["render", *common, "-o", str(tmp_path / "whole.exr"), "--quiet"]) == 0
    ckpt = tmp_path / "run.exr.checkpoint.npz"
    proc = _cli("render", *common, *where, "-o", str(tmp_path / "run.exr"), "--report",
                str(tmp_path / "run.json"), cwd=tmp_path)
    try:
        _checkpoint_with_sigusr1(proc, ckpt)
        assert proc.poll() is None  # the render goes on after a checkpoint
        first = np.load(ckpt)["count"].max()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()  # its pipe closed here, not by a later test's collection
    assert proc.returncode == 130, err
    assert "--resume" in err and str(ckpt.name) in err
    interrupted = json.loads((tmp_path / "run.json").read_text())
    assert interrupted["stopped_by"] == "interrupted"
    done = np.load(ckpt)["count"].max()
    assert first <= done < 2048
    partial = read_image(tmp_path / "run.exr")  # the image so far, written with it
    assert partial.shape == (16, 24, 3) and np.isfinite(partial).all()
    resume_where = ["--nodes", "2", "--scheduler", "spec-insitu"] if not nodes else where
    assert main(["render", *common, *resume_where, "-o", str(tmp_path / "run.exr"),
                 "--report", str(tmp_path / "run.json"), "--resume", str(ckpt)]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]  # without --quiet, as users run it
    assert last.startswith("wrote ") and "2048 spp" in last, last
    np.testing.assert_array_equal(read_image(tmp_path / "run.exr"),
                                  read_image(tmp_path / "whole.exr"))
    resumed = json.loads((tmp_path / "run.json").read_text())
    assert resumed["stopped_by"] == "spp" and resumed["passes"][-1]["spp"] == 2048
    assert resumed["passes"][0]["spp"] == 1  # the series goes on from the checkpoint's
    assert ckpt.exists()  # a checkpoint this run did not write is left to its owner


def test_resume_refuses_a_checkpoint_of_another_render(scene, tmp_path):
    store, toml = scene
    common = [str(store.path), "--scene", str(toml), "--width", "24", "--height", "16",
              "--quiet"]
    from vastray.checkpoint import write_checkpoint

    progression = Progression(24, 16, StopRules(4))
    progression.next_pass()
    progression.add_pass(0, Film(24, 16))
    ckpt = tmp_path / "a.checkpoint.npz"
    write_checkpoint(ckpt, progression, {"settings": {}})
    code = main(["render", *common, "-o", str(tmp_path / "b.exr"), "--resume", str(ckpt)])
    assert code != 0 and not (tmp_path / "b.exr").exists()
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    assert main(["render", *common, "-o", str(tmp_path / "c.exr"), "--resume",
                 str(tmp_path / "junk.npz")]) != 0
    assert not (tmp_path / "c.exr").exists()


def test_a_checkpoint_resumes_only_under_the_bvh_it_was_rendered_with(scene, tmp_path):
    """The BVH ``--bvh`` resolves to is part of a checkpoint's identity (``auto`` and the
    choice it makes are the same render); one written before ``--bvh`` existed was rendered
    with Embree's default BVH."""
    from vastray.checkpoint import read_checkpoint, render_identity, write_checkpoint
    from vastray.render.integrators import RenderSettings
    from vastray.scene.errors import InputError

    store, _ = scene
    progression = Progression(24, 16, StopRules(4))
    progression.next_pass()
    progression.add_pass(0, Film(24, 16))

    def identity(bvh: str) -> dict:
        return render_identity(store, SceneConfig(), None, RenderSettings(24, 16, bvh=bvh), 16)

    fast = tmp_path / "fast.npz"
    write_checkpoint(fast, progression, identity("fast"))
    read_checkpoint(fast, identity("fast"))
    with pytest.raises(InputError, match="rendered with the fast BVH, this render builds the "
                                         "quality one; resume with --bvh fast"):
        read_checkpoint(fast, identity("auto"))  # (a small store: auto is quality)
    old = tmp_path / "old.npz"
    write_checkpoint(old, progression, {k: v for k, v in identity("auto").items() if k != "bvh"})
    read_checkpoint(old, identity("quality"))
    read_checkpoint(old, identity("auto"))
    with pytest.raises(InputError, match="resume with --bvh quality"):
        read_checkpoint(old, identity("fast"))


def test_plot_draws_real_reports(scene, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    store, toml = scene
    _render(tmp_path, store, toml, "--spp", "32", name="ref")
    for name, extra in (("a", []), ("b", ["--cache", "2", "--scheduler", "spec-ooc"])):
        _render(tmp_path, store, toml, "--spp", "16", "--reference", str(tmp_path / "ref.exr"),
                *extra, name=name)
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "a.json"), str(tmp_path / "b.json"), "-o",
                 str(tmp_path / "c.png")]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "c.png").stat().st_size > 10_000
    assert "spec-ooc" in out and "reference" in out  # one table row per run


def test_a_node_lost_mid_passes_re_renders_only_the_passes_not_merged(scene):
    from test_distributed import _node_pids

    store, toml = scene
    st = settings(width=32, height=24, spp=128)
    hit = []

    def strike():  # node 2, once a few passes are merged
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not hit:
            if len(progression.series) >= 3 and _node_pids(2):
                for pid in _node_pids(2):
                    os.kill(pid, signal.SIGKILL)
                    hit.append(pid)
            time.sleep(0.02)

    progression = Progression(32, 24, StopRules(128))
    striker = threading.Thread(target=strike)
    striker.start()
    try:
        result = render_distributed(store.path, toml, st, 3, JobOptions(scheduler="async"),
                                    timeout=60, heartbeat_timeout=5.0,
                                    progression_of=lambda frame: progression)
    finally:
        striker.join()
    assert hit, "no node 2 to kill"
    assert result.counters["nodes"] == 2 and result.counters["node_deaths"] == {"SIGKILL": 1}
    reference = render(store, load_scene_config(toml), st, progress=False).film
    np.testing.assert_array_equal(result.film.image(), reference.image())
    np.testing.assert_array_equal(result.film.count, reference.count)
    # every pass merged once: the series goes on where the loss found it
    assert [p["spp"] for p in result.progress["passes"]] == [1, 2, 4, 8, 16, 32, 48, 64, 80,
                                                             96, 112, 128]


def test_animation_frames_have_their_own_passes_and_rules(scene, tmp_path):
    store, toml = scene
    orbit = tmp_path / "orbit.toml"
    orbit.write_text(toml.read_text() + "\n[camera.orbit]\ndegrees_per_frame = 20\n")
    for where in ([], ["--nodes", "2", "--scheduler", "async"]):
        summary = tmp_path / "s.json"
        assert main(["render", str(store.path), "--scene", str(orbit), "-o",
                     str(tmp_path / "f.exr"), "--frames", "2", "--width", "32", "--height",
                     "24", "--spp", "256", "--target-error", "0.05", "--report", str(summary),
                     "--quiet", *where]) == 0
        frames = json.loads(summary.read_text(), parse_constant=_no_constants)["frames"]
        assert [f["frame"] for f in frames] == [0, 1]
        if where:  # delivered as rendered, not after a node was taken for lost
            frame_report = json.loads((tmp_path / "s_0001.json").read_text())
            assert frame_report["counters"]["node_failures"] == []
        for frame in frames:
            bound = [p.get("stop_bound") for p in frame["passes"]]
            assert frame["stopped_by"] == "target-error", where
            assert bound[-1] <= 0.05 and all(b is None or b > 0.05 for b in bound[:-1])


def test_the_python_api_takes_the_stopping_rules(scene):
    import vastray

    store, toml = scene
    out = vastray.render(store.path, scene=toml, width=32, height=24, spp=512,
                         target_error=0.05, progress=False)
    assert out.report["stopped_by"] == "target-error"
    assert out.report["passes"][-1]["spp"] < 512
    with pytest.raises(vastray.VastrayError, match="checkpoint"):
        vastray.render(store.path, scene=toml, checkpoint_every=5, progress=False)


def test_checkpoints_are_written_when_due_and_read_back(tmp_path):
    from vastray.checkpoint import Checkpointer, read_checkpoint
    from vastray.scene.errors import InputError

    identity = {"settings": {"seed": 3}, "max_pass_spp": 16}
    images = []
    checkpoints = Checkpointer(tmp_path / "c.npz", identity, every=0.0,
                               write_image=lambda p: images.append(p.snapshot.passes_done))
    progression = Progression(4, 2, StopRules(8), on_pass=checkpoints.after_pass)
    rng = np.random.default_rng(0)
    while (step := progression.next_pass()) is not None:
        film = Film(4, 2)
        for s in range(step[1], step[2]):
            film.add(np.arange(8), rng.random((8, 3)), sample=np.full(8, s))
        progression.add_pass(step[0], film)
    checkpoints.drain()
    snap = read_checkpoint(tmp_path / "c.npz", identity)
    assert images and images[-1] == snap.passes_done == 4  # the last pass's, with its image
    np.testing.assert_array_equal(snap.film.sum, progression.film.sum)
    assert [p["spp"] for p in snap.series] == [1, 2, 4, 8]
    with pytest.raises(InputError, match="--seed"):  # another render's checkpoint
        read_checkpoint(tmp_path / "c.npz", {"settings": {"seed": 4}, "max_pass_spp": 16})
    checkpoints.finished()
    assert not (tmp_path / "c.npz").exists()  # its own file, removed once complete
    # a checkpoint that cannot be written fails the render, naming the file
    (tmp_path / "c.npz").mkdir()  # a folder where the file should go
    broken = Checkpointer(tmp_path / "c.npz", identity, every=0.0)
    progression = Progression(4, 2, StopRules(2), on_pass=broken.after_pass)
    progression.next_pass()
    progression.add_pass(0, Film(4, 2))
    with pytest.raises(InputError, match="c.npz"):
        broken.drain()


def test_without_quiet_the_last_line_says_which_rule_stopped_the_render(scene, tmp_path,
                                                                        capsys):
    # the CLI as users run it (a crash in the summary line once hid behind --quiet)
    store, toml = scene
    for where in ([], ["--nodes", "2", "--scheduler", "async"]):
        assert main(["render", str(store.path), "-o", str(tmp_path / "a.exr"), "--scene",
                     str(toml), "--width", "32", "--height", "24", "--spp", "256",
                     "--target-error", "0.05", *where]) == 0
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert last.startswith("wrote ") and "; stopped by --target-error at " in last, last
    assert main(["render", str(store.path), "-o", str(tmp_path / "b.exr"), "--scene", str(toml),
                 "--width", "32", "--height", "24", "--spp", "4"]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("wrote ") and "stopped by" not in last, last  # --spp: said by spp


def test_resume_alone_runs_the_interrupted_command_again_from_anywhere(scene, tmp_path,
                                                                          capsys):
    # Issue 42: `--resume` needed the whole command retyped, and a resume typed with fewer
    # outputs left the interrupted run's partial PNG and report beside the finished image.
    # The checkpoint keeps the command (paths made absolute); `--resume FILE` alone runs it.
    store, toml = scene
    run = tmp_path / "run"
    run.mkdir()
    common = ["--width", "16", "--height", "12", "--spp", "1024", "--max-pass-spp", "16"]
    assert main(["render", str(store.path), "--scene", str(toml), *common, "-o",
                 str(tmp_path / "whole.exr"), "--quiet"]) == 0
    # relative paths, typed in run/: the resume below is typed elsewhere
    proc = _cli("render", str(store.path), "--scene", str(toml), *common, "-o", "run.exr",
                "--png", "run.png", "--report", "run.json", cwd=run)
    ckpt = run / "run.exr.checkpoint.npz"
    try:
        _checkpoint_with_sigusr1(proc, ckpt)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()  # its pipe closed here, not by a later test's collection
    assert proc.returncode == 130, err
    assert json.loads((run / "run.json").read_text())["stopped_by"] == "interrupted"
    capsys.readouterr()
    assert main(["render", "--resume", str(ckpt)]) == 0  # from the test's folder, not run/
    err = capsys.readouterr().err
    assert f"resuming {ckpt}: vastray render {store.path}" in err, err
    np.testing.assert_array_equal(read_image(run / "run.exr"), read_image(tmp_path / "whole.exr"))
    report = json.loads((run / "run.json").read_text())  # rewritten, not left behind
    assert report["stopped_by"] == "spp" and report["passes"][-1]["spp"] == 1024
    assert (run / "run.png").stat().st_mtime >= (run / "run.exr").stat().st_mtime - 5
    # typed options go on top: a larger --spp goes further from the same checkpoint
    assert main(["render", "--resume", str(ckpt), "--spp", "2048", "--quiet"]) == 0
    assert json.loads((run / "run.json").read_text())["passes"][-1]["spp"] == 2048


def test_sigusr1_writes_the_checkpoint_on_a_thread_of_its_own(tmp_path):
    """A handler that wrote the checkpoint ran in the main thread between any two bytecodes,
    once in the middle of an import ("partially initialized module 'fractions'"), and killed
    the render: the handler only wakes a thread, which writes."""
    from vastray.checkpoint import Checkpointer

    checkpoints = Checkpointer(tmp_path / "c.npz", {})
    written_on: list[threading.Thread] = []
    checkpoints.write = lambda: written_on.append(threading.current_thread()) or True
    before = signal.getsignal(signal.SIGUSR1)
    previous = checkpoints.install_signal()
    try:
        os.kill(os.getpid(), signal.SIGUSR1)
        deadline = time.monotonic() + 60
        while not written_on and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        checkpoints.uninstall_signal(previous)
    assert written_on and written_on[0] is not threading.main_thread()
    assert signal.getsignal(signal.SIGUSR1) == before
    assert not [t for t in threading.enumerate() if t.name == "checkpoint-on-sigusr1"]


def test_passes_in_time_predicts_as_the_time_rule_rules():
    from vastray.render.progressive import passes_in_time

    # no limit: every pass after the current one
    assert passes_in_time(None, 5.0, 1.0, [1, 1, 2, 4]) == 3
    # the current pass of 2 spp at 1 s a sample takes 2 s; then 2 s (2 spp) fits 5 s, the
    # next 4 s (4 spp) does not
    assert passes_in_time(5.0, 0.5, 1.0, [2, 2, 4]) == 1
    assert passes_in_time(8.0, 0.5, 1.0, [2, 2, 4]) == 2
    # a pass that has run longer than predicted is predicted from its time so far
    assert passes_in_time(5.0, 3.0, 1.0, [2, 2, 4]) == 0
    # the first pass (no last pass's time a sample): from its own time so far
    assert passes_in_time(1.0, 0.0, None, [1, 1]) == 1
    assert passes_in_time(1.0, 0.6, None, [1, 1]) == 0  # 0.6 + 0.6 > 1


class _Clock:
    """A stand-in for ``time`` in ``vastray.render.progressive``: ``perf_counter`` reads
    ``now``."""

    def __init__(self):
        self.now = 100.0

    def perf_counter(self) -> float:
        return self.now


def test_may_grant_is_what_the_time_rule_then_grants(monkeypatch):
    """``Progression.may_grant`` (what a runtime traces ahead by) agrees with the rule that
    ``next_pass`` applies, pass by pass."""
    from vastray.render import progressive

    clock = _Clock()
    monkeypatch.setattr(progressive, "time", clock)
    progression = Progression(4, 2, StopRules(8, time_limit=10.0))  # passes 1, 1, 2, 4 spp
    assert progression.next_pass() == (0, 0, 1)
    assert progression.pass_clock() == (10.0, None)
    assert progression.may_grant(0) and progression.may_grant(1)  # nothing run yet
    clock.now += 2.0  # pass 0 has run 2 s: pass 1 would end at 4 s; in the first pass no
    # pass beyond the next is predicted
    assert [progression.may_grant(k) for k in (1, 2, 3)] == [True, False, False]
    progression.add_pass(0, Film(4, 2))
    assert progression.next_pass() == (1, 1, 2)  # granted: 2 + 2 <= 10
    budget, per_sample = progression.pass_clock()
    assert budget == pytest.approx(8.0) and per_sample == pytest.approx(2.0)
    # from the last pass's 2 s a sample: pass 1 ends 2 s in, pass 2 6 s, pass 3 14 s (> 8)
    assert progression.may_grant(2) and not progression.may_grant(3)
    clock.now += 3.0  # pass 1 runs longer: from its 3 s, pass 2 would end at 5 + 6 > 10
    assert progression.may_grant(1) and not progression.may_grant(2)
    progression.add_pass(1, Film(4, 2))
    assert progression.next_pass() is None and progression.stopped_by == "time-limit"
    assert not progression.may_grant(2)
    # without a limit every pass may be granted, whatever the time
    free = Progression(4, 2, StopRules(8))
    free.next_pass()
    clock.now += 1e6
    assert free.may_grant(3) and free.pass_clock() == (None, None)


def test_a_node_predicts_from_the_clock_each_grant_brings(monkeypatch):
    """``GrantedPasses.may_grant`` on a node: the job's clock for its first pass, then each
    grant's, read on the node's own clock from the grant's arrival."""
    from vastray.actors import node_ahead

    clock = _Clock()
    monkeypatch.setattr(node_ahead, "time", clock)
    grants = iter([(11, (5.0, 2.0)), (-1, (None, None))])
    passes = node_ahead.GrantedPasses([10, 11, 12], [(0, 1), (1, 2), (2, 4)],
                                      lambda unit, film, ahead: next(grants),
                                      clock=(10.0, None))
    assert passes.next_pass() == (0, 0, 1)
    clock.now += 3.0  # pass 0 has run 3 s of 10: pass 1 would end at 6 s, pass 2 at 12 s
    assert passes.may_grant(1) and not passes.may_grant(2)
    passes.add_pass(0, None)  # granted unit 11 with 5 s left and 2 s a sample
    assert passes.next_pass() == (1, 1, 2) and passes.clock == (5.0, 2.0)
    assert not passes.may_grant(2)  # pass 1's 1 spp, 2 s, then pass 2's 2 spp: 6 s > 5 s
    passes.add_pass(1, None)
    assert passes.next_pass() is None and passes.granted == -1
    untimed = node_ahead.GrantedPasses([0, 1, 2], [(0, 1), (1, 2), (2, 4)],
                                       lambda unit, film, ahead: (1, (None, None)))
    clock.now += 1e6
    assert untimed.may_grant(2)


def test_the_time_rule_predicts_a_pass_as_if_alone_less_what_was_traced_ahead(monkeypatch):
    """Where passes are traced partly ahead of their turn, the rule predicts a pass's work
    as if swept alone (``pass_work``: its seconds less those spent on later passes, plus
    those its own rays took before it led) and takes off what was traced of the next pass
    already. Here pass 0 ran 4 s, 3 of them on later passes (0.9 s on pass 1), under a
    4.5 s limit: pass 1 (1 spp) is predicted to end at 4 + 1 - 0.9 s and is granted; with
    nothing traced ahead (4 + 4 s) it is not."""
    from vastray.render import progressive
    from vastray.render.progressive import pass_work, passes_in_time

    assert passes_in_time(4.5, 4.0, None, [1, 1], ahead_s=3.0, traced=[0.0, 0.9]) == 1
    assert passes_in_time(4.5, 4.0, None, [1, 1], ahead_s=3.0) == 0  # 4 + 1 s
    assert passes_in_time(4.5, 4.0, None, [1, 1]) == 0  # 4 + 4 s
    # a pass whose own rays took 3 s before it led is predicted at its whole work: 4 s a
    # sample, so the next 2 spp end at 1 + 8 s
    assert passes_in_time(10.0, 1.0, None, [1, 2], traced=[3.0]) == 1
    assert passes_in_time(8.0, 1.0, None, [1, 2], traced=[3.0]) == 0
    assert pass_work({"pass_seconds": 4.0, "ahead_seconds": 3.0, "rode_seconds": 0.5}) == 1.5
    assert pass_work({"pass_seconds": 4.0}) == 4.0  # a point of passes swept alone
    clock = _Clock()
    monkeypatch.setattr(progressive, "time", clock)
    for ahead, traced, granted in ((3.0, [0.0, 0.9], True), (0.0, [], False)):
        progression = Progression(4, 2, StopRules(8, time_limit=4.5))
        progression.next_pass()
        clock.now += 4.0
        rule = {"ahead_seconds": ahead, "traced_ahead": traced}
        assert progression.may_grant(1, **rule) is granted
        point = progression.add_pass(0, Film(4, 2), **rule)
        assert point["ahead_seconds"] == ahead and point["pass_seconds"] == pytest.approx(4.0)
        assert (progression.next_pass() is not None) is granted
