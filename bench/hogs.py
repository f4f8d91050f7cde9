"""Busy processes beside a benchmark's renders (bench/peers.py --hog, bench/stress.py,
bench/readme.py --hog): the one way the benches share the machine on purpose."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time

#: A busy process: spins until killed or until its parent (the bench) is gone.
SPINNER = ("import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n"
           "    for _ in range(1000000):\n        pass\n")


@contextlib.contextmanager
def busy_processes(count: int):
    """``count`` CPU spinners beside the block's renders, killed when it ends (Ctrl-C too)."""
    hogs = []
    try:
        for _ in range(count):
            hogs.append(subprocess.Popen([sys.executable, "-c", SPINNER]))
        time.sleep(0.5)  # every spinner started and spinning
        yield hogs
    finally:
        for hog in hogs:
            hog.kill()
        for hog in hogs:
            hog.wait()


@contextlib.contextmanager
def cpu_hog(per_core: int):
    """``per_core`` busy processes per core for the duration of the block; yields their
    count."""
    count = per_core * (os.cpu_count() or 1)
    with busy_processes(count):
        yield count
