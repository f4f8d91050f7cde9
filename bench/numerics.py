"""Numerical stability far from the origin and at extreme distances (issue 20, part 2).

Renders one small scene (a bumpy sphere on a ground slab with boxes, a point light and a sky;
path tracing, 2x2x2 domains) as it is, translated by 1e3 ... 1e7 with its camera and light,
and seen from a camera 6e4 and 6e5 away (field of view narrowed to keep the framing), and
prints each image's mean change and relative MSE against the reference, beside the
seed-to-seed noise (the same reference scene rendered with another seed)::

    python bench/numerics.py                  # 64x48, 8 spp
    python bench/numerics.py --shifts 1e5 1e6 --spp 16

The far cameras are compared with a camera 2e3 away (the projection of a 2-unit scene changes
by about 1e-3 between the two: well under a pixel), the translations with the scene at the
origin. ``tests/test_numerics.py`` builds the same scenes (``far_scene``).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.lights import AmbientLight, PointLight
from vastray.render.scene_config import SceneConfig
from vastray.scene.partition import partition_grid
from vastray.scene.store import DomainArrays, Store, StoreWriter, relative_to

#: Where the camera looks from (a unit direction) and at.
VIEW = np.array([0.55, 0.45, 1.0]) / np.linalg.norm([0.55, 0.45, 1.0])
TARGET = np.array([0.0, -0.2, 0.0])


def far_mesh(shift: float) -> DomainArrays:
    """The scene's triangles moved by ``shift`` along (1, 1, 1) (about 7,000 triangles,
    2.6 units across): positions in float64, stored relative to their centre."""
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    bump = 1.0 + 0.15 * np.sin(8 * sphere.vertices[:, 0]) * np.cos(10 * sphere.vertices[:, 1])
    sphere.vertices *= bump[:, None]
    boxes = []
    for _ in range(6):
        box = trimesh.creation.box(extents=rng.uniform(0.1, 0.3, 3))
        box.apply_translation([rng.uniform(-1, 1), -0.5, rng.uniform(-1, 1)])
        boxes.append(box)
    ground = trimesh.creation.box(extents=[2.6, 0.05, 2.6])
    ground.apply_translation([0, -0.65, 0])
    mesh = trimesh.util.concatenate([sphere, ground, *boxes])
    framed = relative_to(np.asarray(mesh.vertices, np.float64) + shift)
    return dataclasses.replace(framed, indices=np.asarray(mesh.faces, np.uint32))


def far_store(path: Path, shift: float, grid=(2, 2, 2)) -> Store:
    """``far_mesh(shift)`` written as a ``grid`` of domains."""
    with StoreWriter(path) as writer:
        for dom in partition_grid(far_mesh(shift), grid).domains:
            writer.add_domain(dom)
    return Store(path)


def far_config(shift: float = 0.0, distance: float = 4.0, power: float = 6.0) -> SceneConfig:
    """Camera ``distance`` from the target along ``VIEW`` (its field of view keeping the
    framing of a camera 4 units away), a point light of intensity ``power`` and a sky,
    everything moved by ``shift`` along (1, 1, 1)."""
    offset = np.full(3, shift)
    fov = float(np.degrees(2 * np.arctan(np.tan(np.radians(20.0)) * 4.0 / distance)))
    lights = [PointLight(np.array([0.8, 2.0, 0.6]) + offset, np.full(3, power)),
              AmbientLight(np.full(3, 0.15))]
    return SceneConfig(camera={"position": TARGET + offset + VIEW * distance,
                               "look_at": TARGET + offset, "up": np.array([0.0, 1.0, 0.0]),
                               "fov": fov}, lights=lights)


def compare(image: np.ndarray, reference: np.ndarray) -> dict:
    """Mean change (relative) and relative MSE (MSE / mean(reference^2)) of ``image``."""
    finite = np.isfinite(image)
    err = np.where(finite, image, 0.0) - reference
    return {"mean": float(np.where(finite, image, 0.0).mean() / reference.mean() - 1.0),
            "rel_mse": float(np.mean(err ** 2) / np.mean(reference ** 2)),
            "nonfinite": int(np.count_nonzero(~finite))}


def settings(spp: int = 8, seed: int = 1, width: int = 64, height: int = 48) -> RenderSettings:
    return RenderSettings(width=width, height=height, spp=spp, integrator="pt", bounces=1,
                          shadow_samples=2, seed=seed)


def image(store: Store, config: SceneConfig, s: RenderSettings) -> np.ndarray:
    return render(store, config, s, threads=1, progress=False).film.image()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shifts", type=float, nargs="*", default=[1e3, 1e4, 1e5, 1e6, 1e7])
    parser.add_argument("--distances", type=float, nargs="*", default=[6e4, 6e5])
    parser.add_argument("--spp", type=int, default=8)
    args = parser.parse_args()
    s = settings(args.spp)
    with tempfile.TemporaryDirectory() as tmp:
        base = far_store(Path(tmp) / "base.store", 0.0)
        reference = image(base, far_config(), s)
        noise = compare(image(base, far_config(), dataclasses.replace(s, seed=2)), reference)
        print(f"noise (seed 2 vs 1): mean {noise['mean']:+.4%}  rel_mse {noise['rel_mse']:.4g}")
        for shift in args.shifts:
            start = time.perf_counter()
            store = far_store(Path(tmp) / f"s{shift:g}.store", shift)
            c = compare(image(store, far_config(shift), s), reference)
            print(f"translated {shift:.0e}: mean {c['mean']:+.4%}  rel_mse {c['rel_mse']:.4g}  "
                  f"nonfinite {c['nonfinite']}  ({time.perf_counter() - start:.1f} s)")
        near = image(base, far_config(distance=2e3), s)
        for distance in args.distances:
            c = compare(image(base, far_config(distance=distance), s), near)
            print(f"camera {distance:.0e} away (vs 2e3): mean {c['mean']:+.4%}  "
                  f"rel_mse {c['rel_mse']:.4g}")


if __name__ == "__main__":
    main()
