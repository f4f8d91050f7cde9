"""``bench/sim_figures.py``'s temporal-at-scale runs and its command line (the figure itself
simulates 8 to 64 nodes for about 20 minutes, so it is not run here)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from bench_modules import BENCH, load_bench

from vastray.actors.job_options import JobOptions

figures = load_bench("sim_figures")


def test_every_temporal_run_is_a_job_the_nodes_accept():
    labels = [label for label, _, _ in figures.TEMPORAL_RUNS]
    assert labels[:2] == ["async (Galaxy)", "cache-aware baseline"]  # the baselines, first
    assert len(set(labels)) == len(labels)
    for _, scheduler, extra in figures.TEMPORAL_RUNS:
        JobOptions(scheduler=scheduler, cache=2, load_bandwidth=(100.0,), **extra)
    assignments = {extra.get("assignment") for _, s, extra in figures.TEMPORAL_RUNS
                   if s == "temporal"}
    assert {"paper", "affinity", "fit"} <= assignments


def test_the_script_says_which_figure_to_name(tmp_path):
    run = subprocess.run([sys.executable, str(BENCH / "sim_figures.py")], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    assert "--temporal-scale" in run.stderr
    assert not any(Path(tmp_path).iterdir())  # nothing written
