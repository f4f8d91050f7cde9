"""Process facts: a child's peak memory is its own, not the peak of the process that started
it (``ru_maxrss`` keeps that across ``exec`` on Linux: a node started by a large coordinator
reported the coordinator's peak)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from vastray.processes import peak_rss_bytes, running


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux's")
def test_a_childs_peak_is_not_its_parents():
    ballast = bytearray(300_000_000)
    ballast[::4096] = b"\1" * len(ballast[::4096])  # resident, not just reserved
    child = subprocess.run([sys.executable, "-c", "from vastray.processes import "
                            "peak_rss_bytes; print(peak_rss_bytes())"],
                           capture_output=True, text=True, check=True)
    assert peak_rss_bytes() > 300_000_000  # the parent's own peak
    assert int(child.stdout) < 150_000_000, child.stdout  # the interpreter, not the ballast
    del ballast


def test_running_tells_a_live_process_from_a_finished_one():
    finished = subprocess.Popen([sys.executable, "-c", "pass"])
    finished.wait()
    assert running(os.getpid()) and not running(finished.pid)
