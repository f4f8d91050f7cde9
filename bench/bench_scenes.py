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


#: The project's real third-party data (beside the repository); absent in a user's clone.
SHARED_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def cached_scan(name: str, grid: tuple[int, int, int] = (2, 2, 2)) -> Store | None:
    """A real scan of ``../shared/data/meshes`` partitioned into a ``grid`` of domains, made on
    first use; None (said on stdout) where that folder is absent."""
    mesh = SHARED_DATA / "meshes" / name
    if not mesh.is_file():
        print(f"  (no {mesh}: the real scan's rows are skipped)", flush=True)
        return None
    path = CACHE / f"{Path(name).stem}-{'x'.join(map(str, grid))}.store"
    if not (path / "manifest.json").is_file():
        from vastray.cli import main

        if main(["partition", str(mesh), "-o", str(path), "--grid", "x".join(map(str, grid)),
                 "--force", "--quiet"]) != 0:
            raise RuntimeError(f"could not partition {mesh}")
    return Store(path)
