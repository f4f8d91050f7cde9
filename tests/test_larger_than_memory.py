"""A render larger than its memory budget, as a user runs it: `vastray generate`, then
`vastray render --memory-limit ... --cold-reads` in a fresh process (without --quiet), whose
domain cache holds at most the bytes of the largest quarter of the domains; the image equals,
bit for bit, the one rendered with every domain in memory, and the process's measured peak
stays under the limit."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from vastray.preflight import (
    LIMIT_BASE_MARGIN,
    domain_build_bytes,
    domain_footprints,
    estimate_memory,
)
from vastray.render.imageio import read_image
from vastray.scene.store import Store

WIDTH, HEIGHT, SPP = 48, 36, 2
IMAGE = ["--width", str(WIDTH), "--height", str(HEIGHT), "--spp", str(SPP),
         "--integrator", "pt", "--bounces", "3", "--shadow-samples", "1"]


def vastray(*args: str, cwd) -> subprocess.CompletedProcess:
    """The installed CLI in a fresh process, from ``cwd``."""
    run = subprocess.run([sys.executable, "-m", "vastray", *args], cwd=cwd, text=True,
                         capture_output=True, timeout=600,
                         env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert run.returncode == 0, run.stderr[-2000:]
    return run


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Store:
    folder = tmp_path_factory.mktemp("ltm")
    vastray("generate", "rm", "-o", "rm.store", "--resolution", "96", "--grid", "4x4x2",
            cwd=folder)
    return Store(folder / "rm.store")


def quarter_limit(store: Store) -> int:
    """A --memory-limit whose cache holds at most a quarter of the domains: the process's
    fixed part (film, outputs, every path of the frame in flight), the margin a limit keeps
    back, and the largest quarter."""
    fixed = (estimate_memory(WIDTH, HEIGHT, WIDTH * HEIGHT * SPP, 1).total + LIMIT_BASE_MARGIN
             + domain_build_bytes(store.domains, reads_ahead=True))
    largest = sorted(domain_footprints(store.domains), reverse=True)
    return fixed + sum(largest[:len(largest) // 4])


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_a_render_under_a_quarter_of_its_domains_equals_the_all_in_memory_one(
        store, tmp_path, scheduler):
    vastray("render", str(store.path), "-o", "all.exr", "--scheduler", "image",
            "--report", "all.json", *IMAGE, cwd=tmp_path)
    limit = quarter_limit(store)
    run = vastray("render", str(store.path), "-o", "ooc.exr", "--scheduler", scheduler,
                  "--memory-limit", str(limit), "--cold-reads", "--report", "ooc.json",
                  *IMAGE, cwd=tmp_path)
    report = json.loads((tmp_path / "ooc.json").read_text())
    c = report["counters"]
    n = len(store.domains)
    # bounded by bytes: room for the largest quarter, whichever domains fill it
    footprints = domain_footprints(store.domains)
    largest = sorted(footprints, reverse=True)
    assert max(footprints) <= c["cache_bytes"] <= sum(largest[:n // 4]), c["cache_bytes"]
    assert n // 4 <= c["cache_capacity"] < n, c["cache_capacity"]
    assert c["loads"] > c["distinct_domains_loaded"] == n  # domains were evicted and reloaded
    assert c["peak_resident_domains"] <= c["cache_capacity"]
    assert c["peak_resident_bytes"] <= c["cache_bytes"]  # built bytes within the model's
    assert c["peak_rss_bytes"] <= limit, (c["peak_rss_bytes"], limit)  # measured, in the report
    assert report["options"]["memory_limit"] == limit and report["options"]["cold_reads"]
    assert c["belady_loads"] <= c["loads"] and c["bytes_loaded"] > 0
    assert 0 <= c["heap_trims"] <= c["loads"]  # the cache's guard against the heap's keep
    # the summary line says what loading cost and the peak against the limit
    assert "GB read" in run.stderr and "s waited" in run.stderr and "peak RSS" in run.stderr
    assert f"({c['peak_resident_domains']} of {n} domains held at most)" in run.stderr
    all_loaded = json.loads((tmp_path / "all.json").read_text())["counters"]
    assert all_loaded["cache_capacity"] == n and all_loaded["loads"] == n
    np.testing.assert_array_equal(read_image(tmp_path / "ooc.exr"),
                                  read_image(tmp_path / "all.exr"))
