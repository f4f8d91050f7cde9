"""In core: one top-level Embree query per ray against per-domain queries (issue 9).

Renders a many-domain scene with every domain resident, twice per round, interleaved: with
the top-level scene of domain instances (``two_level=True``, the default) and domain by
domain (``two_level=False``, as before). The images must be identical (checked); load time
(read + BVH build, which the renderer reports) is excluded from both and printed apart.
Prints ``two_level_speedup=`` (best per-domain render s / best two-level render s).

    python bench/two_level.py [--grid 4x4x4] [--resolution 320] [--spp 4] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
from bench_scenes import cached_rm

from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid", default="4x4x4", help="domain grid (default 4x4x4)")
    parser.add_argument("--resolution", type=int, default=320, help="rm scene resolution")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    grid = tuple(int(g) for g in args.grid.split("x"))
    store = cached_rm(args.resolution, grid)
    n_tri = sum(d.n_triangles for d in store.domains)
    settings = RenderSettings(width=args.width, height=args.height, spp=args.spp)
    print(f"scene: rm {args.resolution}^3, {n_tri:,} triangles in {len(store.domains)} domains "
          f"(grid {args.grid}); {args.width}x{args.height}, {args.spp} spp, pt, "
          f"{settings.bounces} bounces, {settings.shadow_samples} shadow samples, "
          f"{args.threads} threads, every domain resident")
    config = SceneConfig()
    render(store, config, RenderSettings(width=16, height=12, spp=1), threads=args.threads,
           progress=False)  # warm-up: numba kernels
    times = {True: [], False: []}
    images = {}
    for _ in range(args.repeat):
        for two_level in (False, True):
            result = render(store, config, settings, threads=args.threads, progress=False,
                            two_level=two_level)
            times[two_level].append((result.seconds["trace_and_shade"], result.seconds["load"]))
            images[two_level] = result.film.image()
            rays = result.counters["rays"]["total"]
    same = np.array_equal(images[True], images[False])
    for two_level, label in ((False, "per-domain"), (True, "two-level ")):
        runs = times[two_level]
        print(f"{label}: render s {' '.join(f'{t:.3f}' for t, _ in runs)} (load excluded: "
              f"{' '.join(f'{w:.3f}' for _, w in runs)} s); best "
              f"{rays / min(t for t, _ in runs) / 1e6:.2f} M rays/s")
    print(f"images identical: {same}")
    best = {k: min(t for t, _ in v) for k, v in times.items()}
    print(f"two_level_speedup={best[False] / best[True]:.3f}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
