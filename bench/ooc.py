"""Out-of-core scheduling: SpRay's speculative schedule against the baseline (SpRay Figs. 6, 8).

Generates (or reuses, in .bench_cache/) a Richtmyer-Meshkov-like scene split into many domains
and a second one with fewer, larger domains, then renders AO and PT with domain caches of 25,
50, 75 and 100 % of the domains, with both schedules, in one run. Every load is a real read
(the kernel is told to drop a domain's pages after reading it) plus the BVH build, which the
papers count in load time. "load wait s" is the part of the load time the render thread
actually waited: the rest was hidden by the preloader. Prints a table and, per cache size,
``loads_ratio=`` and ``time_ratio=`` (baseline / speculative); the first pair printed is the
25 % cache's. Then the history-depth sweep of Fig. 8 (H = 1..B for B = 3).

    python bench/ooc.py            # full run (about 10 minutes on 2 cores)
    python bench/ooc.py --quick    # a few-minute subset (1.2 M triangles)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from vastray.actors.local import render_out_of_core
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.generate import generate
from vastray.scene.store import Store

CACHE = Path(__file__).resolve().parent.parent / ".bench_cache"

FULL = {
    "scenes": [("rm", 1400, (5, 5, 4)), ("rm", 1400, (2, 2, 2))],
    "image": (64, 48), "spp": 32, "shadow_samples": 16, "bounces": 3,
    "caches": (0.25, 0.5, 0.75, 1.0),
}
QUICK = {
    "scenes": [("rm", 320, (5, 5, 4)), ("rm", 320, (2, 2, 2))],
    "image": (32, 24), "spp": 8, "shadow_samples": 4, "bounces": 3,
    "caches": (0.25, 1.0),
}


def scene(name: str, resolution: int, grid: tuple[int, int, int]) -> Store:
    path = CACHE / f"{name}-{resolution}-{'x'.join(map(str, grid))}.store"
    if not (path / "manifest.json").is_file():
        print(f"generating {path.name} ...", file=sys.stderr, flush=True)
        generate(name, path, resolution, grid=grid, seed=0, overwrite=True, progress=True)
    return Store(path)


def run(store: Store, settings: RenderSettings, scheduler: str, cache: int,
        history_depth: int | None = None) -> dict:
    start = time.perf_counter()
    result = render_out_of_core(store, SceneConfig(), settings, scheduler=scheduler,
                                cache_capacity=cache, history_depth=history_depth,
                                drop_page_cache=True, progress=False)
    c = result.counters
    return {
        "scheduler": scheduler, "cache": cache, "loads": c["loads"],
        "load_s": c["load_s"], "wait_s": c["load_wait_s"], "render_s": result.seconds["render"],
        "total_s": time.perf_counter() - start, "wasted": c.get("wasted_rays", 0),
        "speculative": c.get("speculative_rays", 0),
    }


def row(integrator: str, r: dict, n_domains: int) -> str:
    pct = round(100 * r["cache"] / n_domains)
    return (f"| {integrator} | {r['scheduler']:8} | {r['cache']:3d} ({pct:3d}%) | {r['loads']:5d} "
            f"| {r['load_s']:7.2f} | {r['wait_s']:7.2f} | {r['render_s']:7.2f} | {r['total_s']:7.2f} "
            f"| {r['wasted']:,} of {r['speculative']:,} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a 2-minute subset")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    width, height = plan["image"]
    for spec in plan["scenes"]:
        store = scene(*spec)
        n = len(store.domains)
        print(f"\n## scene {spec[0]} {spec[1]}^3: {store.n_triangles:,} triangles in {n} domains, "
              f"{width}x{height}, {plan['spp']} spp, {plan['shadow_samples']} shadow rays, "
              f"{plan['bounces']} bounces\n", flush=True)
        print("| integrator | scheduler | cache | loads | load s | load wait s | render s "
              "| total s | wasted speculative rays |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
        for fraction in plan["caches"]:
            cache = max(1, math.ceil(fraction * n))
            for integrator in ("ao", "pt"):
                settings = RenderSettings(width=width, height=height, spp=plan["spp"],
                                          integrator=integrator, bounces=plan["bounces"],
                                          shadow_samples=plan["shadow_samples"])
                base = run(store, settings, "image", cache)
                spec_run = run(store, settings, "spec-ooc", cache)
                print(row(integrator, base, n))
                print(row(integrator, spec_run, n))
                print(f"{integrator} cache={round(100 * fraction)}% "
                      f"loads_ratio={base['loads'] / max(spec_run['loads'], 1):.2f} "
                      f"time_ratio={base['total_s'] / spec_run['total_s']:.2f}", flush=True)
        if spec is plan["scenes"][0]:
            sweep(store, plan)


def sweep(store: Store, plan: dict) -> None:
    """Fig. 8: history depth H = 1..B at a 25 % cache (PT)."""
    n = len(store.domains)
    cache = max(1, math.ceil(0.25 * n))
    width, height = plan["image"]
    settings = RenderSettings(width=width, height=height, spp=plan["spp"], integrator="pt",
                              bounces=plan["bounces"], shadow_samples=plan["shadow_samples"])
    print(f"\n### history depth sweep (pt, cache {cache} of {n} domains)\n")
    print("| H | loads | load s | render s | total s | wasted speculative rays |")
    print("| --- | --- | --- | --- | --- | --- |", flush=True)
    for h in range(1, plan["bounces"] + 1):
        r = run(store, settings, "spec-ooc", cache, history_depth=h)
        print(f"| {h} | {r['loads']} | {r['load_s']:.2f} | {r['render_s']:.2f} "
              f"| {r['total_s']:.2f} | {r['wasted']:,} of {r['speculative']:,} |", flush=True)


if __name__ == "__main__":
    main()
