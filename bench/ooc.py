"""Out-of-core scheduling: SpRay's speculative schedule against the baseline (SpRay Figs. 6, 8).

Generates (or reuses, in .bench_cache/) Richtmyer-Meshkov-like scenes split into domains and
renders them with domain caches of a fraction of the domains and with every domain cached,
with both schedules, in one run. Every load is a real disk read (``cold_reads``: the kernel
drops a domain's pages as it is read) plus the BVH build, which the papers count in load time;
the ``200MB/s`` storage also holds every load to a parallel file system's share of bandwidth
(``load_bandwidth``).

Both schedules run in each configuration, and each is compared only with the other in the
same one (the switches are ``JobOptions`` fields, the same for both):

* ``paper-faithful``: as the papers describe them: domains loaded sequentially (SpRay 5.1.1,
  "data loading is run sequentially"), the baseline's fullest queue first (Listing 1),
  spec-ooc's pure traversal-score order (Listing 2), least-recently-used eviction;
* ``strongest``: both with the preloader thread (each schedule's ``likely_next``) and the
  resident-first rule (domains in memory are served before anything is loaded); with it,
  spec-ooc also serves a resident domain's new rays when the cache is about to evict it
  (``serve_before_evict``) and re-ranks the rest of a round before each pick (``rescore``);
  the baseline serves a resident domain's rays as soon as they arrive (so never evicts one
  with rays waiting) and picks its fullest queue afresh each time; neither builds ahead;
* ``strongest+ahead``: ``strongest`` with one slot of each cache kept for the next domain to
  load, built while the schedule names no preload (``JobOptions.build_ahead``, off by
  default);
* ``strongest+demand``: ``strongest`` with eviction by demand for both
  (``eviction="demand"``: the resident domain the schedule will need last by its own order
  goes first; the baseline's emptiest queue, spec-ooc's latest in its round).

Each cell runs both schedules ``--repeats`` times (default 3; ``--large`` runs its
paper-faithful cells once, with cold reads only), interleaved and alternating
which goes first, after one untimed render per schedule (``warm_up``); the tables give the
per-field medians. Per schedule: loads; "Belady", the fewest loads its own access sequence
allows with that cache (``schedule.belady``); "floor", the domains any ray was traced against
(each loaded at least once); untraced loads (wrong preloads); GB read; load and load-wait
seconds and the wait's share of the total; "render s", the render thread outside loads (the
schedule deciding, spec-ooc's filtering included, and tracing); the process's CPU seconds
(every thread's: reads, Embree's builds, traces, decisions) and the cores they kept busy; and
O(c), the out-of-core overhead: total time over the same schedule's with every domain cached
on the same storage.
Each comparison line gives ``time_ratio=``, ``loads_ratio=``, ``load_time_ratio=`` and
``render_ratio=`` (baseline / spec-ooc) and, for both schedules, ``overhead=``,
``loads_over_floor=``, ``loads_over_belady=`` and ``tail_loads=`` (``a/b/n``: of its ``n``
loads, ``a`` bought fewer than 100 ray queries while they stayed resident and ``b`` fewer than
1,000: issue 40's tail loads, whose read and build buy almost nothing); a ``HEADLINE`` line
per cache and storage sets spec-ooc's fastest configuration against the baseline's fastest
(both with preloading and resident-first: every switch spec-ooc gets, the baseline gets)
beside the goals of issue 25 (1.3x, O(25 %) <= 1.5); its ``overhead=`` is measured in pairs,
each run at the cache next to one with every domain cached (``paired_overheads``: the cells'
O(c), ``overhead_cells=``, divides by a cell run minutes before, on a machine whose speed
drifts), with ``cpu_bound_overhead=``: spec-ooc's
CPU seconds over the cores, over its all-cached time, the least O(c) its loads and traces
allow on this machine however well they overlap. Every render of the tables is one pass,
which is what ``vastray render`` runs out of core by default (issue 40: out of core, where
nothing reads the image between passes, the CLI renders in one pass; same tiles, same loads;
the 100 % cells, in core, are one pass here where the CLI would render passes). The passes
section then sets the CLI's own renders (``vastray.render``, its plan and defaults) beside one
pass, in one process and on 2 nodes, and prints ``passes_loads_ratio=`` (CLI default / one
pass), ``passes_kept_loads_ratio=`` (the CLI with ``--max-pass-spp 16``, the passes a
checkpoint gets), ``passes_apart_loads_ratio=`` (the CLI with ``--target-error``, whose
passes end apart, the next ones traced on the current one's loads, as with a reference),
``passes_timed_loads_ratio=`` (the CLI with a ``--time-limit`` that never stops: the passes
its rule may still grant traced ahead), ``passes_alone_loads_ratio=`` (``--target-error``
with ``--passes-alone``: each pass alone) and ``passes_timed_spp=`` (the samples a pixel a
``--time-limit`` of 1.5x and of 2.5x the one-pass render's seconds reaches, traced ahead /
with ``--passes-alone``), with ``time_limit_overruns=`` (how many of those renders ended
past their limit). Then
(not with ``--large``) the history-depth sweep of Fig. 8
(H = 1..B for B = 3, strongest). With every domain cached nothing is evicted or built
ahead, so ``strongest+ahead``'s and ``strongest+demand``'s 100 % cells are ``strongest``'s.
``--ablation`` adds every switch combination for both schedules, and spec-ooc's own
switches (PT, 25 % cache, first scene).
``--ray-sweep`` adds the strongest PT comparison at a 25 % cache with 4x and 16x the paths
(first scene).

    python bench/ooc.py            # full run (hours on 2 cores)
    python bench/ooc.py --quick    # a few minutes (1.2 M triangles, cold reads only)
    python bench/ooc.py --large    # the large-domain regime (see LARGE; about 20 min on 2 cores)
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import vastray
from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.request import DEFAULT_NODE_SAMPLES_IN_FLIGHT
from vastray.scene.bvh_choice import CHOICES as BVH_CHOICES
from vastray.scene.bvh_choice import describe as describe_bvh
from vastray.scene.generate import generate
from vastray.scene.manifest import VERSION
from vastray.scene.store import Store
from vastray.schedule.spec_ooc import SpeculationRules

CACHE = Path(__file__).resolve().parent.parent / ".bench_cache"

FULL = {
    "scenes": [("rm", 1400, (5, 5, 4)), ("rm", 1400, (2, 2, 2))],
    "image": (64, 48), "spp": 32, "shadow_samples": 16, "bounces": 3,
    "caches": (0.25, 0.5, 0.75), "integrators": ("pt", "ao"), "storage": ("cold", "200MB/s"),
}
QUICK = {
    "scenes": [("rm", 320, (5, 5, 4)), ("rm", 320, (2, 2, 2))],
    "image": (32, 24), "spp": 8, "shadow_samples": 4, "bounces": 3,
    "caches": (0.25,), "integrators": ("pt", "ao"), "storage": ("cold",),
}
#: SpRay's regime at this machine's scale: 30.3 M triangles in 72 domains of 65 k-822 k,
#: whose loads (cold reads, BVH builds) cost 2-8x the rendering they enable; PT only.
#: To keep within its 30 minutes (issue 40) the paper-faithful pair runs once a cell and with
#: cold reads only (SpRay's comparison, not the headline), and passes are compared in one
#: process only (the 2-node comparison is ``--quick``'s and the full run's).
LARGE = {
    "scenes": [("rm", 1600, (6, 6, 2))],
    "image": (128, 96), "spp": 8, "shadow_samples": 1, "bounces": 3,
    "caches": (0.25, 0.5), "integrators": ("pt",), "storage": ("cold", "200MB/s"),
    "paper_faithful": {"repeats": 1, "storage": ("cold",)}, "passes_nodes": (None,),
}


def scene(name: str, resolution: int, grid: tuple[int, int, int]) -> Store:
    path = CACHE / f"{name}-{resolution}-{'x'.join(map(str, grid))}.store"
    if not (path / "manifest.json").is_file() or Store(path).manifest["version"] < VERSION:
        # (again where an older vastray wrote it: a store before version 5 has no occupancy
        # masks, so both schedules would queue rays into every domain their boxes cross)
        print(f"generating {path.name} ...", file=sys.stderr, flush=True)
        generate(name, path, resolution, grid=grid, seed=0, overwrite=True, progress=True)
    return Store(path)


CONFIGS = {  # name -> JobOptions switches, the same for both schedules
    "paper-faithful": {"preload": False, "resident_first": False},
    # the CLI's defaults: neither builds ahead
    "strongest": {"preload": True, "resident_first": True, "build_ahead": False},
    # both keep a slot of the cache for a domain built ahead (JobOptions.build_ahead)
    "strongest+ahead": {"preload": True, "resident_first": True, "build_ahead": True},
    "strongest+demand": {"preload": True, "resident_first": True, "eviction": "demand",
                         "build_ahead": False},
}
#: The CLI's defaults, for the renders outside the tables (passes, sweeps).
DEFAULTS = {"preload": True, "resident_first": True}
#: Configurations whose all-cached cells are strongest's: with every domain cached nothing is
#: evicted and nothing is built ahead (no slot to keep).
SAME_ALL_CACHED = ("strongest+ahead", "strongest+demand")
#: How domains reach memory: every load a real disk read (cold page cache), and the same with
#: a parallel file system's share of bandwidth per node emulated on top.
STORAGE = {
    "cold": {"cold_reads": True},
    "200MB/s": {"cold_reads": True, "load_bandwidth": 200.0},
}
SCHEDULERS = ("image", "spec-ooc")


def run(store: Store, settings: RenderSettings, scheduler: str, cache: int,
        history_depth: int | None = None, ablation: SpeculationRules | None = None,
        **switches) -> dict:
    """One render; ``switches`` are more ``JobOptions`` fields (``preload``,
    ``resident_first``, ``eviction``, ``load_bandwidth``), the same for both schedules. Every
    load is a cold read unless ``cold_reads=False`` is given."""
    switches = {"cold_reads": True, **switches}
    start, cpu = time.perf_counter(), process_cpu_s()
    result = render_out_of_core(store, SceneConfig(), settings,
                                options=JobOptions(scheduler=scheduler, cache=cache,
                                                   history_depth=history_depth, **switches),
                                progress=False, ablation=ablation)
    total, cpu = time.perf_counter() - start, process_cpu_s() - cpu
    c = result.counters
    return {
        "scheduler": scheduler, "cache": cache, "loads": c["loads"],
        "floor": c["domains_traced"], "untraced": c["untraced_loads"],
        "belady": c["belady_loads"], "bytes": c["bytes_loaded"],
        "load_s": c["load_s"], "wait_s": c["load_wait_s"],
        "render_s": result.seconds["render"] + result.seconds["schedule"],  # deciding + tracing
        "total_s": total, "wait_share": c["load_wait_s"] / max(total, 1e-9), "cpu_s": cpu,
        "wasted": c.get("wasted_rays", 0), "speculative": c.get("speculative_rays", 0),
        "under_100": c["loads_under_100_queries"], "under_1000": c["loads_under_1000_queries"],
    }


def process_cpu_s() -> float:
    """CPU seconds this process has used so far, every thread's (user and system): a render's
    reads, builds (Embree's threads), traces and decisions all run in it."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


#: The cores this process may run on: a render's CPU seconds over these are the least time
#: it could take however well its loads overlapped its traces.
CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def median_run(runs: list[dict]) -> dict:
    """The per-field median of repeated runs of one schedule in one cell (loads can differ
    between runs where a preload races the render thread)."""
    out = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            out[key] = statistics.median(r[key] for r in runs)
    out["runs"] = len(runs)
    return out


def cell(store: Store, st: RenderSettings, cache: int, switches: dict,
         repeats: int) -> dict[str, dict]:
    """Both schedules in one cell, ``repeats`` runs each, interleaved and alternating which
    goes first (a drifting machine shifts both alike); returns each schedule's median run."""
    runs: dict[str, list[dict]] = {name: [] for name in SCHEDULERS}
    for i in range(repeats):
        for scheduler in SCHEDULERS if i % 2 == 0 else SCHEDULERS[::-1]:
            runs[scheduler].append(run(store, st, scheduler, cache, **switches))
    return {name: median_run(r) for name, r in runs.items()}


HEADER = ("| integrator | storage | config | scheduler | cache | loads | Belady | floor "
          "| untraced loads | GB read | load s | load wait s | wait share | render s | total s "
          "| CPU s (cores busy) | O(c) | wasted speculative rays |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- "
          "| --- | --- | --- | --- | --- |")


def row(integrator: str, storage: str, config: str, r: dict, n_domains: int,
        overhead: float | None) -> str:
    pct = round(100 * r["cache"] / n_domains)
    o = "" if overhead is None else f"{overhead:.2f}"
    return (f"| {integrator} | {storage} | {config} | {r['scheduler']:8} "
            f"| {r['cache']:3.0f} ({pct:3d}%) | {r['loads']:5.0f} | {r['belady']:5.0f} "
            f"| {r['floor']:.0f} | {r['untraced']:.0f} | {r['bytes'] / 1e9:.2f} "
            f"| {r['load_s']:7.2f} | {r['wait_s']:7.2f} | {r['wait_share']:.2f} "
            f"| {r['render_s']:7.2f} | {r['total_s']:7.2f} "
            f"| {r['cpu_s']:6.2f} ({r['cpu_s'] / max(r['total_s'], 1e-9):.2f}) | {o} "
            f"| {r['wasted']:,.0f} of {r['speculative']:,.0f} |")


SPRAY = "SpRay Fig. 6 (RM/Enzo, paper-faithful): 1.7-2.3x total, 2.7-3.2x load time"


def comparison(integrator: str, fraction: float, storage: str, config: str,
               cells: dict[str, dict], overheads: dict[str, float | None]) -> str:
    """One line of ratios, baseline / speculative (loads, total time, load time, and the
    render thread's time outside loads: the schedule deciding, spec-ooc's filtering included,
    and tracing), then per schedule its out-of-core overhead O(c) = T(c) / T(every domain
    cached, same schedule and storage) and its loads over its floor and over the Belady count
    of its own access sequence."""
    base, spec = cells["image"], cells["spec-ooc"]
    loads = base["loads"] / max(spec["loads"], 1)
    time_ratio = base["total_s"] / spec["total_s"]
    load_time = base["load_s"] / max(spec["load_s"], 1e-9)
    render = base["render_s"] / max(spec["render_s"], 1e-9)

    def each(values: dict[str, float | None]) -> str:
        return ",".join(f"{name}:{'-' if v is None else f'{v:.2f}'}" for name, v in values.items())

    line = (f"{integrator} cache={round(100 * fraction)}% {storage} {config}: "
            f"time_ratio={time_ratio:.2f} loads_ratio={loads:.2f} "
            f"load_time_ratio={load_time:.2f} render_ratio={render:.2f} "
            f"overhead={each(overheads)} "
            f"loads_over_floor={each({n: c['loads'] / max(c['floor'], 1) for n, c in cells.items()})} "
            f"loads_over_belady={each({n: c['loads'] / max(c['belady'], 1) for n, c in cells.items()})} "
            f"tail_loads={tails(cells)}")
    if config == "paper-faithful":
        line += f"  [{SPRAY}]"
    wins = [what for what, ratio in (("loads", loads), ("time", time_ratio)) if ratio < 1]
    return line + (f"  <- the baseline wins on {' and '.join(wins)}" if wins else "")


def tails(cells: dict[str, dict]) -> str:
    """Per schedule, its loads that bought fewer than 100 and fewer than 1,000 ray queries
    while they stayed resident, out of all its loads (``image:a/b/n,spec-ooc:...``)."""
    return ",".join(f"{name}:{c['under_100']:.0f}/{c['under_1000']:.0f}/{c['loads']:.0f}"
                    for name, c in cells.items())


def best_configs(fraction: float, storage: str, results: dict) -> dict[str, tuple] | None:
    """Each schedule's fastest configuration at ``fraction`` and ``storage`` among those with
    preloading and the resident-first rule (the baseline gets every switch spec-ooc gets):
    scheduler -> (median total s, config); None before any such cell has run."""
    best = {}
    for scheduler in SCHEDULERS:
        options = [(results[(fraction, storage, config)][scheduler]["total_s"], config)
                   for config in CONFIGS if config != "paper-faithful"
                   and (fraction, storage, config) in results]
        if not options:
            return None
        best[scheduler] = min(options)
    return best


def paired_overheads(store: Store, st: RenderSettings, cache: int, storage: str,
                     best: dict[str, tuple], repeats: int) -> dict[str, float]:
    """O(c) of each schedule's best configuration measured in pairs: each run at ``cache``
    next to one with every domain cached, the same switches and storage, ``repeats`` pairs
    alternating which goes first; the median of the pairs' ratios.

    Why: the cells' O(c) divides by the 100 % cell, run minutes before on a machine whose
    speed drifts by 10-25 % from one hour to the next (a slow spell inflated one run's 25 %
    cells' CPU seconds by 44 % over the same renders an hour earlier), so a ratio of two
    renders is measured as every other ratio here is, interleaved."""
    ratios: dict[str, list[float]] = {name: [] for name in SCHEDULERS}
    whole = len(store.domains)
    for i in range(repeats):
        for scheduler in SCHEDULERS:
            switches = {**CONFIGS[best[scheduler][1]], **STORAGE[storage]}
            sizes = (cache, whole) if (i + (scheduler == "image")) % 2 == 0 else (whole, cache)
            times = {size: run(store, st, scheduler, size, **switches)["total_s"]
                     for size in sizes}
            ratios[scheduler].append(times[cache] / times[whole])
    return {name: statistics.median(r) for name, r in ratios.items()}


def headline(fraction: float, storage: str, results: dict,
             paired: dict[str, float] | None = None) -> str | None:
    """Our best out-of-core schedule against the strongest baseline at ``fraction`` (each the
    fastest of its configurations, ``best_configs``), and spec-ooc's overhead O(c): measured
    in pairs (``paired``, from ``paired_overheads``) as ``overhead=``, and from the cells as
    ``overhead_cells=``."""
    best = best_configs(fraction, storage, results)
    if best is None:
        return None
    (base_t, base_c), (spec_t, spec_c) = best["image"], best["spec-ooc"]
    full = results.get((1.0, storage, spec_c))
    cells = "-" if full is None else f"{spec_t / full['spec-ooc']['total_s']:.2f}"
    overhead = cells if paired is None else f"{paired['spec-ooc']:.2f}"
    base_o = "" if paired is None else f"; the baseline's {paired['image']:.2f}"
    # however well loads overlapped traces, a render takes at least its CPU seconds over the
    # cores: the overhead that bound allows (issue 40's O(25 %) <= 1.5 needs it below 1.5)
    spec_cpu = results[(fraction, storage, spec_c)]["spec-ooc"]["cpu_s"]
    floor = "-" if full is None else f"{spec_cpu / CORES / full['spec-ooc']['total_s']:.2f}"
    ratio = base_t / spec_t
    verdict = ("neither wins by more than 5 %" if 1 / 1.05 < ratio < 1.05
               else "spec-ooc wins" if ratio > 1 else "the baseline wins")
    return (f"HEADLINE cache={round(100 * fraction)}% {storage}: best spec-ooc ({spec_c}) "
            f"{spec_t:.2f} s vs strongest baseline ({base_c}) {base_t:.2f} s: "
            f"time_ratio={ratio:.2f} (goal 1.30), spec-ooc overhead={overhead} "
            f"(goal 1.50; each run in a pair with an all-cached one{base_o}; "
            f"overhead_cells={cells}: over the 100 % cell; cpu_bound_overhead={floor}: its "
            f"{spec_cpu:.2f} CPU s over {CORES} cores, the least it could be); {verdict}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="a few-minute subset")
    size.add_argument("--large", action="store_true",
                      help="the large-domain regime (PT; cold reads and 200 MB/s; 25, 50 and "
                           "100%% caches; see LARGE)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="interleaved runs per schedule and cell; the tables give medians")
    parser.add_argument("--ablation", action="store_true",
                        help="also every switch combination (PT, 25%% cache, first scene)")
    parser.add_argument("--ray-sweep", action="store_true",
                        help="also the strongest PT 25%% comparison with 4x and 16x the paths "
                             "(first scene)")
    parser.add_argument("--bvh", choices=BVH_CHOICES, default="auto",
                        help="the BVH every render builds, as vastray render's --bvh (default: "
                             "auto, the CLI's: the fast BVH for stores of 8 M triangles or "
                             "more, such as --large's)")
    args = parser.parse_args()
    plan = dict(LARGE if args.large else QUICK if args.quick else FULL, bvh=args.bvh)
    width, height = plan["image"]
    started = time.perf_counter()
    for spec in plan["scenes"]:
        store = scene(*spec)
        n = len(store.domains)
        if spec is plan["scenes"][0]:
            warm_up(store, plan)
        print(f"\n## scene {spec[0]} {spec[1]}^3: {store.n_triangles:,} triangles in {n} domains "
              f"({sum(d.nbytes for d in store.domains) / 1e9:.2f} GB), {width}x{height}, "
              f"{plan['spp']} spp, {plan['shadow_samples']} shadow rays, {plan['bounces']} "
              f"bounces, BVH {describe_bvh(plan['bvh'], store.n_triangles)}; medians of "
              f"{args.repeats} interleaved runs per schedule\n", flush=True)
        print(HEADER, flush=True)
        fractions = sorted(set(plan["caches"]) | {1.0}, reverse=True)  # 100 % first: O(c)
        results: dict = {}
        for storage in plan["storage"]:
            for integrator in plan["integrators"]:
                st = settings(plan, integrator)
                for fraction in fractions:
                    cache = max(1, math.ceil(fraction * n))
                    for config, switches in CONFIGS.items():
                        repeats = args.repeats
                        if config == "paper-faithful" and "paper_faithful" in plan:
                            if storage not in plan["paper_faithful"]["storage"]:
                                continue
                            repeats = min(repeats, plan["paper_faithful"]["repeats"])
                        if fraction == 1.0 and config in SAME_ALL_CACHED:
                            # nothing is evicted or built ahead with every domain cached:
                            # strongest's cells are these
                            cells = results[(1.0, storage, "strongest")]
                        else:
                            cells = cell(store, st, cache, {**switches, **STORAGE[storage]},
                                         repeats)
                        results[(fraction, storage, config)] = cells
                        full = results[(1.0, storage, config)]
                        overheads = {name: cells[name]["total_s"] / full[name]["total_s"]
                                     for name in SCHEDULERS}
                        for name in SCHEDULERS:
                            print(row(integrator, storage, config, cells[name], n,
                                      overheads[name]))
                        print(comparison(integrator, fraction, storage, config, cells,
                                         overheads), flush=True)
                    if integrator == "pt" and fraction < 1.0:
                        best = best_configs(fraction, storage, results)
                        paired = None if best is None else paired_overheads(
                            store, st, cache, storage, best, args.repeats)
                        print(headline(fraction, storage, results, paired), flush=True)
        if spec is plan["scenes"][0]:
            passes(store, plan)
            if not args.large:  # --large keeps to its 30 minutes: Fig. 8 is the full run's
                sweep(store, plan)
            if args.ray_sweep:
                ray_sweep(store, plan)
            if args.ablation:
                ablation(store, plan)
    print(f"\nbench/ooc.py: {time.perf_counter() - started:.0f} s", flush=True)


#: Time limits of the passes section, in one-pass renders' seconds: the spp each reaches.
TIME_LIMITS = (1.5, 2.5)


def cli_run(store: Store, plan: dict, scheduler: str, cache: int, nodes: int | None,
            **passes) -> dict:
    """One render as ``vastray render`` runs it (``vastray.render``: the CLI's own plan,
    defaults and passes), every load a cold read; ``passes`` are more render options
    (``max_pass_spp=16`` keeps the passes a reference or checkpoint would see)."""
    width, height = plan["image"]
    start = time.perf_counter()
    out = vastray.render(store, width=width, height=height, spp=plan["spp"], integrator="pt",
                         bounces=plan["bounces"], shadow_samples=plan["shadow_samples"],
                         scheduler=scheduler, cache=cache, nodes=nodes, cold_reads=True,
                         bvh=plan["bvh"], progress=False, **passes)
    total = time.perf_counter() - start
    return {"loads": out.report["counters"]["loads"], "total_s": total,
            "passes": len(out.report["passes"]), "spp": out.report["passes"][-1]["spp"],
            "render_s": out.report["passes"][-1]["seconds"]}


def passes(store: Store, plan: dict) -> None:
    """What ``vastray render``'s passes cost out of core (issue 40): domain loads and seconds
    of the CLI's default render (one pass out of core when nothing reads the image between
    passes), of the CLI keeping its passes (``--max-pass-spp 16``: what a reference, a
    stopping rule or checkpoints get) and of one pass through ``render_out_of_core`` (the
    tables above), PT at a 25 % cache, cold reads, one process and 2 nodes (one process only
    where the plan says so: ``--large``)."""
    n = len(store.domains)
    cache = max(1, math.ceil(0.25 * n))
    st = settings(plan, "pt")
    print(f"\n### passes as the CLI renders them (pt, cache {cache} of {n} domains, cold reads)\n")
    print("| nodes | scheduler | one-pass loads | CLI default loads (passes) | CLI passes kept "
          "loads (passes) | CLI passes apart, traced ahead, loads | CLI time-limited, traced "
          "ahead, loads | CLI passes apart, each alone, loads | one-pass s | CLI default s | "
          "CLI passes kept s | apart, ahead s | time-limited, ahead s | apart, alone s | "
          + " | ".join(f"spp within {f:g}x one pass's s: ahead / alone" for f in TIME_LIMITS)
          + " |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
          "| ---: | ---: |" + " ---: |" * len(TIME_LIMITS))
    ratios: dict = {}
    overruns = {"ahead": [0, 0], "alone": [0, 0]}  # time-limited renders past / all
    for nodes in plan.get("passes_nodes", (None, 2)):
        for scheduler in SCHEDULERS:
            if nodes is None:
                one = run(store, st, scheduler, cache, **DEFAULTS)
            else:  # the distributed runtime's own one-pass render, the CLI's tile per node
                start = time.perf_counter()
                result = render_distributed(store.path, None, st, nodes, JobOptions(
                    scheduler=scheduler, cache=cache, cold_reads=True,
                    max_samples_in_flight=DEFAULT_NODE_SAMPLES_IN_FLIGHT))
                one = {"loads": result.counters["loads"],
                       "total_s": time.perf_counter() - start}
            default = cli_run(store, plan, scheduler, cache, nodes)
            kept = cli_run(store, plan, scheduler, cache, nodes, max_pass_spp=16)
            # passes apart: an error target that never stops (the next passes traced ahead),
            # a time limit that never stops (those its rule may still grant traced ahead),
            # and the error target with each pass alone
            ahead = cli_run(store, plan, scheduler, cache, nodes, target_error=1e-12)
            timed = cli_run(store, plan, scheduler, cache, nodes, time_limit=3600.0)
            alone = cli_run(store, plan, scheduler, cache, nodes, target_error=1e-12,
                            passes_alone=True)
            # what a user's time limit buys: the samples reached in 1.5x and 2.5x one pass's
            # time, traced ahead and alone
            reached = []
            for factor in TIME_LIMITS:
                limit = round(factor * one["total_s"], 2)
                runs = [cli_run(store, plan, scheduler, cache, nodes, time_limit=limit, **extra)
                        for extra in ({}, {"passes_alone": True})]
                reached.append([r["spp"] for r in runs])
                for r, name in zip(runs, ("ahead", "alone"), strict=True):
                    overruns[name][0] += r["render_s"] > limit
                    overruns[name][1] += 1
            where = "1 process" if nodes is None else f"{nodes} nodes"
            print(f"| {where} | {scheduler} | {one['loads']} | {default['loads']} "
                  f"({default['passes']}) | {kept['loads']} ({kept['passes']}) | "
                  f"{ahead['loads']} ({ahead['passes']}) | {timed['loads']} ({timed['passes']}) "
                  f"| {alone['loads']} ({alone['passes']}) | {one['total_s']:.2f} | "
                  f"{default['total_s']:.2f} | {kept['total_s']:.2f} | {ahead['total_s']:.2f} | "
                  f"{timed['total_s']:.2f} | {alone['total_s']:.2f} | "
                  + " | ".join(f"{a} / {b}" for a, b in reached) + " |", flush=True)
            ratios.setdefault(where, {})[scheduler] = (*(
                r["loads"] / one["loads"] for r in (default, kept, ahead, timed, alone)),
                reached)
    for where, by in ratios.items():
        tag = "" if where == "1 process" else "_nodes"
        print(f"passes_loads_ratio{tag}="
              + ",".join(f"{s}:{r[0]:.2f}" for s, r in by.items())
              + f" (CLI default / one pass, {where}; goal <= 1.1) "
              f"passes_kept_loads_ratio{tag}="
              + ",".join(f"{s}:{r[1]:.2f}" for s, r in by.items())
              + " (CLI with --max-pass-spp 16 / one pass) "
              f"passes_apart_loads_ratio{tag}="
              + ",".join(f"{s}:{r[2]:.2f}" for s, r in by.items())
              + " (CLI with --target-error, the next passes traced ahead / one pass) "
              f"passes_timed_loads_ratio{tag}="
              + ",".join(f"{s}:{r[3]:.2f}" for s, r in by.items())
              + " (CLI with --time-limit, traced ahead / one pass) "
              f"passes_alone_loads_ratio{tag}="
              + ",".join(f"{s}:{r[4]:.2f}" for s, r in by.items())
              + " (--target-error with --passes-alone: each pass alone) "
              f"passes_timed_spp{tag}="
              + ",".join(f"{s}:" + ";".join(f"{a}/{b}" for a, b in r[5]) for s, r in by.items())
              + " (spp reached within " + " and ".join(f"{f:g}x" for f in TIME_LIMITS)
              + " one pass's seconds: traced ahead / --passes-alone)", flush=True)
    print("time_limit_overruns=" + ",".join(f"{name}:{past}/{runs}"
                                             for name, (past, runs) in overruns.items())
          + " (time-limited renders whose last pass ended past the limit / all)", flush=True)


def warm_up(store: Store, plan: dict) -> None:
    """One untimed render per schedule before anything is timed. Without it the first timed
    render (the baseline's, which runs first) also pays numba's first kernel loads and the
    first touches of code and data: measured 0.97-1.12 s warm against 1.26-1.32 s first for
    the same baseline render, which made ``time_ratio`` 1.2-1.4 where it is 1.0."""
    start = time.perf_counter()
    cache = max(1, math.ceil(0.25 * len(store.domains)))
    for scheduler in ("image", "spec-ooc"):
        run(store, settings(plan, "pt"), scheduler, cache, **DEFAULTS)
    print(f"warm-up: one untimed render per schedule, {time.perf_counter() - start:.1f} s",
          flush=True)


def settings(plan: dict, integrator: str) -> RenderSettings:
    width, height = plan["image"]
    return RenderSettings(width=width, height=height, spp=plan["spp"], integrator=integrator,
                          bounces=plan["bounces"], shadow_samples=plan["shadow_samples"],
                          bvh=plan.get("bvh", "auto"))


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
        base = run(store, st, "image", cache, **DEFAULTS)
        spec_run = run(store, st, "spec-ooc", cache, **DEFAULTS)
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
        r = run(store, st, "spec-ooc", cache, history_depth=h, **DEFAULTS)
        print(f"| {h} | {r['loads']} | {r['load_s']:.2f} | {r['render_s']:.2f} "
              f"| {r['total_s']:.2f} | {r['wasted']:,} of {r['speculative']:,} |", flush=True)


if __name__ == "__main__":
    main()
