"""Scenes the benchmarks share, generated once into ``.bench_cache/`` (git-ignored)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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


#: The heavy-tailed scene's camera and lights (``hidden_lamp_scene``): a warm point light in
#: an open-topped cup just under the ceiling, and a dim sky.
HIDDEN_LAMP_TOML = """
[camera]
position = [0.0, 1.1, 3.4]
look_at = [0.0, 0.7, 0.0]
fov = 50
[[light]]
type = "point"
position = [0.0, {light_y}, -0.6]
intensity = [{power}, {power_g}, {power_b}]
[[light]]
type = "ambient"
radiance = 0.03
[material]
diffuse = 0.75
specular = 0.0
"""


def hidden_lamp_scene(folder: Path, cup: float = 0.5, depth: float = 0.2,
                      gap: float = 0.1, power: float = 3.0) -> tuple[Path, Path]:
    """A heavy-tailed scene: a room (floor, back wall, ceiling at height 2; open at the sides
    and front) lit by a point light inside an open-topped cup (half-width ``cup``, the light
    ``depth`` below its rim, the rim ``gap`` below the ceiling). No visible surface sees the
    light: it lights a small spot of the ceiling, very bright, and everything the camera sees
    gets that light through a bounce off the spot, which a diffuse bounce finds rarely (a
    small bright light behind a diffuser: rare bright paths). Writes ``lamp.ply`` and
    ``lamp.toml`` to ``folder``; returns their paths."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)

    def box(lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        b = trimesh.creation.box(extents=hi - lo)
        b.apply_translation((lo + hi) / 2)
        return b

    t = 0.02  # wall thickness
    top = 2.0 - gap  # the cup's rim
    bottom = top - depth - 0.05
    cx, cz = 0.0, -0.6
    parts = [box([-3, -t, -2], [3, 0, 3]),  # floor
             box([-3, 0, -2 - t], [3, 2, -2]),  # back wall
             box([-3, 2, -2], [3, 2 + t, 1.0]),  # ceiling
             box([cx - cup, bottom - t, cz - cup], [cx + cup, bottom, cz + cup])]  # cup floor
    for sx, sz in ((1, 0), (-1, 0), (0, 1), (0, -1)):  # its four sides
        lo = [cx - cup if sx == 0 else cx + sx * cup - (t if sx > 0 else 0), bottom - t,
              cz - cup if sz == 0 else cz + sz * cup - (t if sz > 0 else 0)]
        hi = [cx + cup if sx == 0 else cx + sx * cup + (0 if sx > 0 else t), top,
              cz + cup if sz == 0 else cz + sz * cup + (0 if sz > 0 else t)]
        parts.append(box(lo, hi))
    mesh = trimesh.util.concatenate(parts)
    ply = folder / "lamp.ply"
    mesh.export(ply)
    toml = folder / "lamp.toml"
    toml.write_text(HIDDEN_LAMP_TOML.format(light_y=top - depth, power=power,
                                            power_g=0.7 * power, power_b=0.4 * power))
    return ply, toml
