"""SIGUSR1 asks a render for a checkpoint; sent in a render's first moments, before the
checkpoints' handler is installed, it must change nothing (issue 37: SIGUSR1 in the first 0.3 s
killed the render, rc 138). The installed console script is run as users run it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.render.imageio import read_image

#: The console script pip installed (not a shell wrapper in front of it, such as pyenv's
#: shims: a shell dies of SIGUSR1 before the script runs at all).
SCRIPT = Path(sysconfig.get_path("scripts")) / "vastray"

RENDER = ["render", "-o", "x.exr", "--width", "32", "--height", "24", "--spp", "4", "--quiet"]

#: Runs the console script with a SIGUSR1 to itself at every project module it loads but the
#: first two (the package and ``vastray.cli``, the module the script imports first).
SIGNAL_AT_EACH_IMPORT = """
import os, runpy, signal, sys

def hook(event, args):
    if event == "import" and args[0].startswith("vastray.") and args[0] != "vastray.cli":
        os.kill(os.getpid(), signal.SIGUSR1)

sys.addaudithook(hook)
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""

pytestmark = pytest.mark.skipif(not SCRIPT.exists(), reason=f"no console script at {SCRIPT}")


def _assert_rendered(folder: Path, err: str) -> None:
    image = read_image(folder / "x.exr")
    assert image.shape == (24, 32, 3) and np.isfinite(image).all() and image.max() > 0, err
    assert not list(folder.glob("*.checkpoint.npz"))  # a completed run leaves none


def _cpu_seconds(pid: int) -> float:
    """The CPU time process ``pid`` has run (Linux's /proc: schedstat's nanoseconds, else
    stat's clock ticks); 0 once it is gone."""
    try:
        return int(Path(f"/proc/{pid}/schedstat").read_text().split()[0]) / 1e9
    except (OSError, ValueError, IndexError):
        pass
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def test_sigusr1_in_a_renders_first_second_changes_nothing(tmp_path):
    # From 50 ms into the render, every 20 ms for a second: 50 ms of its own CPU time, not of
    # the clock's, which on a busy machine can pass before the interpreter itself has started
    # (no Python code runs sooner; the test below covers the moments after).
    render = subprocess.Popen([str(SCRIPT), *RENDER], cwd=tmp_path, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    sent = 0
    try:
        while render.poll() is None and _cpu_seconds(render.pid) < 0.05:
            time.sleep(0.001)
        start = time.monotonic()
        while time.monotonic() - start < 1.0 and render.poll() is None:
            render.send_signal(signal.SIGUSR1)
            sent += 1
            time.sleep(0.02)
        _, err = render.communicate(timeout=600)
    finally:
        if render.poll() is None:
            render.kill()
            render.communicate()
    assert render.returncode == 0, f"rc {render.returncode} after {sent} SIGUSR1: {err}"
    assert sent >= 3, "the render ended before the test could signal it"
    _assert_rendered(tmp_path, err)


def test_sigusr1_while_the_cli_loads_changes_nothing(tmp_path):
    # Deterministic: the signal arrives while the command line loads its modules (where it
    # killed the process before SIGUSR1 was ignored first thing), and at every module loaded
    # during the render after.
    done = subprocess.run([sys.executable, "-c", SIGNAL_AT_EACH_IMPORT, str(SCRIPT), *RENDER],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"rc {done.returncode}: {done.stderr}"
    _assert_rendered(tmp_path, done.stderr)
