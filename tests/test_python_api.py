"""The Python API, ``vastray.render``: on real stores made here it gives the CLI's image and
report, refuses with the CLI's messages, works inside a running event loop, and leaves no
node process behind when interrupted."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import vastray
from vastray.cli import main
from vastray.render.imageio import read_image

from scenes import POINT_AND_SKY_TOML, bumpy_scene, child_pids, write_store

SMALL = {"width": 32, "height": 24, "spp": 2}
SMALL_ARGS = ["--width", "32", "--height", "24", "--spp", "2"]
LIGHTS_TOML = "[[light]]" + POINT_AND_SKY_TOML.split("[[light]]", 1)[1]  # its lights only
NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "python_api.ipynb"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("api") / "s.store", bumpy_scene(), grid=(2, 2, 1))


def _cli(*argv: str) -> int:
    return main(["render", *map(str, argv), "--quiet"])


def test_render_gives_the_cli_image_and_report(store, tmp_path):
    assert _cli(store.path, "-o", tmp_path / "cli.exr", "--report", tmp_path / "cli.json",
                *SMALL_ARGS, "--cache", "2") == 0
    out = vastray.render(store.path, cache=2, progress=False, **SMALL)
    assert out.image.shape == (24, 32, 3) and out.image.dtype == np.float32
    assert out.depth.shape == (24, 32) and out.normal.shape == (24, 32, 3)
    np.testing.assert_array_equal(out.image, read_image(tmp_path / "cli.exr"))
    cli = json.loads((tmp_path / "cli.json").read_text())
    for key in ("store", "scheduler", "options", "settings"):
        assert out.report[key] == cli[key], key
    assert out.report["scheduler"] == "spec-ooc"  # auto: the cache holds half the domains
    assert set(out.report["counters"]) == set(cli["counters"])
    assert out.report["command"] == f"vastray.render({str(store.path)!r}, width=32, height=24, " \
                                    "spp=2, cache=2)"
    json.dumps(out.report, allow_nan=False)  # strict JSON, as the CLI writes it
    assert out.seconds == out.report["seconds"]["total"] > 0


def test_an_opened_store_and_a_path_give_the_same_image(store):
    by_store = vastray.render(store, progress=False, integrator="ao", **SMALL)
    by_path = vastray.render(str(store.path), progress=False, integrator="ao", **SMALL)
    np.testing.assert_array_equal(by_store.image, by_path.image)
    assert by_store.image.any()


@pytest.mark.parametrize(("kwargs", "argv"), [
    ({"integrator": "ao", "bounces": 2}, ["--integrator", "ao", "--bounces", "2"]),
    ({"ao_distance": 0.5}, ["--ao-distance", "0.5"]),
    ({"scheduler": "async"}, ["--scheduler", "async"]),
    ({"history_depth": 1}, ["--history-depth", "1"]),
    ({"scheduler": "image", "batch_size": 64}, ["--scheduler", "image", "--batch-size", "64"]),
    ({"node_timeout": 5}, ["--node-timeout", "5"]),
    ({"memory_limit": "1K"}, ["--memory-limit", "1K"]),
])
def test_refusals_are_the_clis_messages(store, tmp_path, capsys, kwargs, argv):
    assert _cli(store.path, "-o", tmp_path / "x.exr", *SMALL_ARGS, *argv) == 2
    printed = capsys.readouterr().err.strip()
    with pytest.raises(vastray.VastrayError) as refused:
        vastray.render(store.path, progress=False, **SMALL, **kwargs)
    assert printed == f"vastray render: error: {refused.value}"


def test_a_missing_store_is_refused_as_the_cli_refuses_it(tmp_path, capsys):
    assert _cli(tmp_path / "none.store", "-o", tmp_path / "x.exr") == 2
    printed = capsys.readouterr().err.strip()
    with pytest.raises(vastray.VastrayError) as refused:
        vastray.render(tmp_path / "none.store")
    assert printed == f"vastray render: error: {refused.value}"
    assert "none.store" in str(refused.value)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"spp": 0}, "spp=0: must be at least 1, got 0"),
    ({"width": 6.5}, "width=6.5: expected a whole number, got '6.5'"),
    ({"integrator": "mlt"}, "integrator='mlt': choose from ao, pt"),
    ({"no_preload": "yes"}, "no_preload must be True or False"),
    ({"cache": "150%"}, "cache='150%': percentage must be in (0, 100]"),
    ({"output": "x.exr"}, "takes no output=: the result's .image"),
    ({"quality": 3}, "unknown argument quality="),
    ({"progress": 1}, "progress must be True or False"),
    ({"camera": {"fov": 190}}, "camera: camera.fov must lie between 0 and 180"),
    ({"camera": {"eye": [0, 0, 1]}}, "unknown key(s) ['eye']"),
    ({"camera": {"position": [0, 0, 1], "look_at": [0, 0, 1]}}, "equals look_at"),
    ({"camera": [0, 0, 1]}, "camera: must be a dict"),
    ({"store": 3}, "store must be a store folder's path, a Store or None"),
    ({"reference": np.zeros((24, 32))}, "reference: must be an (H, W, 3) array"),
    ({"reference": np.zeros((8, 8, 3))}, "reference: reference is 8x8, the render is 32x24"),
])
def test_bad_arguments_are_refused_by_name(store, kwargs, message):
    kwargs = {"store": store, **SMALL, **kwargs}
    with pytest.raises(vastray.VastrayError) as refused:
        vastray.render(**kwargs)
    assert message in str(refused.value)


def test_a_camera_replaces_the_scenes_and_equals_it_in_a_scene_file(store, tmp_path):
    camera = {"position": [1.5, 2.0, 3.0], "look_at": [0.0, -0.2, 0.0], "fov": 30.0}
    lights = tmp_path / "lights.toml"
    lights.write_text("[camera]\nposition = [0, 5, 0.1]\n" + LIGHTS_TOML)
    viewed = tmp_path / "viewed.toml"
    viewed.write_text("[camera]\nposition = [1.5, 2.0, 3.0]\nlook_at = [0.0, -0.2, 0.0]\n"
                      "fov = 30.0\n" + LIGHTS_TOML)
    assert _cli(store.path, "-o", tmp_path / "v.exr", "--scene", viewed, *SMALL_ARGS) == 0
    out = vastray.render(store, scene=lights, camera=camera, progress=False, **SMALL)
    np.testing.assert_array_equal(out.image, read_image(tmp_path / "v.exr"))
    np.testing.assert_allclose(out.camera.position, camera["position"])
    default = vastray.render(store, scene=lights, progress=False, **SMALL)
    assert not np.array_equal(default.image, out.image)


def test_the_result_camera_renders_the_same_view_again(store):
    first = vastray.render(store, progress=False, **SMALL)
    again = vastray.render(store, camera=first.camera, spp=2, progress=False)  # its size too
    np.testing.assert_array_equal(again.image, first.image)
    narrow = vastray.render(store, camera=dataclasses.replace(first.camera, fov=10.0), spp=2,
                            progress=False)
    assert narrow.image.shape == first.image.shape
    assert not np.array_equal(narrow.image, first.image)


def test_reference_array_and_file_give_the_error(store, tmp_path):
    out = vastray.render(store, progress=False, **SMALL)
    out.save(tmp_path / "ref.exr")
    same = vastray.render(store, reference=out.image, progress=False, **SMALL)
    assert same.report["error"]["mse"] == 0.0 and same.report["error"]["reference"] == "<array>"
    other = vastray.render(store, reference=tmp_path / "ref.exr", seed=1, progress=False,
                           **SMALL)
    assert other.report["error"]["mse"] > 0.0
    assert other.report["error"]["reference"] == str(tmp_path / "ref.exr")


def test_save_writes_every_format_and_png_needs_its_extension(store, tmp_path):
    out = vastray.render(store, progress=False, **SMALL)
    np.testing.assert_array_equal(read_image(out.save(tmp_path / "o.exr")), out.image)
    np.testing.assert_array_equal(read_image(out.save(tmp_path / "o.pfm")), out.image)
    png = out.to_png(tmp_path / "o.png", exposure=2.0)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.srgb().shape == (24, 32, 3) and out.srgb().dtype == np.uint8
    with pytest.raises(vastray.VastrayError, match="ending in .png"):
        out.to_png(tmp_path / "o.exr")
    with pytest.raises(vastray.VastrayError, match="unknown image format"):
        out.save(tmp_path / "o.tiff")
    assert not (tmp_path / "o.tiff").exists()
    # a typo in a folder never scatters new folders about (save() once made them)
    with pytest.raises(vastray.VastrayError, match="folder .*missing does not exist"):
        out.save(tmp_path / "missing" / "o.exr")
    assert not (tmp_path / "missing").exists()
    assert "32x24, 2 spp pt" in repr(out)


def test_progress_bar_goes_to_stderr_and_progress_false_hides_it(store, capsys, monkeypatch):
    # the CLI's bar (tqdm's RenderBar), shown at once instead of after two seconds
    from vastray.render import driver
    from vastray.render.progress import RenderBar

    monkeypatch.setattr(driver, "RenderBar",
                        lambda *a, **kw: RenderBar(*a, **{**kw, "delay": 0}))
    vastray.render(store, progress=False, **SMALL)
    assert capsys.readouterr().err == ""
    vastray.render(store, **SMALL)
    err = capsys.readouterr().err
    assert "render:" in err and "path/s" in err, err


async def test_render_works_inside_a_running_event_loop(store):
    # as in a Jupyter cell: a loop runs in this thread, and nodes=1 needs asyncio.run
    asyncio.get_running_loop()
    view = {"position": [2.0, 1.0, 2.5], "fov": 30}  # reaches the node in the scene it is sent
    out = vastray.render(store, nodes=1, scheduler="image", camera=view, progress=False,
                         **SMALL)
    alone = vastray.render(store, scheduler="image", camera=view, progress=False, **SMALL)
    np.testing.assert_allclose(out.image, alone.image, rtol=1e-6, atol=1e-6)
    default = vastray.render(store, scheduler="image", progress=False, **SMALL)
    assert not np.array_equal(default.image, alone.image)
    assert len(out.report["counters"]["per_node"]) == 1
    with pytest.raises(vastray.VastrayError, match="--bounces counts"):
        vastray.render(store, integrator="ao", bounces=1)


async def test_render_async_leaves_the_loop_running(store):
    ticks = 0

    async def tick():
        nonlocal ticks
        while True:
            await asyncio.sleep(0.01)
            ticks += 1

    ticker = asyncio.ensure_future(tick())
    try:
        out = await vastray.render_async(store, progress=False, width=160, height=120, spp=8)
    finally:
        ticker.cancel()
    assert out.image.shape == (120, 160, 3) and out.image.any()
    assert ticks >= 1, "the loop stood still during the render"
    with pytest.raises(vastray.VastrayError, match="spp=0"):
        await vastray.render_async(store, spp=0)


def _node_children(pid: int) -> list[int]:
    """Live (not zombie) node processes whose parent is ``pid``."""
    found = []
    for child in child_pids(pid):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
            state = Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            continue
        if b"vastray.actors.node" in cmd and state != "Z":
            found.append(child)
    return found


LONG = {"width": 320, "height": 240, "spp": 256, "nodes": 2, "scheduler": "async",
        "progress": False}


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
async def test_cancelling_render_async_stops_its_nodes(store):
    task = asyncio.ensure_future(vastray.render_async(store, **LONG))
    deadline = time.monotonic() + 60
    while len(_node_children(os.getpid())) < 2 and time.monotonic() < deadline:
        await asyncio.sleep(0.1)
    assert len(_node_children(os.getpid())) == 2, "the render did not start two nodes"
    await asyncio.sleep(2.0)  # joined and rendering
    assert not task.done()
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert _node_children(os.getpid()) == []  # stopped before the cancellation went on


INTERRUPTED = """
import asyncio, json, os, sys
from pathlib import Path
import vastray

def live_nodes():
    found = []
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        try:  # a thread may end while it is read
            children = (task / "children").read_text().split()
        except FileNotFoundError:
            continue
        for child in children:
            try:
                state = Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[0]
            except FileNotFoundError:
                continue
            if state != "Z":
                found.append(int(child))
    return found

def run():
    try:
        vastray.render(sys.argv[1], **json.loads(sys.argv[2]))
    except KeyboardInterrupt:
        print("interrupted; live children", json.dumps(live_nodes()), flush=True)
    else:
        print("finished", flush=True)

async def in_loop():
    run()

if sys.argv[3] == "loop":  # as ipykernel runs a cell: in a loop, Ctrl-C's default handler
    asyncio.new_event_loop().run_until_complete(in_loop())
else:
    run()
"""


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("where", ["loop", "plain"])
def test_ctrl_c_stops_the_nodes_before_keyboard_interrupt_arrives(store, tmp_path, where):
    script = tmp_path / "interrupted.py"
    script.write_text(textwrap.dedent(INTERRUPTED))
    proc = subprocess.Popen([sys.executable, str(script), str(store.path), json.dumps(LONG),
                             where], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        nodes: list[int] = []
        while len(nodes) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
            nodes = _node_children(proc.pid)
        assert len(nodes) == 2, "the render did not start two nodes"
        time.sleep(2.0)  # joined and rendering
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "interrupted; live children []" in out, (out, err)
    assert not any(Path(f"/proc/{n}").exists() for n in nodes)


def notebook_script(path: Path) -> str:
    """The notebook's code cells as one script, each run inside a running event loop as
    ipykernel runs a cell."""
    notebook = json.loads(path.read_text())
    assert notebook["nbformat"] == 4
    cells = ["".join(cell["source"]) for cell in notebook["cells"]
             if cell["cell_type"] == "code"]
    return textwrap.dedent(f"""\
        import asyncio
        CELLS = {cells!r}

        async def kernel():
            namespace = {{"__name__": "__main__"}}
            for number, source in enumerate(CELLS):
                exec(compile(source, f"<cell {{number}}>", "exec"), namespace)

        asyncio.run(kernel())
        """)


@pytest.mark.slow
def test_example_notebook_runs(tmp_path):
    script = tmp_path / "notebook.py"
    script.write_text(notebook_script(NOTEBOOK))
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "(48, 64, 3) float32" in done.stdout
    assert "async 2 nodes, largest difference 0.0" in done.stdout, done.stdout
    assert "refused: --bounces counts" in done.stdout
    assert (tmp_path / "zoom.png").read_bytes()[:4] == b"\x89PNG"


def test_readme_python_example_runs(tmp_path, monkeypatch, capsys):
    import re

    from vastray.scene.generate import generate

    readme = (NOTEBOOK.parents[1] / "README.md").read_text()
    (block,) = re.findall(r"^```python\n(.*?)^```", readme, flags=re.S | re.M)
    generate("rm", tmp_path / "rm.store", 32, grid=(2, 2, 1))
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "README.md", "exec"), {"__name__": "__main__"})
    assert (tmp_path / "rm.png").read_bytes()[:4] == b"\x89PNG"
    assert "--bounces counts path-tracing bounces" in capsys.readouterr().out
