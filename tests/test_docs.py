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
from vastray.commands_data import SAMPLES, Sample, fetch_sample, sha256_of
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


def test_design_cites_papers_by_title_and_doi_not_by_path():
    design = (ROOT / "docs" / "DESIGN.md").read_text()
    assert "../shared" not in design and "navratil-" not in design
    assert not re.search(r"\b(spray|temporal) §", design)  # nicknames of papers
    for doi in ("10.2312/EGPGV/EGPGV12/061-070", "10.1109/LDAV.2018.8739224",
                "10.1109/TVCG.2022.3219982"):
        assert doi in design


def _help(*command: str, capsys) -> str:
    with pytest.raises(SystemExit):
        main([*command, "--help"])
    return " ".join(capsys.readouterr().out.split())  # argparse's wrapping undone


def test_help_names_no_file_a_pip_install_lacks(capsys):
    assert "reference.exr" not in _help(capsys=capsys)  # a file nothing in it makes
    assert "ironProt" not in _help("partition", capsys=capsys)
    node = _help("node", capsys=capsys)
    assert "srun vastray node --rendezvous" in node and "(see examples/" not in node
    assert "examples/slurm.sbatch)" not in _help("render", capsys=capsys)


def test_render_help_says_which_schedulers_nodes_and_samples_in_flight_serve(capsys):
    text = _help("render", capsys=capsys)
    nodes = text.split("--nodes N ")[1].split(" --node-timeout")[0]
    assert all(s in nodes for s in ("image", "spec-ooc", "async", "spec-insitu", "temporal"))
    in_flight = text.split("--max-samples-in-flight N ")[1].split(" --history-depth")[0]
    assert "every --nodes scheduler" in in_flight


def test_readme_commands_parse_with_the_real_cli():
    parser = build_parser()
    lines = [line for block in _blocks("bash")
             for line in block.replace("\\\n", " ").splitlines()]  # join continued lines
    commands = [line for line in lines if line.startswith("vastray ")]
    assert len(commands) >= 15
    for line in commands:
        words = shlex.split(line.split(" #")[0].split("&&")[0].split(" > ")[0]
                            .rstrip(" &"))[1:]
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


def test_fetch_never_replaces_an_edited_sample_without_force(tmp_path):
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    (mirror / "tri.obj").write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    sample = Sample("tri.obj", "unused", sha256_of(mirror / "tri.obj"), 0, "")
    out = tmp_path / "samples"
    path, _ = fetch_sample(sample, out, mirror=mirror)
    path.write_bytes(b"# my edits\n" + path.read_bytes())
    with pytest.raises(InputError, match="tri.obj: is in the way: it differs from the sample "
                                         r"\(edited\?\); move it, or give --force"):
        fetch_sample(sample, out, mirror=mirror)
    assert path.read_bytes().startswith(b"# my edits")  # untouched
    assert fetch_sample(sample, out, mirror=mirror, force=True) == (path, True)
    assert path.read_bytes() == (mirror / "tri.obj").read_bytes()
    assert sorted(p.name for p in out.iterdir()) == ["tri.obj"]


def test_fetch_cli_refuses_to_replace_an_edited_sample(shared_data, tmp_path, capsys):
    args = ["data", "fetch", "-o", str(tmp_path / "s"), "--from", str(shared_data / "meshes"),
            "--only", "spot.obj"]
    assert main(args) == 0
    (tmp_path / "s" / "spot.obj").write_text("# edited\n")
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "spot.obj (0.3 MB) ... failed"
    assert err[1].startswith(f"vastray data: error: {tmp_path / 's' / 'spot.obj'}: is in the way")
    assert (tmp_path / "s" / "spot.obj").read_text() == "# edited\n"
    assert main([*args, "--force"]) == 0
    assert "fetched, checksum ok" in capsys.readouterr().err


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
