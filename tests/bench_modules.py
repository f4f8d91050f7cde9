"""The bench scripts as modules for the tests that check their tables and helpers: ``bench/``
is not a package, so a script is loaded from its file (and registered in ``sys.modules``:
dataclasses look their module up there)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "bench"


def load_bench(script: str, name: str | None = None):
    """``bench/<script>.py`` as module ``name`` (default ``bench_<script>``), loaded once.

    ``bench/`` goes on the end of ``sys.path`` first, as it is when a script runs: scripts import
    their siblings (``bench_scenes``, ``hogs``) from beside themselves.
    """
    if str(BENCH) not in sys.path:
        sys.path.append(str(BENCH))
    name = name or f"bench_{script}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, BENCH / f"{script}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]
