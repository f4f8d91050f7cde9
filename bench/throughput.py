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

import numpy as np
from bench_scenes import cached_rm
from embreex import mesh_construction, rtcore_scene

from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.store import Store


def scene(resolution: int) -> Store:
    return cached_rm(resolution)


def raw_embree(store: Store, batches: list, threads: int) -> tuple[int, float]:
    """Closest-hit queries of the recorded rays on one Embree scene of all triangles."""
    parts, offset = [], 0
    vertices = []
    for d in range(len(store.domains)):
        dom = store.load_domain(d)
        vertices.append(np.asarray(dom.vertices))
        parts.append(np.asarray(dom.indices) + offset)
        offset += len(dom.vertices)
    embree = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(embree, np.concatenate(vertices), np.concatenate(parts))
    embree.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="DISTANCE")
    pool = ThreadPoolExecutor(threads)

    def query(args):
        kind, o, d, t_max = args
        if kind == "occluded":
            return embree.run(o, d, dists=t_max.copy(), query="OCCLUDED")
        return embree.run(o, d, dists=np.full(len(o), np.inf, np.float32), output=1)

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
    args = parser.parse_args()
    store = scene(args.resolution)
    print(f"scene: rm {args.resolution}^3, {store.n_triangles:,} triangles in "
          f"{len(store.domains)} domains")
    settings = RenderSettings(width=args.width, height=args.height, spp=args.spp,
                              integrator="pt", bounces=3, shadow_samples=args.shadow_samples,
                              batch_size=args.batch_size)
    batches: list = []
    result = render(store, SceneConfig(), settings, threads=args.threads, progress=False,
                    record_rays=batches)
    rays = result.counters["rays"]["total"]
    e2e_seconds = result.seconds["total"] - result.counters["bvh_build_s"]
    raw_rays, raw_seconds = raw_embree(store, batches, args.threads)
    assert raw_rays == rays
    e2e_rate, raw_rate = rays / e2e_seconds, raw_rays / raw_seconds
    print(f"rays traced: {rays:,} ({result.counters['rays']})")
    print(f"end_to_end_rays_per_s={e2e_rate:,.0f}  ({e2e_seconds:.2f} s, BVH builds "
          f"{result.counters['bvh_build_s']:.2f} s excluded)")
    print(f"raw_embree_rays_per_s={raw_rate:,.0f}  ({raw_seconds:.2f} s, the same closest-hit "
          f"and bounded occlusion queries, {args.threads} threads)")
    print(f"throughput_ratio={e2e_rate / raw_rate:.3f}")


if __name__ == "__main__":
    main()
