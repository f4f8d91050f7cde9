"""Scenes the benchmarks share, generated once into ``.bench_cache/`` (git-ignored)."""

from __future__ import annotations

from pathlib import Path

from vastray.scene.generate import generate
from vastray.scene.store import Store

CACHE = Path(__file__).resolve().parent.parent / ".bench_cache"


def cached_rm(resolution: int, grid: tuple[int, int, int] = (2, 2, 2)) -> Store:
    """The ``rm`` scene at ``resolution``^3 in a ``grid`` of domains, made on first use."""
    path = CACHE / f"rm-{resolution}-{'x'.join(map(str, grid))}.store"
    if not (path / "manifest.json").is_file():
        generate("rm", path, resolution, grid=grid, seed=0, overwrite=True, progress=True)
    return Store(path)


def cached_cosmo(resolution: int, grid: tuple[int, int, int] = (4, 4, 4)) -> Store:
    """The ``cosmo`` scene (a cosmic web) at ``resolution``^3 in a ``grid`` of domains (empty
    cells have none: 16x16x8 at 160 gives 1,439 domains), made on first use."""
    path = CACHE / f"cosmo-{resolution}-{'x'.join(map(str, grid))}.store"
    if not (path / "manifest.json").is_file():
        generate("cosmo", path, resolution, grid=grid, seed=0, overwrite=True, progress=True)
    return Store(path)
