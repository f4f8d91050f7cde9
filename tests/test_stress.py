"""``bench/stress.py`` as a slow test: renders under a CPU hog, none may crash natively (even a
crash a node-loss recovery hides) or give an image other than the reference's (issue 20)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

STRESS = Path(__file__).resolve().parent.parent / "bench" / "stress.py"


@pytest.mark.slow
def test_renders_under_a_cpu_hog_never_crash_and_equal_the_reference():
    proc = subprocess.run([sys.executable, str(STRESS), "--local", "7", "--distributed", "5"],
                          capture_output=True, text=True, timeout=1500)
    last = proc.stdout.strip().splitlines()[-1]
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    counts = dict(re.findall(r"(\w+)=(\S+)", last))
    assert counts["native_crashes"] == "0" and counts["wrong_images"] == "0", last
    assert counts["runs"] == "12" and counts["binding"] == "compiled", last
