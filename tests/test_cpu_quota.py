"""Nodes under a real CPU quota: a cgroup made for the test and held to half a CPU, as a
container's ``--cpus 0.5`` holds it (Linux's CFS bandwidth control). Every node reports the
seconds its quota held it back, and the CLI's last lines say so. Skipped where this process
may not make a cgroup (not root, or no writable cpu controller)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from scenes import bumpy_scene, write_store

CGROUP = Path("/sys/fs/cgroup")
QUOTA_US, PERIOD_US = 50_000, 100_000  # half a CPU


def _make_cgroup() -> tuple[Path, str]:
    """A fresh cgroup held to half a CPU: (its folder, the file to add a process to)."""
    name = f"vastray-test-{uuid.uuid4().hex[:8]}"
    for mount in ("cpu", "cpu,cpuacct"):  # cgroup v1
        if (CGROUP / mount / "cpu.cfs_quota_us").is_file():
            folder = CGROUP / mount / name
            folder.mkdir()
            (folder / "cpu.cfs_period_us").write_text(f"{PERIOD_US}\n")
            (folder / "cpu.cfs_quota_us").write_text(f"{QUOTA_US}\n")
            return folder, "cgroup.procs"
    if "cpu" in (CGROUP / "cgroup.subtree_control").read_text().split():  # cgroup v2
        folder = CGROUP / name
        folder.mkdir()
        (folder / "cpu.max").write_text(f"{QUOTA_US} {PERIOD_US}\n")
        return folder, "cgroup.procs"
    raise OSError("no cpu controller to make a cgroup under")


@pytest.fixture
def half_a_cpu():
    try:
        folder, procs = _make_cgroup()
    except OSError as exc:
        pytest.skip(f"cannot make a cgroup with a CPU quota here ({exc})")
    yield folder / procs
    deadline = time.monotonic() + 10
    while True:  # empty once the render's processes have exited
        try:
            folder.rmdir()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


@pytest.mark.timeout(300)
def test_nodes_held_by_a_cpu_quota_report_it_and_the_cli_says_so(half_a_cpu, tmp_path):
    store = write_store(tmp_path / "store", bumpy_scene(), kd=8)
    report = tmp_path / "report.json"

    render = [sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o",
              str(tmp_path / "out.exr"), "--nodes", "2", "--scheduler", "domain", "--threads",
              "1", "--width", "64", "--height", "48", "--spp", "4", "--report", str(report)]
    # the shell joins the cgroup, then becomes the CLI: the nodes it starts inherit it
    proc = subprocess.run(["sh", "-c", f'echo $$ > "{half_a_cpu}" && exec "$@"', "sh", *render],
                          capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr
    counters = json.loads(report.read_text())["counters"]
    held = [node["counters"]["cpu_throttled_s"] for node in counters["per_node"]]
    # two nodes tracing at once want two CPUs and get half of one: the quota holds them back
    assert len(held) == 2 and max(held) > 0.0, counters["per_node"]
    assert counters["cpu_throttled_s_max"] == pytest.approx(max(held), abs=1e-4)
    assert "a CPU quota throttled the nodes" in proc.stderr, proc.stderr
