"""The logs of nodes started here: kept where asked, else removed, also after a coordinator
killed outright (the next coordinator removes its folder)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vastray.actors.node_logs import PREFIX, NodeLogs, sweep_stale

from scenes import bumpy_scene, write_store


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_folders_of_coordinators_that_are_gone_are_swept_and_others_kept(tmp_path):
    gone = tmp_path / f"{PREFIX}{_dead_pid()}-abc"
    alive = tmp_path / f"{PREFIX}{os.getpid()}-def"
    other = tmp_path / "vastray-nodes-notapid"
    for folder in (gone, alive, other):
        folder.mkdir()
        (folder / "node0.log").write_text("joined")
    assert sweep_stale(tmp_path) == [gone]
    assert not gone.exists() and alive.exists() and other.exists()


def test_kept_logs_stay_and_temporary_ones_go(tmp_path):
    kept = NodeLogs(tmp_path / "logs")
    kept.path(0).write_text("x")
    kept.close()
    assert kept.path(0).is_file() and kept.path(1, attempt=1).name == "node1.attempt2.log"
    temporary = NodeLogs()
    assert temporary.folder.name.startswith(f"{PREFIX}{os.getpid()}-")
    temporary.close()
    assert not temporary.folder.exists()


def test_a_coordinator_killed_outright_leaves_a_folder_the_next_run_removes(tmp_path):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=4)
    render = [sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o",
              str(tmp_path / "o.exr"), "--width", "64", "--height", "48", "--spp", "256",
              "--nodes", "2", "--quiet"]
    coordinator = subprocess.Popen(render)
    mine = Path(tempfile.gettempdir()).glob(f"{PREFIX}{coordinator.pid}-*")
    deadline = time.monotonic() + 60
    left = []
    while not left and time.monotonic() < deadline:
        left = [f for f in mine if any(f.glob("node*.log"))] or left
        mine = Path(tempfile.gettempdir()).glob(f"{PREFIX}{coordinator.pid}-*")
        time.sleep(0.1)
    os.kill(coordinator.pid, signal.SIGKILL)
    coordinator.wait()
    assert left and left[0].exists()  # SIGKILL: no cleanup of its own
    quick = subprocess.Popen([a if a != "256" else "1" for a in render])
    assert quick.wait(timeout=120) == 0
    assert not left[0].exists()  # the next run removed it
    assert not list(Path(tempfile.gettempdir()).glob(f"{PREFIX}{quick.pid}-*"))  # and its own
