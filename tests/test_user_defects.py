"""What a new user hit (issue 42, part 4): a verbose node, an interrupted animation, an idle
node taken for lost. Real processes throughout: the CLI in subprocesses, real nodes, real
sockets and signals."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.render.imageio import read_exr

from scenes import POINT_AND_SKY_TOML, bumpy_scene, free_port, write_store

VASTRAY = [sys.executable, "-m", "vastray.cli"]
SMALL = ["--width", "32", "--height", "24", "--spp", "2", "--shadow-samples", "2"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("defects") / "s.store", bumpy_scene(),
                       grid=(2, 1, 1))


def _reap(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=60)


@pytest.mark.parametrize("flags", [["-v"], ["-vv"], ["--verbose", "-v"]])
def test_a_verbose_node_joins_and_renders(store, tmp_path, flags):
    # `vastray -v node --coordinator ...` was refused ('unrecognized arguments')
    port = free_port()
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


@pytest.fixture(scope="module")
def lit_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("uneven")
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    return write_store(root / "s.store", bumpy_scene(), kd=8), root / "scene.toml"


def _throttle(parent: int, rank: int, log: Path, seconds: float, hit: list) -> None:
    """Slow node ``rank`` (a child of ``parent``) down for ``seconds`` once it has its job
    (its ``log`` says it joined): stopped 0.8 s of every second (it still heartbeats every
    second or so), then let it run. Running 0.2 s a second keeps it above the hung node's
    5 % of a core even when other jobs take most of this machine's 2 cores (at 0.1 s a
    second it fell under it once, in CI beside a benchmark, and was taken for hung); at
    0.3 s a second it was once not slow enough, in CI's slow tests side by side: node 0
    busy 9.9 s against the others' 5.4, so they idled less than the node timeout."""
    deadline = time.monotonic() + 120
    while not hit and time.monotonic() < deadline:
        if log.exists() and "joined" in log.read_text(errors="replace"):
            hit.extend(_node_pids(parent, rank))
        time.sleep(0.05)
    end = time.monotonic() + seconds
    try:
        while hit and time.monotonic() < end:
            for pid in hit:
                os.kill(pid, signal.SIGSTOP)
            time.sleep(0.8)
            for pid in hit:
                os.kill(pid, signal.SIGCONT)
            time.sleep(0.2)
    except ProcessLookupError:
        pass
    finally:
        for pid in hit:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)


def _node_pids(parent: int, rank: int) -> list[int]:
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and b"vastray.actors.node" in cmd and b"--rank" in cmd \
                and cmd[cmd.index(b"--rank") + 1] == str(rank).encode():
            pids.append(int(proc.name))
    return pids


@pytest.mark.slow  # 45 s of idling past the node timeout by design (CI runs it)
def test_a_node_done_early_waits_idle_and_is_never_taken_for_lost(lit_store, tmp_path):
    # issue 42: a node done with its share waited for the stop with the node timeout, quit,
    # and the frame was rendered again (--node-timeout 20: 4 nodes cascaded down to 1). Here
    # node 0 is slowed for up to 40 s: nodes 1 and 2 idle
    # for far longer than --node-timeout 5, still heartbeating, and stay members. (Until
    # session 42 node 0 had the image's one tile; now each node has tiles of 4,096 paths
    # round robin, a third of the work each, and node 0's third at 0.2 of its speed takes
    # the others' twice over and more.)
    store, toml = lit_store
    common = [str(store.path), "--scene", str(toml), "--width", "64", "--height", "48",
              "--spp", "96", "--scheduler", "image"]
    proc = subprocess.Popen(
        [*VASTRAY, "render", *common, "-o", "a.exr", "--report", "a.json", "--nodes", "3",
         "--max-samples-in-flight", "4096", "--node-timeout", "5", "--heartbeat-timeout", "30"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    hit: list[int] = []
    log = tmp_path / "a.json.nodes" / "node0.log"
    slow = threading.Thread(target=_throttle, args=(proc.pid, 0, log, 40.0, hit))
    slow.start()
    try:
        _, err = proc.communicate(timeout=600)
    finally:
        slow.join()
        _reap(proc)
    assert hit, "the test found no node 0 to slow down"
    assert proc.returncode == 0, err
    assert "re-rendered" not in err and "failed" not in err, err
    counters = json.loads((tmp_path / "a.json").read_text())["counters"]
    assert counters["nodes"] == 3 and counters["node_failures"] == [], counters
    assert counters["recoveries"] == [], counters
    busy = [node["busy_s"] for node in counters["per_node"]]
    assert busy[0] > max(busy[1:]) + 5, busy  # the premise: the others idled past the timeout
    single = subprocess.run([*VASTRAY, "render", *common, "-o", "ref.exr", "--quiet"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert single.returncode == 0, single.stderr
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "ref.exr"))


@pytest.mark.parametrize("sig, status, said, nodes", [
    (signal.SIGINT, 130, "interrupted; ", []),
    (signal.SIGTERM, 143, "terminated; nodes stopped, ", []),
    (signal.SIGTERM, 143, "terminated; nodes stopped, ", ["--nodes", "2"])])
def test_an_interrupted_animation_keeps_its_finished_frames_and_names_them(
        lit_store, tmp_path, sig, status, said, nodes):
    # issue 42: Ctrl-C or SIGTERM during --frames threw every finished frame away, silently
    store, toml = lit_store
    common = [str(store.path), "--scene", str(toml), "--width", "32", "--height", "24",
              "--spp", "16", "--png", "an.png", "--report", "an.json", *nodes]
    proc = subprocess.Popen([*VASTRAY, "render", *common, "-o", "an.exr", "--frames", "40"],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    try:
        said_before = []
        for line in proc.stderr:  # the bar and a frame's line may share one (a \r between)
            said_before.append(line)
            if "(1/40)" in line:
                proc.send_signal(sig)
                break
        rest: list[str] = []  # read with a deadline: a render hung after the signal fails
        reader = threading.Thread(target=lambda: rest.append(proc.stderr.read()), daemon=True)
        reader.start()
        reader.join(300)
        err = "".join(said_before) + "".join(rest)
        assert not reader.is_alive(), f"still running 300 s after the signal: {err}"
        assert proc.wait(timeout=300) == status, err
    finally:
        _reap(proc)
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    match = re.fullmatch(rf"vastray render: {said}(\d+) of 40 frames written: (.*)", last)
    assert match, last
    count = int(match.group(1))
    numbers = "0000" if count == 1 else f"{{0000..{count - 1:04d}}}"
    assert 1 <= count < 40 and match.group(2) == ", ".join(
        f"an_{numbers}.{ext}" for ext in ("exr", "png", "json")), last
    names = sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".nodes")  # node logs
    assert names == sorted(f"an_{f:04d}.{ext}" for f in range(count)
                           for ext in ("exr", "png", "json")), names  # no temporaries
    for frame in range(count):
        assert read_exr(tmp_path / f"an_{frame:04d}.exr").shape == (24, 32, 3)
        assert json.loads((tmp_path / f"an_{frame:04d}.json").read_text())["frame"] == frame
    whole = tmp_path / "whole"
    whole.mkdir()
    once = subprocess.run([*VASTRAY, "render", *common, "-o", "an.exr", "--frames", "1",
                           "--quiet"], cwd=whole, capture_output=True, text=True, timeout=300)
    assert once.returncode == 0, once.stderr
    np.testing.assert_array_equal(read_exr(tmp_path / "an_0000.exr"),
                                  read_exr(whole / "an_0000.exr"))
