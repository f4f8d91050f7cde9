"""What the README and `--help` promise a new user: runnable examples, a sample scene that
lights its own data, sample data fetched and verified, the licence and the references."""

from __future__ import annotations

import hashlib
import http.server
import os
import re
import shlex
import subprocess
import sys
import threading
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from vastray.cli import build_parser, main
from vastray.commands_data import SAMPLES, Sample, fetch_sample
from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import parse_scene_config
from vastray.scene.errors import InputError
from vastray.scene.generate import generate
from vastray.scene.store import Store

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _blocks(language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", README, flags=re.S | re.M)


def test_readme_names_no_file_a_user_lacks():
    assert "../shared" not in README.split("## Tests")[0]
    assert (ROOT / "LICENSE").read_text().startswith("BSD 3-Clause")
    for doi in ("10.2312/EGPGV/EGPGV12/061-070", "10.1109/LDAV.2018.8739224",
                "10.1109/TVCG.2022.3219982"):
        assert doi in README


def test_readme_commands_parse_with_the_real_cli():
    parser = build_parser()
    lines = [line for block in _blocks("bash")
             for line in block.replace("\\\n", " ").splitlines()]  # join continued lines
    commands = [line for line in lines if line.startswith("vastray ")]
    assert len(commands) >= 15
    for line in commands:
        words = shlex.split(line.split(" #")[0].split("&&")[0].rstrip(" &"))[1:]
        if words[:1] == ["node"]:
            continue
        parser.parse_args(words)  # raises SystemExit on an option that does not exist


def test_readme_scene_lights_its_own_data(tmp_path):
    (toml,) = _blocks("toml")
    config = parse_scene_config(toml, "README.md")
    generate("rm", tmp_path / "rm.store", 32, grid=(2, 2, 2))
    store = Store(tmp_path / "rm.store")
    config.check_objects(store.objects)
    st = RenderSettings(width=40, height=30, spp=2, integrator="pt", bounces=1, shadow_samples=2)
    film = render(store, config, st, progress=False).film
    image, hit = film.image(), film.depth_image() < np.inf
    assert hit.mean() > 0.2  # the camera sees the sheet
    assert image[hit].mean() > 0.15  # and the light reaches it: not "almost black"


@pytest.fixture
def served(tmp_path):
    """A loopback HTTP server over a folder holding one good and one corrupted file."""
    folder = tmp_path / "upstream"
    folder.mkdir()
    (folder / "good.obj").write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (folder / "bad.obj").write_bytes(b"tampered")
    handler = partial(_QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/", folder
    server.shutdown()
    server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def test_fetch_verifies_checksums_and_keeps_nothing_bad(served, tmp_path):
    url, folder = served
    good = Sample("good.obj", "unused", hashlib.sha256((folder / "good.obj").read_bytes())
                  .hexdigest(), 0, "")
    out = tmp_path / "samples"
    path, fetched = fetch_sample(good, out, base_url=url, timeout=10)
    assert fetched and path.read_bytes() == (folder / "good.obj").read_bytes()
    assert fetch_sample(good, out, base_url=url, timeout=10) == (path, False)  # kept
    bad = Sample("bad.obj", "unused", good.sha256, 0, "")
    with pytest.raises(InputError, match="checksum mismatch"):
        fetch_sample(bad, out, base_url=url, timeout=10)
    with pytest.raises(InputError, match="download failed"):
        fetch_sample(Sample("missing.obj", "", good.sha256, 0, ""), out, base_url=url, timeout=10)
    assert sorted(p.name for p in out.iterdir()) == ["good.obj"]  # no partial file left


def test_fetch_from_a_mirror_of_the_real_samples(shared_data, tmp_path, capsys):
    # The project's copies of the samples are byte-identical to their public homes.
    assert main(["data", "fetch", "-o", str(tmp_path / "s"), "--from",
                 str(shared_data / "meshes")]) == 0
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == sorted(s.name for s in SAMPLES)
    assert "checksum ok" in capsys.readouterr().err


def test_hero_image_is_what_the_first_command_renders(tmp_path, monkeypatch):
    # README: "The picture above is exactly what the first command writes to default.png".
    from PIL import Image

    monkeypatch.setenv("VASTRAY_CACHE", str(tmp_path / "cache"))
    assert "vastray render -o default.exr --png default.png" in _blocks("bash")[0]
    assert main(["render", "-o", str(tmp_path / "default.exr"), "--png",
                 str(tmp_path / "default.png"), "--quiet"]) == 0
    made = np.asarray(Image.open(tmp_path / "default.png"))
    shown = np.asarray(Image.open(ROOT / "docs" / "default.png"))
    assert made.shape == (480, 640, 3)
    # Embree picks its kernels by the CPU (SSE, AVX2, AVX-512), and their rounding differs in
    # the last bits: on another machine a handful of pixels may land one or two levels apart.
    diff = np.abs(made.astype(np.int16) - shown.astype(np.int16))
    assert diff.max() <= 2 and np.count_nonzero(diff) <= 0.0001 * diff.size


def test_fetch_offline_suggests_a_mirror_and_leaves_no_folder(tmp_path):
    # No internet: every proxy points at a closed loopback port, so each download fails at once.
    env = {**os.environ, "http_proxy": "http://127.0.0.1:9", "https_proxy": "http://127.0.0.1:9",
           "HTTP_PROXY": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9"}
    env.pop("no_proxy", None)
    env.pop("NO_PROXY", None)
    run = subprocess.run([sys.executable, "-m", "vastray", "data", "fetch", "-o", "samples"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode != 0
    last = run.stderr.strip().splitlines()[-1]
    assert SAMPLES[0].url in last and "download failed" in last and "--from DIR" in last
    assert "Traceback" not in run.stderr
    assert not (tmp_path / "samples").exists()
