"""Domain load cost: seconds per million triangles to read a domain and build its BVH.

Loads every domain of a generated >= 1 M-triangle scene (reused from .bench_cache/, as
bench/throughput.py makes it) the way ``DomainCache`` does (``store.load_domain(mmap=True)``,
then the scene and its BVH), with both Embree paths, interleaved domain by domain, repeated:

* ``embreex``: the former path: the memory-mapped arrays are copied into embreex's buffers
  (``mesh_construction.TriangleMesh``), the BVH is built on the first query;
* ``zero-copy``: ``DomainBVH`` on the compiled binding (``vastray.scene.embree``): Embree uses
  the memory-mapped arrays in place (``rtcSetSharedGeometryBuffer``), the BVH is built at once.

Both build with the robust scene flag (see ``vastray.scene.embree.scenes``) on Embree's own threads.
Per path it prints the best repetition (the machine may be shared: best = least disturbed)
and the median, read (load_domain) and build separately, and finally ``load_s_per_mtri=`` for
the zero-copy path (goal: <= 0.35). ``--cold`` drops the domain files from the page cache
before every load, so each read comes from disk.

    python bench/load.py [--resolution 384] [--repeat 5] [--cold]
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import time

import numpy as np
from bench_scenes import cached_rm
from embreex import mesh_construction, rtcore_scene

from vastray.scene.bvh import DomainBVH
from vastray.scene.embree.library import binding
from vastray.scene.store import Store


def scene(resolution: int) -> Store:
    return cached_rm(resolution)


def drop_pages(store: Store, domain: int) -> None:
    for rel in store.domains[domain].files.values():
        fd = os.open(store.path / rel, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def load_embreex(store: Store, domain: int) -> tuple[float, float, object]:
    start = time.perf_counter()
    arrays = store.load_domain(domain, mmap=True)
    read = time.perf_counter()
    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, np.ascontiguousarray(arrays.vertices, np.float32),
                                   np.ascontiguousarray(arrays.indices, np.uint32))
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="DISTANCE")
    return read - start, time.perf_counter() - read, scene


def load_zero_copy(store: Store, domain: int) -> tuple[float, float, object]:
    start = time.perf_counter()
    arrays = store.load_domain(domain, mmap=True)
    read = time.perf_counter()
    bvh = DomainBVH(domain, arrays)
    assert bvh.compiled
    return read - start, time.perf_counter() - read, bvh


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=384)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--cold", action="store_true",
                        help="drop each domain's files from the page cache before loading it")
    args = parser.parse_args()
    store = scene(args.resolution)
    mtri = store.n_triangles / 1e6
    api = binding()
    assert api is not None, "the compiled Embree binding is unavailable"
    print(f"scene: rm {args.resolution}^3, {store.n_triangles:,} triangles in "
          f"{len(store.domains)} domains; Embree {api.version}, {os.cpu_count()} cores, "
          f"page cache {'dropped before each load' if args.cold else 'warm'}")
    paths = {"embreex": load_embreex, "zero-copy": load_zero_copy}
    # one untimed round: page cache, Embree's thread pool and the kernels warm
    for load in paths.values():
        load(store, 0)
    totals: dict[str, list[tuple[float, float]]] = {name: [] for name in paths}
    for _ in range(args.repeat):
        sums = {name: [0.0, 0.0] for name in paths}
        for d in range(len(store.domains)):
            for name, load in paths.items():
                if args.cold:
                    drop_pages(store, d)
                gc.collect()
                read, build, keep = load(store, d)
                sums[name][0] += read
                sums[name][1] += build
                del keep
        for name in paths:
            totals[name].append(tuple(sums[name]))
    for name, runs in totals.items():
        best = min(runs, key=sum)
        median = statistics.median(sum(r) for r in runs)
        print(f"{name:>9}: best {sum(best) / mtri:.3f} s/Mtri (read {best[0] / mtri:.3f}, "
              f"build {best[1] / mtri:.3f}), median {median / mtri:.3f} s/Mtri "
              f"over {len(runs)} runs")
    new = min(sum(r) for r in totals["zero-copy"]) / mtri
    old = min(sum(r) for r in totals["embreex"]) / mtri
    print(f"speedup={old / new:.2f}")
    print(f"load_s_per_mtri={new:.3f}")


if __name__ == "__main__":
    main()
