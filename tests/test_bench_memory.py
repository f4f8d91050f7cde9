"""``bench/memory.py --quick``: the preflight's memory estimate stays within 0.8-1.5 of the
peak RSS real renders reach (issue 23). Renders a few small images as real processes, about
20 s on 2 cores, so it is marked slow."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "bench" / "memory.py"
spec = importlib.util.spec_from_file_location("bench_memory", SCRIPT)
memory = importlib.util.module_from_spec(spec)
sys.modules[spec.name] = memory  # dataclasses look their module up there
spec.loader.exec_module(memory)


def test_table_rows_and_ratios():
    rows = [memory.Row("a", "process", 300, 200), memory.Row("b", "node", 100, 125)]
    text = memory.table(rows)
    assert text.splitlines()[0] == "| case | role | estimate | measured peak RSS | ratio |"
    assert "| a | process | 0 MB | 0 MB | 1.50 |" in text and "| 0.80 |" in text
    assert [r.ratio for r in rows] == [1.5, 0.8]


def test_quick_cases_cover_sizes_threads_schedulers_and_nodes():
    labels = " ".join(label for label, _ in memory.cases(quick=True))
    for part in ("64²", "1024²", "t1", "t2", "spec-ooc", "--nodes 2", "default"):
        assert part in labels
    assert len(memory.cases(quick=False)) > len(memory.cases(quick=True))


@pytest.mark.slow
def test_quick_sweep_keeps_every_estimate_within_range_of_the_measured_peak():
    out = subprocess.run([sys.executable, str(SCRIPT), "--quick"], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    ratios = [float(line.rsplit("|", 2)[1]) for line in out.stdout.splitlines()
              if re.match(r"\| .* \| \d+\.\d\d \|$", line)]
    assert len(ratios) == 8, out.stdout  # 7 cases, the --nodes one as node and coordinator
    low, high = memory.RATIO_RANGE
    assert all(low <= r <= high for r in ratios), out.stdout
    assert re.search(r"^cases=8 min_ratio=\S+ max_ratio=\S+", out.stdout, re.M), out.stdout
