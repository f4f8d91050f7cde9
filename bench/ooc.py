"""Out-of-core scheduling: SpRay's speculative schedule against the baseline (SpRay Figs. 6, 8).

Generates (or reuses, in .bench_cache/) a Richtmyer-Meshkov-like scene split into many domains
and a second one with fewer, larger domains, then renders PT and AO with domain caches of 25,
50, 75 and 100 % of the domains, with both schedules, in one run. Every load is a real read
(the kernel is told to drop a domain's pages after reading it) plus the BVH build, which the
papers count in load time.

Both schedules run in two configurations, and each is compared only with the other in the same
one:

* ``paper-faithful``: as the papers describe them: domains loaded sequentially (SpRay 5.1.1,
  "data loading is run sequentially"), the baseline's fullest queue first (Listing 1) and
  spec-ooc's pure traversal-score order (Listing 2);
* ``strongest``: both with every improvement this project has: the preloader thread (each
  schedule's ``likely_next``) and the resident-first rule (domains in memory are served before
  anything is loaded); with it, spec-ooc also serves a resident domain's new rays when the
  cache is about to evict it rather than on each arrival (``serve_before_evict``) and re-ranks
  the rest of a round before each pick (``rescore``). The baseline has no counterpart to
  either: it serves a resident domain's rays as soon as they arrive (before anything is
  loaded, so never evicts one with rays waiting) and picks its fullest queue afresh each time.

Before anything is timed, each schedule renders once untimed (``warm_up``).

"load wait s" is the part of the load time the render thread actually waited: the rest was
hidden by the preloader. "floor" is the number of domains any ray was traced against (each must
be loaded at least once); "untraced loads" are loads after which no ray was traced against the
domain (with the preloader: wrong guesses). Per cache size, integrator and configuration it
prints ``loads_ratio=``, ``time_ratio=``, ``load_time_ratio=`` and ``render_ratio=`` (baseline
/ speculative; render = the render thread's tracing time, without loads) and
``loads_over_floor=`` (spec-ooc loads / floor), paper-faithful lines beside SpRay's figures;
the first line printed is the strongest comparison at a 25 % cache with PT. Then the
history-depth sweep of Fig. 8 (H = 1..B for B = 3, strongest configuration).
``--ablation`` adds every switch combination for both schedules, and spec-ooc's own switches
in every combination (PT, 25 % cache, first scene). ``--ray-sweep`` adds the strongest PT
comparison at a 25 % cache with 4x and 16x the paths (first scene): speculation saves more
loads the more rays each domain gathers, and the papers render 1024x1024 at 32 spp.

    python bench/ooc.py            # full run (well over an hour on 2 cores)
    python bench/ooc.py --quick    # a few-minute subset (1.2 M triangles)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.generate import generate
from vastray.scene.store import Store
from vastray.schedule.spec_ooc import SpeculationRules

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


CONFIGS = {  # name -> render_out_of_core switches, the same for both schedules
    "strongest": {"preload": True, "resident_first": True},
    "paper-faithful": {"preload": False, "resident_first": False},
}


def run(store: Store, settings: RenderSettings, scheduler: str, cache: int,
        history_depth: int | None = None, ablation: SpeculationRules | None = None,
        **switches) -> dict:
    """One render; ``switches`` are more ``JobOptions`` fields (``preload``,
    ``resident_first``), the same for both schedules."""
    start = time.perf_counter()
    result = render_out_of_core(store, SceneConfig(), settings,
                                options=JobOptions(scheduler=scheduler, cache=cache,
                                                   history_depth=history_depth, cold_reads=True,
                                                   **switches),
                                progress=False, ablation=ablation)
    c = result.counters
    return {
        "scheduler": scheduler, "cache": cache, "loads": c["loads"],
        "floor": c["domains_traced"], "untraced": c["untraced_loads"],
        "load_s": c["load_s"], "wait_s": c["load_wait_s"],
        "render_s": result.seconds["render"] + result.seconds["schedule"],  # deciding + tracing
        "total_s": time.perf_counter() - start, "wasted": c.get("wasted_rays", 0),
        "speculative": c.get("speculative_rays", 0),
    }


HEADER = ("| integrator | config | scheduler | cache | loads | floor | untraced loads | load s "
          "| load wait s | render s | total s | wasted speculative rays |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")


def row(integrator: str, config: str, r: dict, n_domains: int) -> str:
    pct = round(100 * r["cache"] / n_domains)
    return (f"| {integrator} | {config} | {r['scheduler']:8} | {r['cache']:3d} ({pct:3d}%) "
            f"| {r['loads']:5d} | {r['floor']} | {r['untraced']} | {r['load_s']:7.2f} "
            f"| {r['wait_s']:7.2f} | {r['render_s']:7.2f} | {r['total_s']:7.2f} "
            f"| {r['wasted']:,} of {r['speculative']:,} |")


SPRAY = "SpRay Fig. 6 (RM/Enzo, paper-faithful): 1.7-2.3x total, 2.7-3.2x load time"


def comparison(integrator: str, fraction: float, config: str, base: dict, spec: dict) -> str:
    """One line of ratios, baseline / speculative: loads, total time, load time and the
    render thread's time outside loads (the schedule deciding, spec-ooc's filtering included,
    and tracing: per-batch work the two schedules do differently), and spec-ooc's loads over
    its floor."""
    loads = base["loads"] / max(spec["loads"], 1)
    time_ratio = base["total_s"] / spec["total_s"]
    load_time = base["load_s"] / max(spec["load_s"], 1e-9)
    render = base["render_s"] / max(spec["render_s"], 1e-9)
    line = (f"{integrator} cache={round(100 * fraction)}% {config}: loads_ratio={loads:.2f} "
            f"time_ratio={time_ratio:.2f} load_time_ratio={load_time:.2f} "
            f"render_ratio={render:.2f} "
            f"loads_over_floor={spec['loads'] / max(spec['floor'], 1):.2f}")
    if config == "paper-faithful":
        line += f"  [{SPRAY}]"
    wins = [what for what, ratio in (("loads", loads), ("time", time_ratio)) if ratio < 1]
    return line + (f"  <- the baseline wins on {' and '.join(wins)}" if wins else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few-minute subset")
    parser.add_argument("--ablation", action="store_true",
                        help="also every switch combination (PT, 25%% cache, first scene)")
    parser.add_argument("--ray-sweep", action="store_true",
                        help="also the strongest PT 25%% comparison with 4x and 16x the paths "
                             "(first scene)")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    width, height = plan["image"]
    for spec in plan["scenes"]:
        store = scene(*spec)
        n = len(store.domains)
        if spec is plan["scenes"][0]:
            warm_up(store, plan)
        print(f"\n## scene {spec[0]} {spec[1]}^3: {store.n_triangles:,} triangles in {n} domains, "
              f"{width}x{height}, {plan['spp']} spp, {plan['shadow_samples']} shadow rays, "
              f"{plan['bounces']} bounces\n", flush=True)
        print(HEADER, flush=True)
        for fraction in plan["caches"]:
            cache = max(1, math.ceil(fraction * n))
            for integrator in ("pt", "ao"):
                st = settings(plan, integrator)
                for config, switches in CONFIGS.items():
                    base = run(store, st, "image", cache, **switches)
                    spec_run = run(store, st, "spec-ooc", cache, **switches)
                    print(row(integrator, config, base, n))
                    print(row(integrator, config, spec_run, n))
                    print(comparison(integrator, fraction, config, base, spec_run), flush=True)
        if spec is plan["scenes"][0]:
            sweep(store, plan)
            if args.ray_sweep:
                ray_sweep(store, plan)
            if args.ablation:
                ablation(store, plan)


def warm_up(store: Store, plan: dict) -> None:
    """One untimed render per schedule before anything is timed. Without it the first timed
    render (the baseline's, which runs first) also pays numba's first kernel loads and the
    first touches of code and data: measured 0.97-1.12 s warm against 1.26-1.32 s first for
    the same baseline render, which made ``time_ratio`` 1.2-1.4 where it is 1.0."""
    start = time.perf_counter()
    cache = max(1, math.ceil(0.25 * len(store.domains)))
    for scheduler in ("image", "spec-ooc"):
        run(store, settings(plan, "pt"), scheduler, cache, **CONFIGS["strongest"])
    print(f"warm-up: one untimed render per schedule, {time.perf_counter() - start:.1f} s",
          flush=True)


def settings(plan: dict, integrator: str) -> RenderSettings:
    width, height = plan["image"]
    return RenderSettings(width=width, height=height, spp=plan["spp"], integrator=integrator,
                          bounces=plan["bounces"], shadow_samples=plan["shadow_samples"])


def ablation(store: Store, plan: dict) -> None:
    """Each switch alone, for both schedules: PT at a 25 % cache."""
    n = len(store.domains)
    cache = max(1, math.ceil(0.25 * n))
    st = settings(plan, "pt")
    print(f"\n### switches (pt, cache {cache} of {n} domains)\n")
    print("| scheduler | resident first | preload | loads | floor | untraced loads | load wait s "
          "| total s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    for scheduler in ("image", "spec-ooc"):
        for resident_first in (False, True):
            for preload in (False, True):
                r = run(store, st, scheduler, cache, resident_first=resident_first,
                        preload=preload)
                print(f"| {scheduler} | {'yes' if resident_first else 'no'} "
                      f"| {'yes' if preload else 'no'} | {r['loads']} | {r['floor']} "
                      f"| {r['untraced']} | {r['wait_s']:.2f} | {r['total_s']:.2f} |", flush=True)
    print(f"\n### spec-ooc's own switches (pt, strongest, cache {cache} of {n} domains)\n")
    print("| serve before evict | rescore | preload | loads | floor | render s | total s |")
    print("| --- | --- | --- | --- | --- | --- | --- |", flush=True)
    for serve in (False, True):
        for rescore in (False, True):
            for preload in (False, True):
                r = run(store, st, "spec-ooc", cache, resident_first=True, preload=preload,
                        ablation=SpeculationRules(serve, rescore))
                print(f"| {'yes' if serve else 'no'} | {'yes' if rescore else 'no'} "
                      f"| {'yes' if preload else 'no'} | {r['loads']} | {r['floor']} "
                      f"| {r['render_s']:.2f} | {r['total_s']:.2f} |", flush=True)


def ray_sweep(store: Store, plan: dict) -> None:
    """The strongest PT comparison at a 25 % cache with 1x, 4x and 16x the plan's paths (2x the
    width and height, then also 4x the samples): both schedules trace the same paths each time."""
    n = len(store.domains)
    cache = max(1, math.ceil(0.25 * n))
    width, height = plan["image"]
    print(f"\n### paths sweep (pt, strongest, cache {cache} of {n} domains)\n")
    print("| image | spp | paths | image loads | spec-ooc loads | loads_ratio | time_ratio |")
    print("| --- | --- | --- | --- | --- | --- | --- |", flush=True)
    for scale, spp_scale in ((1, 1), (2, 1), (2, 4)):
        sized = {**plan, "image": (width * scale, height * scale), "spp": plan["spp"] * spp_scale}
        st = settings(sized, "pt")
        base = run(store, st, "image", cache, **CONFIGS["strongest"])
        spec_run = run(store, st, "spec-ooc", cache, **CONFIGS["strongest"])
        w, h = sized["image"]
        print(f"| {w}x{h} | {sized['spp']} | {w * h * sized['spp']:,} | {base['loads']} "
              f"| {spec_run['loads']} | {base['loads'] / max(spec_run['loads'], 1):.2f} "
              f"| {base['total_s'] / spec_run['total_s']:.2f} |", flush=True)


def sweep(store: Store, plan: dict) -> None:
    """Fig. 8: history depth H = 1..B at a 25 % cache (PT, strongest configuration)."""
    n = len(store.domains)
    cache = max(1, math.ceil(0.25 * n))
    st = settings(plan, "pt")
    print(f"\n### history depth sweep (pt, strongest, cache {cache} of {n} domains)\n")
    print("| H | loads | load s | render s | total s | wasted speculative rays |")
    print("| --- | --- | --- | --- | --- | --- |", flush=True)
    for h in range(1, plan["bounces"] + 1):
        r = run(store, st, "spec-ooc", cache, history_depth=h, **CONFIGS["strongest"])
        print(f"| {h} | {r['loads']} | {r['load_s']:.2f} | {r['render_s']:.2f} "
              f"| {r['total_s']:.2f} | {r['wasted']:,} of {r['speculative']:,} |", flush=True)


if __name__ == "__main__":
    main()
