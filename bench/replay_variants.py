"""Five design choices of the node runtimes compared by replay (``vastray.sim.replay``), each
side on the same constants, recording and nodes in one run.

    python bench/replay_variants.py --quick   # 2^18 paths, P = 1, 64, 1,024 (about 7 min)
    python bench/replay_variants.py           # 2^20 paths, P = 1, 4, ... 1,024 (about 4 min)

1. **All-reductions**: over the butterfly of ranks (recursive doubling, log2 P exchange steps:
   the product's, ``actors/tree_reduce.py``) against the first design's reduce up the binary
   tree and broadcast back down (2 ceil(log2 P) steps). Strong scaling of the frame
   ``bench/simulate.py`` scales (cosmo 160³ in 1,439 domains, a node caching a quarter of
   them, 200 MB/s storage); ``speedup_<P>_<reduction>=`` per scheduler that all-reduces.
2. **The tile of the domain-decomposition schedulers**: the product's (65,536 paths a job
   or 4,096 a node, whichever is more: ``job_options.default_tile``, since session 50)
   against the job's 65,536 paths on any number of nodes (before) and 65,536 paths per
   node; and ``dynamic``'s rule 3 as the product has it (busy nodes take unheld domains
   that keep the round as short, ``schedule.dynamic``) against the paper's (idle nodes
   only), on the product's tile and on the fixed one. Weak scaling at 4,096 paths a node;
   ``weak_<P>_<tile>=`` efficiencies T(1)/T(P), ``dynamic_weak_<P>_<rule>_<tile>=``.
3. **``dynamic``'s tiles in flight**: the next tile taken in while the last one's rays thin
   out, up to two tiles (the product's, ``actors/dynamic_frame.py``) against one tile at a
   time (before session 41), in tiles of 65,536 paths (the product's tile is one frame from
   64 nodes on). Strong scaling of the frame of 1.; ``dynamic_seconds_<tiles>=``
   the virtual seconds by P, ``dynamic_speedup_<tiles>=`` T(1)/T(P), each side against its
   own T(1).
4. **The sort-first schedules' share of the image**: a band of the image a node cut at
   equal estimated cost (``ownership.weighted_band_cuts`` over ``schedule.image_cost``'s
   weights: the product's for ``image``) against a band of equal paths (the product's for
   ``spec-ooc``, and both schedulers' before session 49) and up to 4 blocks a node dealt
   round robin (shares spread over the image: balanced, but each node meets more domains;
   on real nodes sharing this machine's cores they lost, session 42). Strong scaling of the
   frame of 1. and weak scaling at 4,096 paths a node;
   ``sort_first_speedup_<P>_<share>=`` and ``sort_first_weak_<P>_<share>=`` per
   scheduler (share ``cost``, ``equal`` or ``blocks``), against the same T(1) (one node
   has one share either way).

5. **``spec-insitu``'s routes and holders**: copies over the two hops of ``schedule.relay``
   (the product's since session 52) against a batch straight to each node with copies and the
   batches' (P,) counts all-reduced first (before); and more holders for the domains the
   camera rays cross most (``ownership.insitu_holders``, bounded by the bytes of the node
   owning the most: the product's since session 52) against each domain held by its owner
   alone (before, SpRay's in situ). Weak scaling at 4,096 paths a node;
   ``insitu_weak_<variant>=`` efficiencies T(1)/T(P) by P.

The constants are ``--costs`` (default ``.bench_cache/costs.json``, which ``bench/simulate.py``
writes; else a quick calibration now); the nodes' own code is fitted first, as
``bench/simulate.py`` does (about 75 s).
"""

from __future__ import annotations

import argparse
import time

import replay_scaling as rs
from bench_scenes import CACHE, cached_cosmo, cached_rm
from simulate import SCALING_GRID, scaling_options

from vastray.actors.job_options import MIN_NODE_SHARE, default_tile
from vastray.schedule import image_cost, ownership
from vastray.sim.calibrate import calibrate
from vastray.sim.costs import CostModel
from vastray.sim.replay import DEFAULT_TILE, REDUCTIONS

#: Schedulers whose frames make all-reductions (the others' times do not depend on them).
REDUCING = ("domain", "dynamic", "spec-insitu")
#: Domain-decomposition schedulers the tile applies to.
TILED = ("domain", "dynamic", "spec-insitu", "async")
#: The sort-first schedulers.
SORT_FIRST = rs.SORT_FIRST
#: Section 4's shares of the image a sort-first node renders: name -> (blocks a node,
#: schedulers whose bands are cut by cost, label); the product's: ``image`` cut by cost,
#: ``spec-ooc`` equal (``image_cost.CUT_BY_COST``).
SHARES = {"cost": (1, frozenset(SORT_FIRST), "a band cut by cost"),
          "equal": (1, frozenset(), "a band of equal paths"),
          "blocks": (4, frozenset(), "up to 4 blocks dealt round robin")}
#: A domain-decomposition job's paths in flight before session 50, on any number of nodes.
JOB_TILE = DEFAULT_TILE
#: Section 2's tiles by node count: the product's, the fixed job's, and one a node.
TILES = {"product": lambda nodes: default_tile("domain", nodes),
         "job": lambda nodes: JOB_TILE, "node": lambda nodes: JOB_TILE * nodes}
TILE_LABELS = {"product": f"{JOB_TILE:,} or {MIN_NODE_SHARE:,} a node (the product)",
               "job": f"{JOB_TILE:,} paths a job (before)",
               "node": f"{JOB_TILE:,} paths a node"}


def constants(path: str | None) -> CostModel:
    default = CACHE / "costs.json"
    if path is None and not default.exists():
        print("+ calibrate --quick (no .bench_cache/costs.json yet)", flush=True)
        costs = calibrate(cached_rm(64, (3, 3, 2)).path, quick=True)
        costs.save(default)
        return costs
    return CostModel.load(path or default)


def strong_by_reduction(store, costs: CostModel, quick: bool, counts) -> dict:
    """{reduction: {scheduler: {P: seconds}}} of the strong-scaling frame."""
    settings = rs.STRONG_QUICK if quick else rs.STRONG
    crossings = rs.recording(store, settings)
    times: dict = {}
    for reduction in REDUCTIONS:
        replay = rs.replay_of(store, crossings, costs.warm().with_cores(None),
                              decisions=rs.scaling_decisions(store, settings),
                              reduction=reduction)
        jobs = [(s, n, rs.node_cache(len(store.domains), n, s)) for s in REDUCING for n in counts]
        for (scheduler, nodes, _), result in zip(jobs, rs.replayed(replay, jobs), strict=True):
            times.setdefault(reduction, {}).setdefault(scheduler, {})[nodes] = result.seconds
            print(f"  {reduction:9s} {scheduler:11s} P={nodes:5d}: {result.seconds:8.4f} s "
                  f"virtual ({result.counters['rounds']:,} synchronisations)", flush=True)
    return times


def dynamic_by_tiles(store, costs: CostModel, quick: bool, counts) -> dict:
    """{tiles in flight: {P: (seconds, all-reductions)}} of ``dynamic`` in the strong-scaling
    frame (``dynamic_frame.MAX_TILES``, set before the replays are forked), in tiles of
    ``JOB_TILE`` paths on every node count (the product's tile holds the whole frame from 64
    nodes on, where tiles in flight change nothing)."""
    from vastray.actors import dynamic_frame

    settings = rs.STRONG_QUICK if quick else rs.STRONG
    crossings = rs.recording(store, settings)
    product = dynamic_frame.MAX_TILES
    times: dict = {}
    try:
        for tiles in (product, 1):
            dynamic_frame.MAX_TILES = tiles
            replay = rs.replay_of(store, crossings, costs.warm().with_cores(None),
                                  decisions=rs.scaling_decisions(store, settings),
                                  tile=JOB_TILE)
            jobs = [("dynamic", n, rs.node_cache(len(store.domains), n, "dynamic")) for n in counts]
            for (_, nodes, _), result in zip(jobs, rs.replayed(replay, jobs), strict=True):
                times.setdefault(tiles, {})[nodes] = (result.seconds, result.counters["rounds"])
                print(f"  dynamic, {tiles} tile(s) in flight, P={nodes:5d}: "
                      f"{result.seconds:8.4f} s virtual ({result.counters['rounds']:,} "
                      "all-reductions)", flush=True)
    finally:
        dynamic_frame.MAX_TILES = product
    return times


def sort_first_by_share(store, costs: CostModel, quick: bool, counts) -> dict:
    """{share: {"strong" | "weak": {scheduler: {P: seconds}}}} of the sort-first schedules,
    each share of ``SHARES`` set (``ownership.BLOCKS_PER_NODE``, ``image_cost.CUT_BY_COST``) before
    the replays are forked."""
    settings = rs.STRONG_QUICK if quick else rs.STRONG
    crossings = rs.recording(store, settings)
    base, own, fitted = rs.weak_setup(store, costs, quick)
    product = ownership.BLOCKS_PER_NODE, image_cost.CUT_BY_COST
    times: dict = {}
    try:
        for share, (blocks, weighted, _) in SHARES.items():
            ownership.BLOCKS_PER_NODE, image_cost.CUT_BY_COST = blocks, weighted
            frames = [("strong", nodes, crossings) for nodes in counts]
            frames += [("weak", nodes, rs.weak_frame(base, nodes)) for nodes in counts]
            for kind, nodes, frame in frames:
                replay = (rs.replay_of(store, frame, costs.warm().with_cores(None),
                                       decisions=rs.scaling_decisions(store, settings))
                          if kind == "strong" else
                          rs.replay_of(store, frame, own, activations=fitted))
                jobs = [(s, nodes, rs.node_cache(len(store.domains), nodes, s))
                        for s in SORT_FIRST]
                for scheduler, result in zip(SORT_FIRST, rs.replayed(replay, jobs),
                                             strict=True):
                    times.setdefault(share, {}).setdefault(kind, {}).setdefault(
                        scheduler, {})[nodes] = result.seconds
                    print(f"  {share:6s} {kind:6s} {scheduler:8s} P={nodes:5d} "
                          f"({frame.n_paths:,} paths): {result.seconds:8.4f} s virtual "
                          f"({result.counters['loads']:,} loads)", flush=True)
    finally:
        ownership.BLOCKS_PER_NODE, image_cost.CUT_BY_COST = product
    return times


def weak_by_tile(store, costs: CostModel, quick: bool, counts) -> dict:
    """{tile name: {scheduler: {P: seconds}}} at ``WEAK_PATHS_PER_NODE`` paths a node, and
    under ``"paper <tile>"`` ``dynamic`` with the paper's rule 3."""
    base, own, fitted = rs.weak_setup(store, costs, quick)
    times: dict = {}
    for nodes in counts:
        frame = rs.weak_frame(base, nodes)
        for name, tile in TILES.items():
            for fill_busy in (True, False):
                schedulers = TILED if fill_busy else ("dynamic",)
                if name == "node" and not fill_busy:
                    continue
                replay = rs.replay_of(store, frame, own, activations=fitted,
                                      tile=tile(nodes), fill_busy=fill_busy)
                jobs = [(s, nodes, rs.node_cache(len(store.domains), nodes, s))
                        for s in schedulers]
                key = name if fill_busy else f"paper {name}"
                for scheduler, result in zip(schedulers, rs.replayed(replay, jobs), strict=True):
                    times.setdefault(key, {}).setdefault(scheduler, {})[nodes] = result.seconds
                    print(f"  {key:13s} {scheduler:11s} P={nodes:5d} "
                          f"({frame.n_paths:,} paths): {result.seconds:8.4f} s virtual "
                          f"({result.counters['rounds']:,} synchronisations, at most "
                          f"{result.counters.get('most_rays_held', 0):,} rays held by a node)",
                          flush=True)
    return times


#: Section 5's variants of ``spec-insitu``: name -> (routes, holders, label).
INSITU_VARIANTS = {"holders": ("relay", "camera", "two hops, more holders for the domains "
                               "crossed most (the product)"),
                   "relay": ("relay", "owner", "two hops, one holder a domain"),
                   "straight": ("straight", "owner", "straight, one holder (before session 52)")}


def insitu_variants(store, costs: CostModel, quick: bool, counts) -> dict:
    """{variant: {P: (seconds, busiest node's seconds by kind)}} of ``INSITU_VARIANTS`` at
    ``WEAK_PATHS_PER_NODE`` paths a node."""
    base, own, fitted = rs.weak_setup(store, costs, quick)
    times: dict = {}
    for nodes in counts:
        replay = rs.replay_of(store, rs.weak_frame(base, nodes), own, activations=fitted)
        for name, (routes, holders, _) in INSITU_VARIANTS.items():
            replay.insitu_routes, replay.insitu_holders = routes, holders
            result = replay.run("spec-insitu", nodes)
            times.setdefault(name, {})[nodes] = (result.seconds, result.busiest)
            print(f"  {name:8s} P={nodes:5d}: {result.seconds:8.4f} s virtual "
                  f"({result.counters['messages']:,} batches, {result.counters['loads']:,} "
                  f"loads)", flush=True)
    return times


def print_insitu(times: dict, counts) -> None:
    """Section 5's table and ``insitu_weak_*=`` lines from ``insitu_variants``."""
    last = counts[-1]
    print("\n| variant | " + " | ".join(f"P={n}" for n in counts[1:])
          + f" | busiest node at P={last}: messages / reduction / own code (s) |")
    print("| --- |" + " --- |" * len(counts))
    for name, by in times.items():
        b = by[last][1]
        print(f"| {INSITU_VARIANTS[name][2]} | "
              + " | ".join(f"{by[1][0] / by[n][0]:.2f}" for n in counts[1:])
              + f" | {b['messages']:.3f} / {b['reduction']:.3f} / {b['own']:.3f} |")
    for name, by in times.items():
        print(f"insitu_weak_{name}=" + ",".join(f"{n}:{by[1][0] / by[n][0]:.2f}"
                                               for n in counts[1:]))


def print_sort_first(by_share: dict, counts) -> None:
    """Section 4's table and ``sort_first_*=`` lines from ``sort_first_by_share``."""
    print("\n| scheduler | a node's share | scaling | "
          + " | ".join(f"P={n}" for n in counts[1:]) + " |")
    print("| --- | --- | --- |" + " --- |" * (len(counts) - 1))
    for scheduler in SORT_FIRST:
        for share, t in by_share.items():
            for kind, word in (("strong", "speed-up"), ("weak", "weak efficiency")):
                by = t[kind][scheduler]
                ours = (SHARES[share][0] == ownership.BLOCKS_PER_NODE and (
                    scheduler in SHARES[share][1]) == (scheduler in image_cost.CUT_BY_COST))
                label = SHARES[share][2] + (" (the product)" if ours else "")
                print(f"| {scheduler} | {label} | {word} | "
                      + " | ".join(f"{by[1] / by[n]:.2f}" for n in counts[1:]) + " |")
    for share, t in by_share.items():
        for kind, name in (("strong", "speedup"), ("weak", "weak")):
            for n in counts[1:]:
                print(f"sort_first_{name}_{n}_{share}=" + ",".join(
                    f"{s}:{t[kind][s][1] / t[kind][s][n]:.2f}" for s in SORT_FIRST))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="2^18 paths at 1, 64 and 1,024 nodes (default: 2^20 paths at "
                             "every fourth power of two)")
    parser.add_argument("--costs", metavar="FILE",
                        help="the calibration to replay with (default: "
                             ".bench_cache/costs.json, else a quick calibration now)")
    args = parser.parse_args()
    start = time.perf_counter()
    costs = constants(args.costs)
    store = cached_cosmo(160, SCALING_GRID)
    if costs.node_cpu_scale:
        rs.own_costs_of(store, scaling_options)
    counts = (1, 64, 1024) if args.quick else rs.STRONG_NODES
    print("\n1. all-reductions: strong scaling by replay, "
          f"{(rs.STRONG_QUICK if args.quick else rs.STRONG).paths:,} paths, "
          f"{len(store.domains)} domains:", flush=True)
    strong = strong_by_reduction(store, costs, args.quick, counts)
    print("\n| scheduler | all-reductions | " + " | ".join(f"P={n}" for n in counts[1:])
          + " |")
    print("| --- | --- |" + " --- |" * (len(counts) - 1))
    for scheduler in REDUCING:
        for reduction in REDUCTIONS:
            t = strong[reduction][scheduler]
            print(f"| {scheduler} | {reduction}{' (the product)' if reduction == 'butterfly' else ''}"
                  " | " + " | ".join(f"{t[1] / t[n]:.2f}" for n in counts[1:]) + " |")
    for reduction in REDUCTIONS:
        for n in counts[1:]:
            print(f"speedup_{n}_{reduction}=" + ",".join(
                f"{s}:{strong[reduction][s][1] / strong[reduction][s][n]:.2f}"
                for s in REDUCING))
    weak_counts = (1, 64, 1024)
    print(f"\n2. the tile: weak scaling by replay, {rs.WEAK_PATHS_PER_NODE:,} paths a node:",
          flush=True)
    weak = weak_by_tile(store, costs, args.quick, weak_counts)
    print("\n| scheduler | tile | " + " | ".join(f"P={n}" for n in weak_counts[1:]) + " |")
    print("| --- | --- |" + " --- |" * (len(weak_counts) - 1))
    one = weak["job"]  # one node: the same tile of 4,096 paths either way
    for scheduler in TILED:
        for name in TILES:
            t = weak[name][scheduler]
            print(f"| {scheduler} | {TILE_LABELS[name]} | "
                  + " | ".join(f"{one[scheduler][1] / t[n]:.2f}" for n in weak_counts[1:])
                  + " |")
            if scheduler == "dynamic" and f"paper {name}" in weak:
                t = weak[f"paper {name}"]["dynamic"]
                print(f"| {scheduler} | {TILE_LABELS[name]}, the paper's rule 3 | "
                      + " | ".join(f"{t[1] / t[n]:.2f}" for n in weak_counts[1:])
                      + " |")
    for name in TILES:
        for n in weak_counts[1:]:
            print(f"weak_{n}_{name}=" + ",".join(
                f"{s}:{one[s][1] / weak[name][s][n]:.2f}" for s in TILED))
    for name in ("product", "job"):
        for n in weak_counts[1:]:
            paper = weak[f"paper {name}"]["dynamic"]  # against its own T(1)
            print(f"dynamic_weak_{n}_paper_{name}={paper[1] / paper[n]:.2f}")
    print("\n3. dynamic's tiles in flight: strong scaling by replay, the frame of 1.:",
          flush=True)
    by_tiles = dynamic_by_tiles(store, costs, args.quick, counts)
    print("\n| tiles in flight | " + " | ".join(f"P={n}" for n in counts) + " |")
    print("| --- |" + " --- |" * len(counts))
    for tiles, t in by_tiles.items():
        label = f"{tiles} (the product)" if tiles > 1 else "1 (before session 41)"
        print(f"| {label}: seconds (all-reductions) | "
              + " | ".join(f"{t[n][0]:.3f} ({t[n][1]:,})" for n in counts) + " |")
        print(f"| {label}: speed-up | "
              + " | ".join(f"{t[1][0] / t[n][0]:.2f}" for n in counts) + " |")
    for tiles, t in by_tiles.items():
        print(f"dynamic_seconds_{tiles}=" + ",".join(f"{n}:{t[n][0]:.3f}" for n in counts))
        print(f"dynamic_speedup_{tiles}=" + ",".join(f"{n}:{t[1][0] / t[n][0]:.2f}"
                                                  for n in counts))
    print("\n4. the sort-first schedules' share of the image: strong scaling of the frame of "
          f"1. and weak scaling at {rs.WEAK_PATHS_PER_NODE:,} paths a node:", flush=True)
    print_sort_first(sort_first_by_share(store, costs, args.quick, counts), counts)
    insitu_counts = (1, 64, 256, 1024)
    print("\n5. spec-insitu's routes and holders: weak scaling by replay, "
          f"{rs.WEAK_PATHS_PER_NODE:,} paths a node:", flush=True)
    print_insitu(insitu_variants(store, costs, args.quick, insitu_counts), insitu_counts)
    print(f"\n{time.perf_counter() - start:.0f} s in all")


if __name__ == "__main__":
    main()
