"""The temporal scheduler and the simplified model on real node processes: lossless runs give
the reference image, nodes load only their own domains within their cache, and simplified
rays never travel between nodes."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render
from vastray.render.scene_config import load_scene_config
from vastray.scene.simplify import build_simplified
from vastray.scene.store import Store

from scenes import POINT_AND_SKY_TOML, bumpy_scene, settings, write_store

ORBIT_TOML = POINT_AND_SKY_TOML + """
[camera.orbit]
degrees_per_frame = 20
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("temporal")
    store = write_store(root / "grid", bumpy_scene(), grid=(3, 2, 3))
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    return store, root / "scene.toml"


@pytest.fixture(scope="module")
def reference(scene):
    store, toml = scene
    return render(store, load_scene_config(toml), settings(width=32, height=24, spp=2),
                  progress=False).film


def run(scene, nodes, **options):
    store, toml = scene
    cache = options.pop("cache", None)
    return render_distributed(store.path, toml, settings(width=32, height=24, spp=2), nodes,
                              options=JobOptions(scheduler=options.pop("scheduler", "temporal"),
                                                 cache=cache, max_samples_in_flight=400, **options),
                              timeout=60)


@pytest.mark.parametrize("nodes,cache", [(1, 1), (2, 2), (3, None), (4, 2)])
def test_temporal_gives_the_reference_image(scene, reference, nodes, cache):
    result = run(scene, nodes, cache=cache)
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(result.film.count, reference.count)
    per_node = result.counters["per_node"]
    for report in per_node:
        counters = report["counters"]
        assert counters["nonlocal_loads"] == 0  # a node loads only its own group
        assert counters["peak_resident_domains"] <= counters["cache_capacity"]
    # every domain with triangles belongs to exactly one group
    nonempty = sum(d.n_triangles > 0 for d in Store(scene[0].path).domains)
    assert sum(r["counters"]["local_domains"] for r in per_node) >= nonempty


@pytest.mark.parametrize("assignment,priority", [("sequential", "spray"),
                                                 ("spatial", "queue"),
                                                 ("paper", "queue+act"),
                                                 ("affinity", "cost-benefit"),
                                                 ("spatial", "queue+resident"),
                                                 ("fit", "cost-rate")])
def test_every_assignment_and_priority_is_lossless(scene, assignment, priority):
    # Two frames: frame 0 bootstraps (spatial groups, queue order); frame 1 plans from its
    # statistics. (Temporal with its default cost-rate: test_animation_frames_equal_...)
    from vastray.animation import frame_settings
    from vastray.render.scene_config import parse_scene_config

    store = scene[0]
    config = parse_scene_config(ORBIT_TOML, "orbit.toml")
    base = settings(width=32, height=24, spp=2)
    got = {}
    render_distributed(store.path, None, base, 2,
                       options=JobOptions(scheduler="temporal", cache=2, max_samples_in_flight=400,
                                          assignment=assignment, priority=priority), timeout=60,
                       config=config, frames=[0, 1],
                       on_frame=lambda f, r: got.setdefault(f, r.film.image()))
    lo, hi = store.bounds
    for frame in (0, 1):
        expected = render(store, config.at_frame(frame, lo, hi, base.width, base.height),
                          frame_settings(base, frame), progress=False).film.image()
        np.testing.assert_allclose(got[frame], expected, rtol=1e-6, atol=1e-6)


def test_preloading_overlaps_rendering(scene):
    result = run(scene, 2, cache=3, load_bandwidth=20.0)  # 20 MB/s: loads take time
    for report in result.counters["per_node"]:
        counters = report["counters"]
        assert counters["preloads"] > 0
        assert counters["load_wait_s"] < counters["load_s"]


def test_s_proc_times_activations_with_their_load_waits(scene):
    # S_PROC(d) is the rays of d over the seconds of its activations, the wait for its load
    # included: with slow loads (one domain cached, 2 MB/s) nearly all of a node's activation
    # time is that wait, which tracing time alone would leave out.
    result = run(scene, 2, cache=1, load_bandwidth=2.0, priority="cost-benefit")
    per_node = [report["counters"] for report in result.counters["per_node"]]
    for counters in per_node:
        assert counters["load_wait_s"] > 0
        assert counters["proc_s"] >= 0.99 * counters["load_wait_s"]
    # (one node's domains are a few kB: its waits are some 0.05 s, too near a bound to hold
    # on a busy machine; the other's, 1.3 MB at 2 MB/s, some 0.7 s)
    assert max(c["load_wait_s"] for c in per_node) > 0.25


def test_simplified_none_is_the_reference_and_identity_model_is_close(scene, reference,
                                                                       tmp_path):
    store, toml = scene
    exact = run(scene, 2, cache=2, simplified="none")
    np.testing.assert_array_equal(exact.film.image(), reference.image())
    identity = write_store(tmp_path / "identity", bumpy_scene(), grid=(3, 2, 3))
    build_simplified(identity, 1.0)  # the original triangles: only the BVH differs
    result = render_distributed(identity.path, toml, settings(width=32, height=24, spp=2), 2,
                                options=JobOptions(scheduler="async", max_samples_in_flight=400,
                                                   simplified="depth>0"), timeout=60)
    image, ref = result.film.image(), reference.image()
    rel_mse = float(np.mean((image - ref) ** 2) / np.mean(ref ** 2))
    assert rel_mse < 1e-4
    assert sum(r["counters"]["simplified_rays"] for r in result.counters["per_node"]) > 0


def test_simplified_rays_never_travel_and_policies_nest(scene, reference, tmp_path):
    store, toml = scene
    simple = write_store(tmp_path / "simple", bumpy_scene(), grid=(3, 2, 3))
    build_simplified(simple, 0.2, min_faces=50)
    sent, simplified = {}, {}
    for policy in ("none", "depth>1", "depth>0"):
        result = render_distributed(simple.path, toml, settings(width=32, height=24, spp=2), 2,
                                    options=JobOptions(scheduler="temporal", cache=2,
                                                       max_samples_in_flight=400, simplified=policy),
                                    timeout=60)
        per_node = result.counters["per_node"]
        sent[policy] = sum(r["counters"]["rays_sent"] for r in per_node)
        simplified[policy] = sum(r["counters"]["simplified_rays"] for r in per_node)
        if policy != "none":
            assert np.mean((result.film.image() - reference.image()) ** 2) > 0  # lossy
    assert simplified["none"] == 0 < simplified["depth>1"] < simplified["depth>0"]
    assert sent["depth>0"] <= sent["depth>1"] <= sent["none"]


def test_portal_policy_records_then_predicts(scene, tmp_path):
    store, toml = scene
    simple = write_store(tmp_path / "simple", bumpy_scene(), grid=(3, 2, 3))
    build_simplified(simple, 0.2, min_faces=50)
    result = render_distributed(simple.path, toml, settings(width=32, height=24, spp=2), 2,
                                options=JobOptions(scheduler="temporal", cache=2,
                                                   max_samples_in_flight=400, simplified="portal"),
                                timeout=60)
    counters = [r["counters"] for r in result.counters["per_node"]]
    assert all(c["portal_recording"] == 1 for c in counters)  # a single image records
    assert sum(c["portal_crossings"] for c in counters) > 0
    assert sum(c["portal_records"] for c in counters) > 0
    assert sum(c["predicted_low"] for c in counters) == 0  # nothing predicted while recording



@pytest.fixture(scope="module")
def simple_store(tmp_path_factory):
    store = write_store(tmp_path_factory.mktemp("simple") / "grid", bumpy_scene(),
                        grid=(3, 2, 3))
    build_simplified(store, 0.2, min_faces=50)
    return Store(store.path)


def portal_frames(store, nodes: int, scheduler: str = "temporal", cache: int | None = None,
                  frames: tuple[int, ...] = (0, 1), **options) -> dict:
    """Frames 0 (recording the portals) and 1 (predicting with them; the camera has moved),
    and any later ``frames``, of an orbit under the portal policy: {frame: result}."""
    from vastray.render.scene_config import parse_scene_config

    delivered = {}
    render_distributed(store.path, None, settings(width=32, height=24, spp=2), nodes,
                       options=JobOptions(scheduler=scheduler, cache=cache, max_samples_in_flight=400,
                                          simplified="portal", **options), timeout=60,
                       config=parse_scene_config(ORBIT_TOML, "orbit.toml"), frames=list(frames),
                       on_frame=lambda f, r: delivered.setdefault(f, r))
    return delivered


def summed(result, key: str) -> int:
    """A counter summed over a frame's nodes."""
    return sum(n["counters"].get(key, 0) for n in result.counters["per_node"])


@pytest.fixture(scope="module")
def portal_reference(simple_store):
    return portal_frames(simple_store, 2, cache=2, priority="cost-benefit")


@pytest.mark.parametrize("scheduler,nodes,cache,priority", [("temporal", 1, None, "queue"),
                                                            ("temporal", 3, 1, "spray"),
                                                            ("async", 2, 2, None)])
def test_a14_simplified_frames_do_not_depend_on_nodes_cache_or_priority(
        simple_store, portal_reference, scheduler, nodes, cache, priority):
    # The choice of model is a function of the portals and the ray only, and the portals
    # merge by MAX: every ray makes the same choice on any P, C and priority.
    got = portal_frames(simple_store, nodes, scheduler, cache,
                        **({} if priority is None else {"priority": priority}))
    assert summed(portal_reference[1], "predicted_low") > 0  # frame 1 predicts with frame 0's
    assert portal_reference[0].counters["simplified_share"] == 0.0  # a recording frame
    assert 0 < portal_reference[1].counters["simplified_share"] < 1
    for frame in (0, 1):
        want = portal_reference[frame]
        np.testing.assert_allclose(got[frame].film.image(), want.film.image(), rtol=1e-6,
                                   atol=1e-6, err_msg=f"frame {frame}")
        np.testing.assert_array_equal(got[frame].film.count, want.film.count)
        for key in ("portal_crossings", "predicted_low", "simplified_rays",
                    "simplified_shadow_rays"):
            assert summed(got[frame], key) == summed(want, key), (frame, key)
        assert got[frame].counters["simplified_share"] == want.counters["simplified_share"]


def test_acc_is_measured_in_an_instrumented_run(simple_store, portal_reference):
    # Notes §9 "ACC (reading)": the instrumented run traces every frame as a recording frame
    # (every depth-1 ray fine, so each crossing's radiance is known) and classifies its
    # crossings with the portals the timed run predicts the frame with (frame 0's here).
    timed = portal_reference
    measured = portal_frames(simple_store, 3, cache=2, portal_accuracy=True)
    assert "acc" not in measured[0].counters  # frame 0 has nothing to predict with
    counters = measured[1].counters
    crossings = summed(timed[1], "portal_crossings")
    assert summed(measured[1], "acc_crossings") == crossings > 0  # the same crossings
    assert summed(measured[1], "acc_predicted_low") == summed(timed[1], "predicted_low")
    assert counters["acc_simplified_share"] == timed[1].counters["simplified_share"]
    agree = summed(measured[1], "acc_agree")
    assert 0 <= counters["acc"] == agree / crossings <= 1
    assert (summed(measured[1], "acc_false_low") + summed(measured[1], "acc_false_high")
            == crossings - agree)
    for frame in (0, 1):  # traced as recording frames; their own portals never predict low
        assert summed(measured[frame], "predicted_low") == 0
        assert measured[frame].counters["simplified_share"] == 0.0
        assert measured[frame].counters["replay_false_low"] == 0
        assert (summed(measured[frame], "replay_crossings")
                == summed(measured[frame], "portal_crossings") > 0)
    # only frame 0 records as the timed run does, and its image is the timed run's
    assert [summed(measured[f], "portal_recording") for f in (0, 1)] == [3, 0]
    np.testing.assert_allclose(measured[0].film.image(), timed[0].film.image(), rtol=1e-6,
                               atol=1e-6)


@pytest.mark.parametrize("scheduler,nodes,cache", [("temporal", 2, 1), ("temporal", 3, 2),
                                                   ("temporal", 4, None), ("async", 2, 2)])
def test_animation_frames_equal_the_single_process_frames(scene, tmp_path, scheduler, nodes,
                                                          cache):
    from vastray.animation import frame_settings
    from vastray.render.scene_config import parse_scene_config

    store = scene[0]
    config = parse_scene_config(ORBIT_TOML, "orbit.toml")
    base = settings(width=32, height=24, spp=2)
    delivered = {}
    result = render_distributed(store.path, None, base, nodes,
                                options=JobOptions(scheduler=scheduler, cache=cache,
                                                   max_samples_in_flight=400), timeout=60,
                                config=config, frames=[0, 1, 2],
                                on_frame=lambda f, r: delivered.setdefault(f, r))
    assert sorted(delivered) == [0, 1, 2]
    assert [f["frame"] for f in result.counters["frames"]] == [0, 1, 2]
    lo, hi = store.bounds
    for frame, got in delivered.items():
        expected = render(store, config.at_frame(frame, lo, hi, base.width, base.height),
                          frame_settings(base, frame), progress=False).film
        np.testing.assert_allclose(got.film.image(), expected.image(), rtol=1e-6, atol=1e-6,
                                   err_msg=f"frame {frame}")
    if scheduler == "temporal":
        # frame 0 is planned spatially (no statistics yet); later frames by Algorithm 1
        digests = [delivered[f].counters["per_node"][0]["counters"]["assignment_digest"]
                   for f in (0, 1, 2)]
        assert digests[1] != digests[0]


def test_ray_statistics_do_not_depend_on_nodes_cache_or_priority(scene):
    # A4/A5: s(A, B) and r(A) of a lossless frame depend on the scene, camera and seed only,
    # and after the tree all-reduce every node holds the same.
    digests = set()
    for nodes, cache, priority in [(1, None, "queue"), (2, 1, "cost-benefit"), (3, 2, "spray")]:
        result = run(scene, nodes, cache=cache, priority=priority)
        per_node = [r["counters"] for r in result.counters["per_node"]]
        digests |= {c["ray_stats_digest"] for c in per_node}
        assert all(c["ray_transmissions"] > 0 for c in per_node)
    assert len(digests) == 1


@pytest.mark.parametrize("extra,message", [
    (["--nodes", "2", "--scheduler", "temporal", "--simplified"], "vastray simplify"),
    (["--nodes", "2", "--scheduler", "domain", "--simplified", "none"], "async or temporal"),
    (["--nodes", "2", "--scheduler", "async", "--priority", "queue"], "--scheduler temporal"),
    (["--scheduler", "temporal"], "--nodes"),
])
def test_temporal_options_refused_with_what_to_do(scene, tmp_path, capsys, extra, message):
    from vastray.cli import main

    out = tmp_path / "out.exr"
    assert main(["render", str(scene[0].path), "-o", str(out), "--width", "16", "--height",
                 "12", "--spp", "1", *extra]) != 0
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_cli_temporal_simplified_animation_without_quiet(tmp_path, capsys):
    # As a user runs it: two frames on two nodes, temporal scheduling and the simplified
    # model, progress and summary lines on stderr, every file written, reports that say how.
    import json

    from vastray.cli import main

    store = write_store(tmp_path / "s.store", bumpy_scene(), grid=(3, 2, 3))
    assert main(["simplify", str(store.path), "--ratio", "0.2", "--min-faces", "50"]) == 0
    toml = tmp_path / "orbit.toml"
    toml.write_text(ORBIT_TOML)
    out, report = tmp_path / "t.exr", tmp_path / "t.json"
    assert main(["render", str(store.path), "-o", str(out), "--scene", str(toml), "--frames", "2",
                 "--nodes", "2", "--scheduler", "temporal", "--cache", "2", "--simplified",
                 "--report", str(report), "--width", "32", "--height", "24", "--spp", "1"]) == 0
    err = capsys.readouterr().err
    assert "wrote 2 frames" in err and "frame 1 (2/2)" in err
    assert all((tmp_path / f"t_000{f}.exr").is_file() for f in (0, 1))
    summary = json.loads(report.read_text())
    assert summary["scheduler"] == "temporal" and summary["options"]["simplified"] == "portal"
    frame1 = json.loads((tmp_path / "t_0001.json").read_text())
    per_node = frame1["counters"]["per_node"]
    assert sum(n["counters"]["simplified_rays"] for n in per_node) > 0
    # Simple/total in every frame's report: 0 while recording, then the crossings predicted low
    frame0 = json.loads((tmp_path / "t_0000.json").read_text())
    assert frame0["counters"]["simplified_share"] == 0.0
    crossings = sum(n["counters"]["portal_crossings"] for n in per_node)
    low = sum(n["counters"]["predicted_low"] for n in per_node)
    assert frame1["counters"]["simplified_share"] == pytest.approx(low / crossings)
    assert low > 0


def test_portal_memory_accumulates_and_the_instrumented_run_follows_it(simple_store):
    # --portal-memory: frames 1 and 2 record the depth-1 rays they trace fine, so frame 2
    # predicts from frames 0 and 1. The instrumented run folds in the same crossings (those
    # its portals predict high), so it classifies frame 2 with the timed run's portals.
    frames = (0, 1, 2)
    timed = portal_frames(simple_store, 2, cache=2, frames=frames, portal_memory=4)
    paper = portal_frames(simple_store, 2, cache=2, frames=frames)
    assert summed(timed[1], "portal_records") > 0  # a predicting frame records
    assert summed(paper[1], "portal_records") == 0  # the paper's: only frame 0 records
    assert summed(timed[1], "predicted_low") == summed(paper[1], "predicted_low")
    assert summed(timed[2], "predicted_low") > summed(paper[2], "predicted_low")  # it filled
    one_node = portal_frames(simple_store, 1, frames=frames, portal_memory=4)
    assert summed(one_node[2], "predicted_low") == summed(timed[2], "predicted_low")
    measured = portal_frames(simple_store, 3, cache=2, frames=frames, portal_memory=4,
                             portal_accuracy=True)
    for frame in (1, 2):
        assert (summed(measured[frame], "acc_predicted_low")
                == summed(timed[frame], "predicted_low")), frame
        assert summed(measured[frame], "acc_crossings") == summed(timed[frame],
                                                                  "portal_crossings")
    assert (measured[2].counters["acc_unrecorded_share"]
            < measured[1].counters["acc_unrecorded_share"])


def test_cli_measures_portal_accuracy_without_quiet(tmp_path, capsys):
    # `--portal-accuracy`: the instrumented run as a user asks for it; frame 1 is classified
    # with frame 0's portals, and a frame's own portals never predict a false low (A12).
    import json

    from vastray.cli import main

    store = write_store(tmp_path / "s.store", bumpy_scene(), grid=(3, 2, 3))
    assert main(["simplify", str(store.path), "--ratio", "0.2", "--min-faces", "50"]) == 0
    toml = tmp_path / "orbit.toml"
    toml.write_text(ORBIT_TOML)
    common = ["render", str(store.path), "--scene", str(toml), "--frames", "2", "--nodes", "2",
              "--scheduler", "async", "--width", "32", "--height", "24", "--spp", "1"]
    assert main([*common, "-o", str(tmp_path / "a.exr"), "--report", str(tmp_path / "a.json"),
                 "--simplified", "--portal-accuracy", "--portal-resolution", "8"]) == 0
    assert "wrote 2 frames" in capsys.readouterr().err
    frame0 = json.loads((tmp_path / "a_0000.json").read_text())["counters"]
    frame1 = json.loads((tmp_path / "a_0001.json").read_text())["counters"]
    assert frame0["portal_resolution"] == frame1["portal_resolution"] == 8
    assert "acc" not in frame0  # nothing to predict frame 0 with
    assert 0 <= frame1["acc"] <= 1 and 0 <= frame1["acc_unrecorded_share"] <= 1
    assert frame0["replay_false_low"] == frame1["replay_false_low"] == 0
    # without the portal policy there is nothing to measure: a one-line error, no output
    assert main([*common, "-o", str(tmp_path / "b.exr"), "--simplified", "depth>1",
                 "--portal-accuracy"]) == 2
    assert "--portal-accuracy" in capsys.readouterr().err
    assert not list(tmp_path.glob("b*.exr"))
    with pytest.raises(SystemExit) as exit_:  # argparse: beyond the paper's largest portal
        main([*common, "-o", str(tmp_path / "c.exr"), "--simplified",
              "--portal-resolution", "200"])
    assert exit_.value.code == 2 and "at most 128" in capsys.readouterr().err
