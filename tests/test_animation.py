"""Animations: keyframed and orbiting cameras, moving lights, per-frame seeds, `vastray render
--frames N` (numbered outputs, reports and a summary, every scheduler giving the same frames),
errors against per-frame references and `vastray plot`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions
from vastray.animation import frame_path, reference_path
from vastray.cli import main
from vastray.render.driver import render
from vastray.render.imageio import image_error, read_exr
from vastray.render.lights import PointLight, QuadLight
from vastray.render.rng import frame_seed
from vastray.render.scene_config import parse_scene_config
from vastray.scene.errors import InputError

from scenes import POINT_AND_SKY_TOML, bumpy_scene, settings, write_store

LO, HI = np.array([-3.0, -1.4, -3.0]), np.array([3.0, 1.2, 3.0])

ORBIT_TOML = """
[camera]
position = [3.0, 2.2, 4.5]
look_at = [0.0, -0.5, 0.0]
[camera.orbit]
degrees_per_frame = 40
[[light]]
type = "point"
position = [2.0, 3.0, 1.0]
intensity = 12.0
move = [-0.5, 0, 0]
[[light]]
type = "ambient"
radiance = 0.2
"""

SMALL = ["--width", "32", "--height", "24", "--spp", "1", "--shadow-samples", "1",
         "--bounces", "1"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("anim") / "s.store", bumpy_scene(),
                       grid=(2, 1, 2))


@pytest.fixture(scope="module")
def orbit_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("toml") / "orbit.toml"
    path.write_text(ORBIT_TOML)
    return path


# --- scene configuration -------------------------------------------------------------------

def test_camera_keys_interpolate_and_hold_outside():
    cfg = parse_scene_config("""
[camera]
look_at = [0, 0, 0]
fov = 30
[[camera.key]]
frame = 2
position = [0, 0, 10]
[[camera.key]]
frame = 6
position = [4, 0, 2]
fov = 50
""", "keys.toml")
    assert cfg.animated
    at = {f: cfg.at_frame(f, LO, HI, 32, 24) for f in (0, 2, 3, 4, 6, 9)}
    np.testing.assert_array_equal(at[0].camera["position"], [0, 0, 10])  # held before
    np.testing.assert_array_equal(at[2].camera["position"], [0, 0, 10])
    np.testing.assert_allclose(at[3].camera["position"], [1, 0, 8])
    np.testing.assert_allclose(at[4].camera["position"], [2, 0, 6])
    np.testing.assert_array_equal(at[9].camera["position"], [4, 0, 2])  # held after
    assert at[0].camera["fov"] == 50 and at[6].camera["fov"] == 50  # one key: constant
    np.testing.assert_array_equal(at[4].camera["look_at"], [0, 0, 0])  # [camera] kept
    assert not at[4].animated and at[4].frame == 4
    np.testing.assert_array_equal(cfg.camera["position"], [0, 0, 10])  # the config: frame 0


def test_orbit_turns_the_camera_about_its_axis():
    cfg = parse_scene_config("""
[camera]
position = [1, 0, 0]
look_at = [0, 0, 0]
[camera.orbit]
degrees_per_frame = 90
""", "orbit.toml")
    expected = {0: [1, 0, 0], 1: [0, 0, -1], 2: [-1, 0, 0], 3: [0, 0, 1], 4: [1, 0, 0]}
    for frame, position in expected.items():
        camera = cfg.at_frame(frame, LO, HI, 32, 24).camera
        np.testing.assert_allclose(camera["position"], position, atol=1e-12)
        np.testing.assert_array_equal(camera["look_at"], [0, 0, 0])
        np.testing.assert_allclose(camera["up"], [0, 1, 0], atol=1e-12)  # the axis: kept
    tilted = parse_scene_config("""
[camera]
position = [2, 1, 1]
look_at = [0, 0, 0]
up = [0, 0, 1]
[camera.orbit]
degrees_per_frame = 45
axis = [0, 0, 2]
center = [1, 1, 0]
""", "orbit.toml").at_frame(2, LO, HI, 32, 24)  # 90 degrees about z through (1, 1, 0)
    np.testing.assert_allclose(tilted.camera["position"], [1, 2, 1], atol=1e-12)
    np.testing.assert_allclose(tilted.camera["up"], [0, 0, 1], atol=1e-12)


def test_an_orbit_of_more_than_a_turn_a_frame_is_refused():
    """1e308 degrees a frame once overflowed to NaN cameras and a flat sky, exit 0."""
    for degrees in ("1e308", "-361"):
        with pytest.raises(InputError, match=r"^orbit.toml: \[camera.orbit\].degrees_per_frame "
                                             r"must be within -360..360"):
            parse_scene_config(f"[camera.orbit]\ndegrees_per_frame = {degrees}\n", "orbit.toml")
    parse_scene_config("[camera.orbit]\ndegrees_per_frame = -360\n", "orbit.toml")


def test_orbit_of_the_default_camera_circles_the_scene():
    cfg = parse_scene_config("[camera.orbit]\ndegrees_per_frame = 30\n", "orbit.toml")
    still = parse_scene_config("", "orbit.toml")
    base = still.resolve_camera(LO, HI, 32, 24)
    center = (LO + HI) / 2
    for frame in (0, 3, 7):
        camera = cfg.at_frame(frame, LO, HI, 32, 24).resolve_camera(LO, HI, 32, 24)
        np.testing.assert_allclose(np.linalg.norm(camera.position - center),
                                   np.linalg.norm(base.position - center))
        assert camera.position[1] == pytest.approx(base.position[1])  # about +y
    np.testing.assert_allclose(cfg.at_frame(0, LO, HI, 32, 24).camera["position"],
                               base.position)


def test_lights_move_by_keys_and_by_move():
    cfg = parse_scene_config("""
[[light]]
type = "point"
position = [0, 2, 0]
intensity = 5
move = [0.5, 0, -1]
[[light]]
type = "quad"
edge1 = [1, 0, 0]
edge2 = [0, 0, 1]
radiance = 3
[[light.key]]
frame = 0
corner = [0, 4, 0]
[[light.key]]
frame = 10
corner = [10, 4, 0]
edge1 = [2, 0, 0]
[[light]]
type = "directional"
direction = [0, -1, 0]
irradiance = 1
""", "lights.toml")
    assert cfg.animated
    point, quad, sun = cfg.at_frame(4, LO, HI, 32, 24).lights
    assert isinstance(point, PointLight) and isinstance(quad, QuadLight)
    np.testing.assert_allclose(point.position, [2, 2, -4])
    np.testing.assert_allclose(quad.corner, [4, 4, 0])
    np.testing.assert_allclose(quad.edge1, [2, 0, 0])  # one key: held
    assert sun is cfg.lights[2]  # not animated: the same light
    np.testing.assert_array_equal(cfg.lights[1].corner, [0, 4, 0])  # the config: frame 0
    np.testing.assert_allclose(cfg.at_frame(30, LO, HI, 32, 24).lights[1].corner, [10, 4, 0])


def test_frame_zero_of_a_static_config_is_the_config():
    cfg = parse_scene_config(POINT_AND_SKY_TOML, "static.toml")
    assert not cfg.animated
    for frame in (0, 5):
        at = cfg.at_frame(frame, LO, HI, 32, 24)
        assert at.frame == frame and not at.animated
        assert at.camera.keys() == cfg.camera.keys()
        for key in cfg.camera:
            np.testing.assert_array_equal(at.camera[key], cfg.camera[key])
        assert at.lights == cfg.lights or all(a is b for a, b in zip(at.lights, cfg.lights,
                                                                      strict=True))
        assert (at.text, at.source) == (cfg.text, cfg.source)
    default = parse_scene_config("", "empty.toml").at_frame(0, LO, HI, 32, 24)
    assert default.camera == {} and default.lights is None


@pytest.mark.parametrize("toml, message", [
    ("[[camera.key]]\nposition = [1, 2, 3]\n", r"\[\[camera.key\]\] #1 needs `frame = N`"),
    ("[[camera.key]]\nframe = 3\nposition = [1, 2, 3]\n[[camera.key]]\nframe = 3\n"
     "position = [1, 2, 4]\n", r"#2: frames must increase"),
    ("[[camera.key]]\nframe = 0\nzoom = 2\n", r"#1: unknown key\(s\) \['zoom'\]"),
    ("[[camera.key]]\nframe = 0\n", r"#1 sets nothing"),
    ("[[camera.key]]\nframe = 0\nfov = 200\n", r"fov must lie between"),
    ("[[camera.key]]\nframe = 1.5\nfov = 20\n", r"needs `frame = N`"),
    ("[camera.orbit]\naxis = [0, 0, 0]\n", r"\[camera.orbit\].axis must not be zero"),
    ("[camera.orbit]\nspeed = 3\n", r"unknown key"),
    ("[camera.orbit]\n[[camera.key]]\nframe = 0\nfov = 20\n", r"both"),
    ('[[light]]\ntype = "ambient"\nradiance = 1\nmove = [1, 0, 0]\n', r"#1: move translates"),
    ('[[light]]\ntype = "point"\nintensity = 1\n[[light.key]]\nframe = 0\nintensity = 2\n',
     r"#1 \[\[light.key\]\] #1: unknown key"),
    ('[[light]]\ntype = "point"\nintensity = 1\n', r"needs \['position'\]"),
])
def test_bad_keys_name_the_file_and_the_key(toml, message):
    with pytest.raises(InputError, match=message) as err:
        parse_scene_config(toml, "bad.toml")
    assert str(err.value).startswith("bad.toml: ")


def test_a_degenerate_frame_names_its_frame():
    cfg = parse_scene_config("""
[[light]]
type = "directional"
irradiance = 1
[[light.key]]
frame = 0
direction = [0, -1, 0]
[[light.key]]
frame = 2
direction = [0, 1, 0]
""", "flip.toml")  # passes through a zero direction at frame 1
    cfg.at_frame(0, LO, HI, 8, 8)
    with pytest.raises(InputError, match=r"flip.toml: \[\[light\]\] #1 at frame 1.direction"):
        cfg.at_frame(1, LO, HI, 8, 8)


def test_frame_seed_is_deterministic_and_differs_per_frame():
    seeds = [frame_seed(7, f) for f in range(100)]
    assert seeds == [frame_seed(7, f) for f in range(100)]
    assert len(set(seeds)) == 100 and all(0 <= s < 2 ** 63 for s in seeds)
    assert frame_seed(8, 0) != frame_seed(7, 0) and frame_seed(0, 0) != 0
    assert frame_seed(2 ** 64 - 1, 10 ** 9) < 2 ** 63
    with pytest.raises(ValueError):
        frame_seed(0, -1)


def test_names_of_frames_and_references(tmp_path):
    assert frame_path("out/anim.exr", 7).as_posix() == "out/anim_0007.exr"
    assert frame_path("anim.exr", 12345).name == "anim_12345.exr"
    assert reference_path("ref_{frame:03d}.exr", 5).name == "ref_005.exr"
    assert reference_path("ref.exr", 5).name == "ref_0005.exr"
    with pytest.raises(InputError, match="pattern"):
        reference_path("ref_{name}.exr", 5)


# --- the command line ----------------------------------------------------------------------

def test_frames_write_numbered_outputs_reports_and_a_summary(store, orbit_toml, tmp_path,
                                                              capsys):
    out, png, report = tmp_path / "x.exr", tmp_path / "x.png", tmp_path / "r.json"
    assert main(["render", str(store.path), "-o", str(out), "--png", str(png), "--report",
                 str(report), "--scene", str(orbit_toml), "--frames", "3", "--seed", "5",
                 *SMALL]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert [line.split(" (")[0] for line in err if line.startswith("frame ")] == \
        ["frame 0", "frame 1", "frame 2"]
    last = err[-1]
    assert last.startswith("wrote 3 frames: ") and f"{tmp_path}/x_{{0000..0002}}.exr" in last
    assert "s per frame" in last and f"summary {report}" in last
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["r.json", "r_0000.json", "r_0001.json", "r_0002.json", "x_0000.exr",
                     "x_0000.png", "x_0001.exr", "x_0001.png", "x_0002.exr", "x_0002.png"]
    frames = [read_exr(frame_path(out, f)) for f in range(3)]
    for a, b in ((0, 1), (1, 2), (0, 2)):
        assert np.abs(frames[a] - frames[b]).mean() > 1e-3, "the orbit moves the camera"
    summary = json.loads(report.read_text())
    assert summary["scheduler"] == "reference" and summary["animation"]["frames"] == 3
    assert [e["frame"] for e in summary["frames"]] == [0, 1, 2]
    assert [e["seed"] for e in summary["frames"]] == [frame_seed(5, f) for f in range(3)]
    total = sum(e["seconds"]["total"] for e in summary["frames"])
    assert summary["totals"]["seconds"] == pytest.approx(total, abs=1e-3)
    assert summary["means"]["seconds_per_frame"] == pytest.approx(total / 3, abs=1e-3)
    assert summary["totals"]["loads"] == sum(e["loads"] for e in summary["frames"])
    one = json.loads((tmp_path / "r_0001.json").read_text())
    assert one["frame"] == 1 and one["settings"]["seed"] == frame_seed(5, 1)
    assert one["options"]["frames"] == 3 and "error" not in one


def test_a_frame_is_the_render_of_its_camera_and_seed(store, orbit_toml, tmp_path):
    out = tmp_path / "o.exr"
    assert main(["render", str(store.path), "-o", str(out), "--scene", str(orbit_toml),
                 "--first-frame", "2", "--frames", "1", "--seed", "3", "--quiet", *SMALL]) == 0
    assert not out.exists() and frame_path(out, 2).exists()
    cfg = parse_scene_config(ORBIT_TOML, orbit_toml).at_frame(2, *store.bounds, 32, 24)
    st = settings(width=32, height=24, spp=1, shadow_samples=1, bounces=1,
                  seed=frame_seed(3, 2))
    expected = render(store, cfg, st, progress=False).film.image()
    np.testing.assert_array_equal(read_exr(frame_path(out, 2)), expected.astype(np.float32))
    # The same camera and light written out as a static SCENE.toml, rendered with that seed.
    static = tmp_path / "static.toml"
    static.write_text("[camera]\n" + "".join(f"{k} = {np.asarray(v).tolist()}\n"
                                             for k, v in cfg.camera.items())
                      + '[[light]]\ntype = "point"\nposition = [1.0, 3.0, 1.0]\n'
                        'intensity = 12.0\n[[light]]\ntype = "ambient"\nradiance = 0.2\n')
    single = tmp_path / "single.exr"
    assert main(["render", str(store.path), "-o", str(single), "--scene", str(static),
                 "--seed", str(frame_seed(3, 2)), "--quiet", *SMALL]) == 0
    np.testing.assert_array_equal(read_exr(single), read_exr(frame_path(out, 2)))


def test_image_and_reference_schedulers_give_the_same_frames(store, orbit_toml, tmp_path):
    for scheduler in ("reference", "image"):
        assert main(["render", str(store.path), "-o", str(tmp_path / f"{scheduler}.exr"),
                     "--scene", str(orbit_toml), "--frames", "2", "--scheduler", scheduler,
                     "--cache", "2", "--quiet", *SMALL]) == 0
    for frame in (0, 1):
        np.testing.assert_allclose(read_exr(tmp_path / f"image_{frame:04d}.exr"),
                                   read_exr(tmp_path / f"reference_{frame:04d}.exr"), atol=1e-6)


def test_nodes_give_the_single_process_frames(store, orbit_toml, tmp_path):
    single, nodes = tmp_path / "single.exr", tmp_path / "nodes.exr"
    common = ["--scene", str(orbit_toml), "--frames", "2", "--first-frame", "1", "--quiet",
              *SMALL]
    assert main(["render", str(store.path), "-o", str(single), *common]) == 0
    assert main(["render", str(store.path), "-o", str(nodes), "--nodes", "2", "--scheduler",
                 "async", "--report", str(tmp_path / "nodes.json"), *common]) == 0
    for frame in (1, 2):
        np.testing.assert_allclose(read_exr(frame_path(nodes, frame)),
                                   read_exr(frame_path(single, frame)), atol=1e-6)
    summary = json.loads((tmp_path / "nodes.json").read_text())
    assert summary["scheduler"] == "async" and summary["options"]["nodes"] == 2


def test_nodes_frames_without_quiet_say_each_frame_and_the_summary(store, orbit_toml,
                                                                   tmp_path):
    # The CLI as users run it (no --quiet) on the paths the tests above take quietly: a
    # first frame other than 0, a bound on the samples in flight and a node timeout.
    import subprocess
    import sys

    single = tmp_path / "single.exr"
    common = ["--scene", str(orbit_toml), "--frames", "2", "--first-frame", "1", *SMALL]
    assert main(["render", str(store.path), "-o", str(single), "--quiet", *common]) == 0
    out = subprocess.run([sys.executable, "-m", "vastray.cli", "render", str(store.path),
                          "-o", "a.exr", "--report", "a.json", "--nodes", "2", "--scheduler",
                          "async", "--max-samples-in-flight", "64", "--node-timeout", "30",
                          *common], cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    assert "frame 1 (1/2): " in out.stderr and "frame 2 (2/2): " in out.stderr, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("wrote 2 frames: a_{0001..0002}.exr, a_{0001..0002}.json, "
                           "summary a.json (32x24"), last
    for frame in (1, 2):
        np.testing.assert_allclose(read_exr(frame_path(tmp_path / "a.exr", frame)),
                                   read_exr(frame_path(single, frame)), atol=1e-6)


def test_a_slow_frame_write_does_not_silence_the_coordinator(store, orbit_toml):
    # Writing a frame (a 4K EXR and PNG take seconds) must not stop the coordinator's
    # heartbeats: nodes hearing nothing for COORDINATOR_SILENCE_S exit, and frames were then
    # rendered again on fewer nodes. Here frame 0's callback takes a second longer than
    # that while the nodes render frame 1, and frame 1's while they wait for the stop.
    import time

    from vastray.actors import protocol
    from vastray.actors.coordinator import render_distributed
    from vastray.render.scene_config import load_scene_config

    seen = []

    def on_frame(frame, result):
        time.sleep(protocol.COORDINATOR_SILENCE_S + 1.0)
        seen.append(frame)

    result = render_distributed(store.path, None, settings(width=32, height=24, spp=16), 2,
                                options=JobOptions(scheduler="async", max_samples_in_flight=200),
                                config=load_scene_config(orbit_toml), frames=[0, 1],
                                on_frame=on_frame, timeout=60)
    assert seen == [0, 1]  # every frame, in order
    assert result.counters["node_failures"] == [] and result.counters["nodes"] == 2


def test_reference_pattern_gives_error_per_frame(store, orbit_toml, tmp_path, capsys):
    ref = tmp_path / "ref.exr"
    common = [str(store.path), "--scene", str(orbit_toml), "--frames", "2", *SMALL]
    assert main(["render", "-o", str(ref), *common, "--quiet", "--spp", "4"]) == 0
    report = tmp_path / "run.json"
    assert main(["render", "-o", str(tmp_path / "run.exr"), *common, "--report", str(report),
                 "--reference", str(tmp_path / "ref_{frame:04d}.exr")]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "mean MSE" in last and "PSNR" in last
    summary = json.loads(report.read_text())
    for entry in summary["frames"]:
        error = entry["error"]
        assert error["mse"] > 0 and error["rel_mse"] > 0 and np.isfinite(error["psnr_db"])
        image = read_exr(tmp_path / f"run_{entry['frame']:04d}.exr")
        reference = read_exr(tmp_path / f"ref_{entry['frame']:04d}.exr")
        assert error["rel_mse_global"] == pytest.approx(
            error["mse"] / np.mean(reference.astype(np.float64) ** 2))
        assert error["rel_mse"] == pytest.approx(np.mean(
            (image.astype(np.float64) - reference) ** 2 / (reference.astype(np.float64) ** 2
                                                           + 1e-2)))
        assert error == dict(image_error(image, reference), reference=error["reference"])
    assert summary["means"]["mse"] == pytest.approx(
        np.mean([e["error"]["mse"] for e in summary["frames"]]))
    assert [p["frame"] for p in summary["error_vs_time"]] == [0, 1]
    frame = json.loads((tmp_path / "run_0001.json").read_text())
    assert frame["error"]["rel_mse"] == summary["frames"][1]["error"]["rel_mse"]
    # a plain path means ref_NNNN.exr
    assert main(["render", "-o", str(tmp_path / "plain.exr"), *common, "--quiet",
                 "--reference", str(ref), "--report", str(tmp_path / "plain.json")]) == 0
    plain = json.loads((tmp_path / "plain.json").read_text())
    assert [e["error"]["mse"] for e in plain["frames"]] == \
        [e["error"]["mse"] for e in summary["frames"]]


@pytest.mark.parametrize("case", ["missing_reference", "frame_in_the_way", "bad_pattern",
                                  "degenerate_frame"])
def test_every_frame_is_checked_before_rendering(store, orbit_toml, tmp_path_factory, capsys,
                                                 case):
    tmp_path = tmp_path_factory.mktemp("out")
    out = tmp_path / "a.exr"
    args = ["render", str(store.path), "-o", str(out), "--scene", str(orbit_toml),
            "--frames", "3", "--report", str(tmp_path / "a.json"), "--quiet", *SMALL]
    expect = "nope_0000.exr: image not found"
    if case == "missing_reference":
        args += ["--reference", str(tmp_path / "nope.exr")]
    elif case == "frame_in_the_way":
        (tmp_path / "a_0002.exr").mkdir()  # the third frame's image is a folder
        expect = "a_0002.exr: -o is a folder"
    elif case == "bad_pattern":
        args += ["--reference", str(tmp_path / "r_{frame:q}.exr")]
        expect = "not a pattern with a {frame} field"
    else:  # the camera passes through its target at frame 1
        scene = tmp_path_factory.mktemp("scene") / "through.toml"
        scene.write_text("[camera]\nlook_at = [0, 0, 0]\n[[camera.key]]\nframe = 0\n"
                         "position = [0, 0, 2]\n[[camera.key]]\nframe = 2\n"
                         "position = [0, 0, -2]\n")
        args[args.index("--scene") + 1] = str(scene)
        expect = f"{scene}: frame 1: [camera] position [0.0, 0.0, 0.0] equals look_at"
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray render: error:") and len(err.splitlines()) == 1, err
    assert expect in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == (
        ["a_0002.exr"] if case == "frame_in_the_way" else [])


def test_plot_draws_error_vs_time_of_runs(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="vastray[plot] (matplotlib) is not installed")

    def summary(scheduler, options, mse):
        return {"scheduler": scheduler, "options": options, "settings": {"spp": 2},
                "frames": [{"frame": f, "seconds": {"total": 0.5 + 0.1 * f},
                            "error": {"mse": m, "psnr_db": None, "rel_mse": m}}
                           for f, m in enumerate(mse)]}

    runs = {"lossless.json": summary("image", {"nodes": None, "cache": 2}, [0.0, 0.0]),
            "lossy.json": summary("temporal", {"nodes": 4, "simplified": "portal"},
                                  [1e-3, 2e-3]),
            "single.json": {"scheduler": "reference", "seconds": {"total": 2.0},
                            "error": {"mse": 1e-4}}}
    for name, doc in runs.items():
        (tmp_path / name).write_text(json.dumps(doc))
    out = tmp_path / "error_vs_time.png"
    assert main(["plot", *(str(tmp_path / n) for n in runs), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "3 runs, 5 points" in capsys.readouterr().err
    from vastray.plot import load_series

    assert load_series(tmp_path / "lossy.json").label == \
        "temporal --spp 2 --nodes 4 --simplified portal"
    (tmp_path / "none.json").write_text(json.dumps({"scheduler": "image", "seconds": {}}))
    assert main(["plot", str(tmp_path / "none.json"), "-o", str(tmp_path / "n.png")]) == 2
    assert "render with --reference" in capsys.readouterr().err
    assert not (tmp_path / "n.png").exists()


def test_plot_of_real_reports(store, orbit_toml, tmp_path):
    pytest.importorskip("matplotlib", reason="vastray[plot] (matplotlib) is not installed")
    common = [str(store.path), "--scene", str(orbit_toml), "--frames", "2", "--quiet", *SMALL]
    assert main(["render", "-o", str(tmp_path / "ref.exr"), *common, "--spp", "4"]) == 0
    for name, extra in (("a", []), ("b", ["--scheduler", "image", "--cache", "2"])):
        assert main(["render", "-o", str(tmp_path / f"{name}.exr"), *common, *extra,
                     "--reference", str(tmp_path / "ref.exr"),
                     "--report", str(tmp_path / f"{name}.json")]) == 0
    # a single render's report (not --frames) plots as one point
    assert main(["render", "-o", str(tmp_path / "c.exr"), str(store.path), "--quiet", *SMALL,
                 "--reference", str(tmp_path / "ref_0000.exr"), "--report",
                 str(tmp_path / "c.json")]) == 0
    out = tmp_path / "plot.png"
    assert main(["plot", *(str(tmp_path / f"{n}.json") for n in "abc"), "-o", str(out),
                 "--title", "test"]) == 0
    assert out.stat().st_size > 1000


def test_settings_seed_of_frames_leaves_the_default_run_alone(store, tmp_path):
    # Without --frames, nothing is numbered and the seed is the one given.
    out = tmp_path / "one.exr"
    assert main(["render", str(store.path), "-o", str(out), "--seed", "4", "--quiet",
                 *SMALL]) == 0
    st = settings(width=32, height=24, spp=1, shadow_samples=1, bounces=1, seed=4)
    cfg = parse_scene_config("", "none")
    expected = render(store, cfg, st, progress=False).film.image()
    np.testing.assert_array_equal(read_exr(out), expected.astype(np.float32))


def test_an_in_core_animation_loads_each_domain_once(store, orbit_toml, tmp_path):
    """The domain cache is kept over the frames: a domain that fits is loaded once, not once
    per frame (each frame's report counts its own loads)."""
    report = tmp_path / "r.json"
    assert main(["render", str(store.path), "-o", str(tmp_path / "x.exr"), "--report",
                 str(report), "--scene", str(orbit_toml), "--frames", "4", *SMALL]) == 0
    summary = json.loads(report.read_text())
    loads = [e["loads"] for e in summary["frames"]]
    assert loads[0] > 0
    assert summary["totals"]["loads"] <= len(store.domains), loads  # was 4 per frame


def test_plot_labels_tell_simplified_variants_apart():
    from vastray.report import run_label

    def label(**options):
        return run_label({"scheduler": "temporal", "settings": {"spp": 4},
                          "options": {"nodes": 4, "portal_threshold": 0.5,
                                      "portal_resolution": 32, "portal_interval": 10,
                                      **options}})

    variants = [label(), label(simplified="portal"), label(simplified="depth>1"),
                label(simplified="portal", portal_threshold=0.25),
                label(simplified="portal", portal_resolution=8),
                label(simplified="portal", priority="queue"),
                label(simplified="portal", assignment="spatial")]
    assert len(set(variants)) == len(variants), variants
    assert variants[3] == "temporal --spp 4 --nodes 4 --simplified portal --portal-threshold 0.25"


def test_frames_rendered_again_say_how_many_files_they_replaced(store, orbit_toml, tmp_path,
                                                                capsys):
    args = ["render", str(store.path), "-o", str(tmp_path / "x.exr"), "--report",
            str(tmp_path / "r.json"), "--scene", str(orbit_toml), "--frames", "2",
            *[a for a in SMALL if a != "--quiet"]]
    assert main(args) == 0
    assert "replaced" not in capsys.readouterr().err
    assert main(args) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.endswith("; replaced 5 existing files"), last  # 2 images, 2 reports, summary
