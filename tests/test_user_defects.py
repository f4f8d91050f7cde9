"""What a new user hit (issue 42, part 4): a verbose node, an interrupted animation, an idle
node taken for lost. Real processes throughout: the CLI in subprocesses, real nodes, real
sockets and signals."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from vastray.render.imageio import read_exr

from scenes import bumpy_scene, write_store

VASTRAY = [sys.executable, "-m", "vastray.cli"]
SMALL = ["--width", "32", "--height", "24", "--spp", "2", "--shadow-samples", "2"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("defects") / "s.store", bumpy_scene(),
                       grid=(2, 1, 1))


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _reap(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=60)


@pytest.mark.parametrize("flags", [["-v"], ["-vv"], ["--verbose", "-v"]])
def test_a_verbose_node_joins_and_renders(store, tmp_path, flags):
    # `vastray -v node --coordinator ...` was refused ('unrecognized arguments')
    port = _free_port()
    coordinator = subprocess.Popen(
        [*VASTRAY, "render", str(store.path), "-o", "x.exr", *SMALL, "--nodes", "1",
         "--listen", f"127.0.0.1:{port}", "--node-timeout", "60"], cwd=tmp_path,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    node = subprocess.Popen([*VASTRAY, *flags, "node", "--coordinator",
                             f"tcp://127.0.0.1:{port}", "--timeout", "60"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _, node_log = node.communicate(timeout=120)
        _, err = coordinator.communicate(timeout=120)
        assert node.returncode == 0 and b"joined" in node_log, node_log
        assert coordinator.returncode == 0, err
        assert read_exr(tmp_path / "x.exr").shape == (24, 32, 3)
    finally:
        _reap(node)
        _reap(coordinator)


def test_node_verbosity_after_node_is_accepted_too(tmp_path):
    out = subprocess.run([*VASTRAY, "node", "-v", "--help"], capture_output=True, text=True,
                         timeout=60, cwd=tmp_path)
    assert out.returncode == 0 and "--verbose" in out.stdout, out.stderr

