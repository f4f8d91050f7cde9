"""End-to-end path-tracing throughput against raw Embree on the same rays.

Renders a >= 1 M-triangle generated scene with ``pt`` while recording every query batch, then
replays exactly what the renderer asked: closest-hit queries (full hit output) for camera and
bounce rays, bounded occlusion queries (``t_max``) for shadow rays, against one Embree scene
of all triangles on as many threads as the render used (all cores by default). Prints rays/s
of both and ``throughput_ratio=`` (end-to-end / raw), where end-to-end time is the render's
wall time minus its one-off BVH builds (the raw side's build is not timed either). Floor: 0.5.
(Before the replay recorded query kinds it replayed shadow rays as unbounded closest-hit
queries: about 1.19x more work on the raw side than the renderer did.)

    python bench/throughput.py [--spp 8] [--resolution 384] [--shadow-samples 16]
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
from bench_scenes import cached_rm
from embreex import mesh_construction, rtcore_scene

from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.embree.library import binding
from vastray.scene.embree.scenes import Scene
from vastray.scene.store import Store


def scene(resolution: int) -> Store:
    return cached_rm(resolution)


def all_triangles(store: Store) -> tuple[np.ndarray, np.ndarray]:
    """Every domain's triangles as one mesh: (V, 3) float32 vertices, (T, 3) uint32 indices."""
    parts, offset = [], 0
    vertices = []
    for d in range(len(store.domains)):
        dom = store.load_domain(d)
        vertices.append(np.asarray(dom.vertices))
        parts.append(np.asarray(dom.indices) + offset)
        offset += len(dom.vertices)
    return np.concatenate(vertices), np.concatenate(parts).astype(np.uint32)


def raw_compiled(store: Store, batches: list, threads: int) -> float:
    """Seconds for the recorded queries through vastray's compiled Embree kernels
    (``scene/embree/``) on one scene of all triangles: the renderer's own query path,
    without anything around it."""
    scene = Scene(*all_triangles(store))
    one = np.zeros((1, 3), np.float32)
    scene.intersect(one, one + 1, np.full(1, np.inf, np.float32), threads)  # load the kernels
    start = time.perf_counter()
    for kind, o, d, t_max in batches:
        if kind == "occluded":
            scene.occluded(o, d, t_max, threads)
        else:
            scene.intersect(o, d, np.full(len(o), np.inf, np.float32), threads)
    seconds = time.perf_counter() - start
    scene.close()
    return seconds


def raw_embree(store: Store, batches: list, threads: int) -> tuple[int, float]:
    """The recorded queries through embreex on one Embree scene of all triangles."""
    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, *all_triangles(store))
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="DISTANCE")
    pool = ThreadPoolExecutor(threads)

    def query(args):
        kind, o, d, t_max = args
        if kind == "occluded":
            return scene.run(o, d, dists=t_max.copy(), query="OCCLUDED")
        return scene.run(o, d, dists=np.full(len(o), np.inf, np.float32), output=1)

    chunks = []
    for kind, o, d, t_max in batches:
        bounds = np.linspace(0, len(o), threads + 1).astype(int)
        chunks += [(kind, o[a:b], d[a:b], None if t_max is None else t_max[a:b])
                   for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    start = time.perf_counter()
    list(pool.map(query, chunks))
    seconds = time.perf_counter() - start
    pool.shutdown()
    return sum(len(o) for _, o, _, _ in batches), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=384)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--shadow-samples", type=int, default=16)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                        help="Embree threads for both sides (default: all cores)")
    parser.add_argument("--batch-size", type=int, default=65536)
    parser.add_argument("--cold", action="store_true",
                        help="no untimed warm-up render (numba's start is timed)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="renders and replays, interleaved; the best of each side counts")
    args = parser.parse_args()
    store = scene(args.resolution)
    print(f"scene: rm {args.resolution}^3, {store.n_triangles:,} triangles in "
          f"{len(store.domains)} domains")
    settings = RenderSettings(width=args.width, height=args.height, spp=args.spp,
                              integrator="pt", bounces=3, shadow_samples=args.shadow_samples,
                              batch_size=args.batch_size)
    if not args.cold:
        start = time.perf_counter()
        render(store, SceneConfig(), replace(settings, width=32, height=24, spp=1),
               threads=args.threads, progress=False)
        print(f"warm-up render (untimed): {time.perf_counter() - start:.2f} s")
    batches: list = []
    e2e_runs, builds, raw_runs, compiled_runs = [], [], [], []
    compiled = binding() is not None
    for run in range(args.repeat):
        # Renders are deterministic: the first one's queries are every run's.
        result = render(store, SceneConfig(), settings, threads=args.threads, progress=False,
                        record_rays=batches if run == 0 else None)
        rays = result.counters["rays"]["total"]
        builds.append(result.counters["bvh_build_s"])
        e2e_runs.append(result.seconds["total"] - builds[-1])
        raw_rays, raw_seconds = raw_embree(store, batches, args.threads)
        assert raw_rays == rays
        raw_runs.append(raw_seconds)
        if compiled:
            compiled_runs.append(raw_compiled(store, batches, args.threads))
    # One run: its figures. Several: the best of each side (interleaved, so a slow spell of
    # this shared machine hits both sides alike), as peers.py does.
    e2e_seconds, raw_seconds = min(e2e_runs), min(raw_runs)
    build = builds[e2e_runs.index(e2e_seconds)]
    e2e_rate, raw_rate = rays / e2e_seconds, raw_rays / raw_seconds
    print(f"rays traced: {rays:,} ({result.counters['rays']})")
    if args.repeat > 1:
        print(f"runs (s): end to end {_secs(e2e_runs)}, raw embreex {_secs(raw_runs)}"
              + (f", raw compiled {_secs(compiled_runs)}" if compiled else "") + "; best of each:")
    print(f"end_to_end_rays_per_s={e2e_rate:,.0f}  ({e2e_seconds:.2f} s, BVH builds "
          f"{build:.2f} s excluded)")
    print(f"raw_embree_rays_per_s={raw_rate:,.0f}  ({raw_seconds:.2f} s, the same closest-hit "
          f"and bounded occlusion queries, {args.threads} threads)")
    if compiled:
        compiled_rate = rays / min(compiled_runs)
        print(f"raw_compiled_rays_per_s={compiled_rate:,.0f}  (the same queries through "
              f"vastray's compiled kernels, {args.threads} threads)")
        print(f"compiled_throughput_ratio={e2e_rate / compiled_rate:.3f}  (issue 9: goal 0.7)")
    print(f"throughput_ratio={e2e_rate / raw_rate:.3f}")


def _secs(runs: list[float]) -> str:
    return ", ".join(f"{s:.2f}" for s in runs)


if __name__ == "__main__":
    main()
