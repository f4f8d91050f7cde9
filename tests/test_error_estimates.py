"""Error estimates a user can trust without a reference (issue 41): the refusal of a target
error a lossy render cannot keep, the batch estimator on heavy-tailed samples, the stopping
rule's promise on real renders, and the estimate's independence of the node count."""

from __future__ import annotations

import subprocess
import sys


def vastray(*args, cwd, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vastray.cli", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def test_target_error_without_reference_is_refused_for_simplified(tmp_path):
    out = vastray("render", "-o", "x.exr", "--spp", "4", "--width", "8", "--height", "8",
                  "--target-error", "0.1", "--simplified", "--scheduler", "async",
                  "--nodes", "2", cwd=tmp_path)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "--target-error" in lines[0] and "--simplified" in lines[0]
    assert "--reference" in lines[0] and not (tmp_path / "x.exr").exists()
