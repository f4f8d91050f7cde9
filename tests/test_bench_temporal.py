"""``bench/temporal.py``'s error split and its runs, on hand-made images (the script renders
animations on 4 nodes for minutes, so it is not run here)."""

from __future__ import annotations

import numpy as np
import pytest
from bench_modules import load_bench

temporal = load_bench("temporal")


def test_converged_split_takes_the_variances_out_of_the_error():
    reference = np.ones((4, 6, 3))
    run = {"images": {3: reference + 0.1}, "variances": {3: np.full((4, 6, 3), 0.002)}}
    split = temporal.converged_split(run, {3: (reference, np.full((4, 6, 3), 0.001))})
    assert split["rel_mse_global"] == pytest.approx(0.01)  # 0.1^2 over a mean square of 1
    assert split["variance"] == pytest.approx(0.002)
    assert split["reference_variance"] == pytest.approx(0.001)
    assert split["bias2"] == pytest.approx(0.01 - 0.002 - 0.001)
    unbiased = {"images": {3: reference}, "variances": {3: np.zeros((4, 6, 3))}}
    assert temporal.converged_split(unbiased, {3: (reference, np.zeros((4, 6, 3)))}) == {
        "rel_mse_global": 0.0, "variance": 0.0, "bias2": 0.0, "reference_variance": 0.0}


def test_baselines_get_what_the_method_gets():
    head = temporal.HEADLINE
    # the cache-aware baseline and temporal differ in assignment and priority only, and
    # --simplified adds the same portal policy to both
    for lossless, lossy in ((temporal.AWARE_BASELINE, temporal.AWARE_SIMPLIFIED),
                            (temporal.TEMPORAL, temporal.TEMPORAL_SIMPLIFIED)):
        assert {k: v for k, v in head[lossy].items() if k != "simplified"} == head[lossless]
        assert head[lossy]["simplified"] is True
    assert head[temporal.AWARE_BASELINE]["assignment"] == "spatial"
    assert head[temporal.TEMPORAL] == {"assignment": "affinity", "priority": "cost-rate"}


def test_ablations_cover_assignment_by_priority_once():
    quick, full = temporal.ablations(False), temporal.ablations(True)
    pairs = {(c["assignment"], c["priority"]) for c in full.values()}
    assert len(pairs) == len(full) == 7  # 2 assignments x 4 priorities, less the headline
    assert ("affinity", "cost-rate") not in pairs
    assert {(c["assignment"], c["priority"]) for c in quick.values()} == {
        ("paper", "cost-rate"), ("paper", "queue+resident"), ("affinity", "queue+resident")}
