"""``bench/stress.py`` as a slow test: renders under a CPU hog, none may crash natively (even a
crash a node-loss recovery hides) or give an image other than the reference's (issue 20)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

STRESS = Path(__file__).resolve().parent.parent / "bench" / "stress.py"


@pytest.mark.timeout(2000)  # its own limit is 1,500 s
@pytest.mark.slow
def test_renders_under_a_cpu_hog_never_crash_and_equal_the_reference():
    proc = subprocess.run([sys.executable, str(STRESS), "--local", "7", "--distributed", "5"],
                          capture_output=True, text=True, timeout=1500)
    last = proc.stdout.strip().splitlines()[-1]
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    counts = dict(re.findall(r"(\w+)=(\S+)", last))
    assert counts["native_crashes"] == "0" and counts["wrong_images"] == "0", last
    assert counts["runs"] == "12" and counts["binding"] == "compiled", last


def test_bounds_checked_children_get_a_fresh_numba_cache(monkeypatch):
    # numba's cache does not key on NUMBA_BOUNDSCHECK: a checked run that loaded cached
    # unchecked kernels would check nothing, so the benches give such children a fresh cache
    monkeypatch.syspath_prepend(str(STRESS.parent))
    from numba_env import checked_env

    plain = {"PATH": "/bin"}
    assert checked_env(plain) is plain
    assert checked_env({"NUMBA_BOUNDSCHECK": "0"}) == {"NUMBA_BOUNDSCHECK": "0"}
    mine = {"NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": "/somewhere"}
    assert checked_env(mine) == mine  # a folder the user named is kept
    first = checked_env({"NUMBA_BOUNDSCHECK": "1"})
    folder = Path(first["NUMBA_CACHE_DIR"])
    assert folder.is_dir() and not any(folder.iterdir())
    # one folder per script run: its renders share the checked kernels
    assert checked_env({"NUMBA_BOUNDSCHECK": "1"})["NUMBA_CACHE_DIR"] == str(folder)


def test_a_checked_kernel_raises_where_a_cached_unchecked_one_would_not(tmp_path):
    # the reason for the above, shown: with a fresh cache and the flag, an index out of range
    # in a render kernel raises IndexError in a child process
    code = ("import numpy as np\n"
            "from vastray.render import kernels as K\n"
            "n = 3\n"
            "try:\n"
            "    K.one_domain_hits(np.array([0, 1, 99], np.int32), np.ones(n, np.float32),\n"
            "        np.zeros(n, np.float32), np.zeros(n, np.float32), np.ones((n, 3), np.float32),\n"
            "        np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.uint32), np.empty(n),\n"
            "        np.empty((n, 3)), np.empty((n, 3)), np.empty(n))\n"
            "except IndexError:\n"
            "    print('checked')\n")
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0 and "checked" in done.stdout, done.stderr[-2000:]
