"""In core: one top-level Embree query per ray against per-domain queries (issue 9).

Renders a many-domain scene with every domain resident, twice per round, interleaved: with
the top-level scene of domain instances (``two_level=True``, the default) and domain by
domain (``two_level=False``, as before). The images must be identical (checked). Both use one
domain cache loaded beforehand (read + BVH build timed apart), so no render loads anything.
Prints wall and CPU seconds (the process's, all threads: steadier on a shared machine) and
``two_level_speedup=`` (best per-domain wall s / best two-level wall s) and
``two_level_cpu_speedup=`` (the same with CPU seconds).

    python bench/two_level.py [--grid 4x4x4] [--resolution 320] [--spp 4] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from bench_scenes import cached_rm

from vastray.render.driver import render, shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.cache import DomainCache


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
    n_tri = store.n_triangles
    settings = RenderSettings(width=args.width, height=args.height, spp=args.spp)
    print(f"scene: rm {args.resolution}^3, {n_tri:,} triangles in {len(store.domains)} domains "
          f"(grid {args.grid}); {args.width}x{args.height}, {args.spp} spp, pt, "
          f"{settings.bounces} bounces, {settings.shadow_samples} shadow samples, "
          f"{args.threads} threads, every domain resident")
    config = SceneConfig()
    _, keep, _ = shading_inputs(store, config, settings.integrator)
    cache = DomainCache(store, len(store.domains), keep)
    start = time.perf_counter()
    for d in range(len(store.domains)):
        if store.domains[d].n_triangles:
            cache.get(d)
    print(f"load (read + BVH build of every domain, once, not timed below): "
          f"{time.perf_counter() - start:.3f} s")
    for two_level in (False, True):  # warm-up: numba kernels, the filter
        render(store, config, RenderSettings(width=16, height=12, spp=1), threads=args.threads,
               progress=False, cache=cache, two_level=two_level)
    times = {True: [], False: []}
    images = {}
    for _ in range(args.repeat):
        for two_level in (False, True):
            wall, cpu = time.perf_counter(), time.process_time()
            result = render(store, config, settings, threads=args.threads, progress=False,
                            two_level=two_level, cache=cache)
            times[two_level].append((time.perf_counter() - wall, time.process_time() - cpu))
            images[two_level] = result.film.image()
            rays = result.counters["rays"]["total"]
    same = np.array_equal(images[True], images[False])
    for two_level, label in ((False, "per-domain"), (True, "two-level ")):
        runs = times[two_level]
        print(f"{label}: wall s {' '.join(f'{w:.3f}' for w, _ in runs)}, CPU s "
              f"{' '.join(f'{c:.3f}' for _, c in runs)}; best "
              f"{rays / min(w for w, _ in runs) / 1e6:.2f} M rays/s, "
              f"{rays / min(c for _, c in runs) / 1e6:.2f} M rays per CPU s")
    print(f"images identical: {same} ({rays:,} rays per render)")
    wall = {k: min(w for w, _ in v) for k, v in times.items()}
    cpu = {k: min(c for _, c in v) for k, v in times.items()}
    print(f"two_level_speedup={wall[False] / wall[True]:.3f} "
          f"two_level_cpu_speedup={cpu[False] / cpu[True]:.3f}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
