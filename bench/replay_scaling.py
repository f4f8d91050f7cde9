"""Scaling at the papers' work per node, by replay (``vastray.sim.replay``), for
``bench/simulate.py``.

One frame of the 1,439-domain cosmology store is traced once for real (Embree, one process,
``record_crossings``: 2^18 paths with ``--quick``, 2^20 in full) and every scheduler's policy
is replayed over its crossings on 1 to 1,024 virtual nodes, each node a core, caching a
quarter of the domains (the temporal-coherence paper's ratio; a node never caches fewer than
it owns, ``node_cache``), reading them at ``STORAGE_MB_S`` and talking over ``NETWORK``.
Weak scaling keeps
``WEAK_PATHS_PER_NODE`` paths per node: an interleaved subset of the recording's paths below
its size, the recording repeated above it (the same rays again, as more samples would).

Before any figure the replay is checked against the simulator that runs the nodes' own code
(``sim.simulate``, itself checked against real runs) on a frame small enough for it,
``CHECK`` on the same store, at P = 1, 16 and 64 (``--quick``: 64): ``replay_error_max=``.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_scenes import CACHE

from vastray.render.driver import shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW
from vastray.sim.cache import Domains, domain_sizes
from vastray.sim.costs import CostModel
from vastray.sim.crossings import Crossings, record_crossings
from vastray.sim.replay import (
    REPLAY_SCHEDULERS,
    Network,
    Replay,
    fit_activation_costs,
    fit_node_own_costs,
    sort_first_decisions,
)
from vastray.sim.simulate import simulate

#: The strong-scaling frames: 2^18 paths (--quick) and 2^20 (full), one bounce of pt.
STRONG_QUICK = RenderSettings(width=512, height=512, spp=1, integrator="pt", bounces=1)
STRONG = RenderSettings(width=1024, height=1024, spp=1, integrator="pt", bounces=1)
#: The frame on which the replay is checked against the real-code simulator.
CHECK = RenderSettings(width=96, height=96, spp=1, integrator="pt", bounces=1)
CHECK_NODES = (1, 16, 64)
CHECK_NODES_QUICK = (64,)
#: Virtual nodes the nodes' own code is fitted at (``fit_node_own_costs``; the checks' 64
#: are not among them).
OWN_FIT_NODES = (4, 16)
#: Node counts of the full bench's strong and weak scaling (every fourth power of two: the
#: full bench must stay within 30 minutes on 2 cores)
STRONG_NODES = (1, 4, 16, 64, 256, 1024)
WEAK_NODES = (1, 4, 16, 64, 256, 1024)
WEAK_PATHS_PER_NODE = 4096
#: Storage a node reads its domains at (a parallel file system's share), MB/s.
STORAGE_MB_S = 200.0
#: The network beyond a message's CPU cost: 10 Gb/s Ethernet, 25 us a message.
NETWORK = Network(latency_s=25e-6, bandwidth=1.25e9)
#: A node caches this share of the store's domains (at least those it owns).
CACHE_SHARE = 4


def recording(store, settings: RenderSettings) -> Crossings:
    """The store's frame's crossings, recorded once and kept in ``.bench_cache``."""
    path = CACHE / (f"crossings-{Path(store.path).stem}-{settings.width}x{settings.height}-"
                    f"{settings.spp}-{settings.integrator}{settings.bounces}.npz")
    if path.exists():
        try:
            return Crossings.load(path)
        except Exception as exc:  # a stale format: record again
            print(f"  {exc}; recording again", flush=True)
    start = time.perf_counter()
    crossings, _ = record_crossings(store, settings)
    crossings.save(path)
    print(f"  recorded {settings.paths:,} paths on {len(store.domains)} domains: "
          f"{len(crossings):,} segments, {int(crossings.visits.sum()):,} domain visits "
          f"({time.perf_counter() - start:.0f} s, kept in {path.name})", flush=True)
    return crossings


def replay_of(store, crossings: Crossings, costs: CostModel, network: Network = NETWORK,
              storage_mb_s: float | None = STORAGE_MB_S, activations=None,
              decisions: dict | None = None, domains: Domains | None = None,
              whole_caches: bool = False, reduction: str = "butterfly",
              tile: int | None = None, fill_busy: bool = True) -> Replay:
    """The replay of ``crossings``; ``decisions``: the sort-first nodes' decision costs
    (``sort_first_decisions``) on the fitted activation costs; the nodes' own code as
    fitted on ``store`` (``own_costs_of``), where it was; with ``costs.load_scale``, each
    domain's load as this machine takes it (``loads_of``; ``domains``: the store's built
    domains, else built here; ``whole_caches``: nodes caching every domain); ``reduction``,
    ``tile`` and ``fill_busy`` as ``Replay``'s (default: the product's)."""
    lo, hi = store.domain_boxes()
    if decisions is not None:
        activations = replace(activations or fit_activation_costs(crossings, costs),
                              sort_first_decision_s=decisions)
    return Replay(crossings, *domain_sizes(store), lo, hi, costs, activations, network,
                  None if storage_mb_s is None else storage_mb_s * 1e6,
                  own=_own_costs.get(str(store.path)) if costs.node_cpu_scale else None,
                  loads=loads_of(store, costs, domains, whole_caches) if costs.load_scale
                  else None, reduction=reduction, tile=tile, fill_busy=fill_busy)


def loads_of(store, costs: CostModel, domains: Domains | None, whole_caches: bool
             ) -> tuple[np.ndarray, np.ndarray]:
    """(D,) read and (D,) build seconds of each of ``store``'s domains as this machine loads
    them (``Domains.load_seconds``, times ``costs.load_scale``), as the real-code simulator
    charges them: built at the qualities of a node cache holding every domain
    (``whole_caches``) or a share of them (Embree's LOW scene quality; the replay's caches
    of D/4 or D/P, and the P = 1 run's whole store too), measured once per store."""
    key = (str(store.path), whole_caches)
    if key not in _loads:
        own = domains is None
        if own:
            domains = Domains(store, shading_inputs(store, SceneConfig(), CHECK.integrator)[1])
        try:
            _loads[key] = domains.load_seconds(None if whole_caches else RTC_BUILD_QUALITY_LOW)
        finally:
            if own:
                domains.close()
    return tuple(costs.load_scale * seconds for seconds in _loads[key])


#: (store path, whole caches) -> (D,) read and (D,) build CPU seconds (``loads_of``)
_loads: dict = {}


#: store path -> each scheduler's ``NodeOwnCosts`` (``own_costs_of``)
_own_costs: dict = {}


def own_costs_of(store, scaling_options) -> dict:
    """Each scheduler's nodes' own code on ``store`` (``fit_node_own_costs`` on ``CHECK`` at
    each of ``OWN_FIT_NODES`` nodes), fitted once, printed, and used by every replay of the
    store: one scheduler a job, the jobs on as many fresh processes as this machine has
    cores, each building the store's domains itself."""
    key = str(store.path)
    if key not in _own_costs:
        start = time.perf_counter()
        fits = list(in_parallel(_check_job, own_fit_jobs(store, scaling_options), "spawn"))
        took_own_fits(store, fits, time.perf_counter() - start)
    return _own_costs[key]


def own_fit_jobs(store, scaling_options) -> list[tuple]:
    """The check workers' jobs (``_check_job``) that fit each replayed scheduler's own code."""
    return [("fit", str(store.path), scheduler,
             {n: scaling_options(scheduler, n, CHECK.paths) for n in OWN_FIT_NODES})
            for scheduler in REPLAY_SCHEDULERS]


def took_own_fits(store, fits: list, seconds: float) -> None:
    """Keep the fits of ``own_fit_jobs`` (in its order) for ``store``'s replays; print them."""
    _own_costs[str(store.path)] = dict(zip(REPLAY_SCHEDULERS, fits, strict=True))
    print(f"  the nodes' own code (fitted on {' and '.join(map(str, OWN_FIT_NODES))} "
          f"virtual nodes running the product's code, {CHECK.paths:,} paths), per frame / "
          "batch sent + a ray in it / batch received + a ray / activation: " + "; ".join(
              f"{name} {c.per_node_s * 1e3:.1f} ms / {c.sent_s * 1e6:.0f} + "
              f"{c.ray_sent_s * 1e6:.1f} / {c.received_s * 1e6:.0f} + "
              f"{c.ray_received_s * 1e6:.1f} / {c.activation_s * 1e6:.0f} us"
              for name, c in _own_costs[str(store.path)].items())
          + f" ({seconds:.0f} s)", flush=True)


def decisions_of(store, settings: RenderSettings, cache: int | None, sizes,
                 domains: Domains | None = None) -> dict:
    """The sort-first nodes' decision costs per activation on ``store`` at tiles of
    ``sizes`` paths through ``cache`` domains (``sort_first_decisions``), printed;
    ``domains``: the store's domains already built (default: built here, closed after)."""
    start = time.perf_counter()
    own = domains is None
    if own:
        domains = Domains(store, shading_inputs(store, SceneConfig(), settings.integrator)[1])
    try:
        decisions = sort_first_decisions(store, settings, domains, cache, sizes)
    finally:
        if own:
            domains.close()
    print("  a sort-first node's decisions per activation (the product's loop, one virtual "
          f"node, cache {cache or 'all'}): " + "; ".join(
              f"{scheduler} " + ", ".join(f"{us * 1e6:.0f} us at {paths:,} paths"
                                         for paths, us in points)
              for scheduler, points in decisions.items())
          + f" ({time.perf_counter() - start:.0f} s)", flush=True)
    return decisions


#: The replay the worker processes run (inherited at fork: the recording is not copied).
_REPLAY: Replay | None = None


def _replay_one(job: tuple[str, int, int]):
    scheduler, nodes, cache = job
    return _REPLAY.run(scheduler, nodes, cache=cache)


def replayed(replay: Replay, jobs: list[tuple[str, int, int]]):
    """``replay.run`` of every (scheduler, nodes, cache) in ``jobs``, in order, on as many
    processes as this machine has cores (forked: each replay is one process's numpy work)."""
    global _REPLAY
    _REPLAY = replay
    yield from in_parallel(_replay_one, jobs, "fork")


def in_parallel(function, jobs: list, start_method: str):
    """``function`` of every job, in order, on as many processes as this machine has cores,
    started by ``start_method`` ("fork" or "spawn"); here, one after another, where one
    process would do."""
    workers = min(len(jobs), os.cpu_count() or 1)
    if workers <= 1:
        yield from map(function, jobs)
        return
    with multiprocessing.get_context(start_method).Pool(workers) as pool:
        yield from pool.imap(function, jobs)


def _sort_first(scheduler: str) -> bool:
    from vastray.schedule import registry

    return registry.find(scheduler).simulation is registry.Simulation.SORT_FIRST


#: The replayed sort-first schedulers (``node_cache`` gives their one-node run a quarter of
#: the domains, as on more nodes).
SORT_FIRST = tuple(s for s in REPLAY_SCHEDULERS if _sort_first(s))


def node_cache(n_domains: int, nodes: int, scheduler: str) -> int:
    """Domains a node of ``scheduler`` caches: a quarter of the store, and never fewer than
    it owns (a domain-decomposition node on fewer than ``CACHE_SHARE`` nodes owns more).

    A sort-first node owns none, so it caches a quarter on one node too: until session 51
    the one-node run cached every domain (as the owners of a one-node domain decomposition
    must), four times the memory of a sort-first node on more, which made T(1), the
    speed-ups' and weak efficiencies' base, that of a larger machine."""
    quarter = -(-n_domains // CACHE_SHARE)
    if _sort_first(scheduler):
        return quarter
    return max(quarter, -(-n_domains // nodes))


_CHECK_DOMAINS: dict = {}  # a check worker's built domains, by store path


def _check_domains(path: str) -> Domains:
    """The store's domains built in this check worker (once)."""
    from vastray.scene.store import Store

    if path not in _CHECK_DOMAINS:
        store = Store(path)
        _CHECK_DOMAINS[path] = Domains(
            store, shading_inputs(store, SceneConfig(), CHECK.integrator)[1])
    return _CHECK_DOMAINS[path]


def _check_job(job):
    """One job of a check worker: ``("sim", path, scheduler, nodes, options, costs)`` ->
    (simulated seconds, wall seconds) of one check point; ``("fit", path, scheduler,
    {nodes: options})`` -> the scheduler's ``NodeOwnCosts`` (``fit_node_own_costs``)."""
    if job[0] == "fit":
        _, path, scheduler, options = job
        domains = _check_domains(path)
        return fit_node_own_costs(domains.store, CHECK, domains, OWN_FIT_NODES,
                                  lambda _s, nodes, _p: options[nodes],
                                  schedulers=[scheduler])[scheduler]
    _, path, scheduler, nodes, options, costs = job
    domains = _check_domains(path)
    start = time.perf_counter()
    sim = simulate(domains.store, options, nodes, costs, CHECK, max_pass_spp=None,
                   domains=domains)
    return sim.seconds, time.perf_counter() - start


def check_against_code(store, costs: CostModel, scaling_options, quick: bool) -> list[dict]:
    """The replay against the simulator running the nodes' own code, on ``CHECK``: both with
    the calibrated loopback network and storage and the product's caches."""
    own = costs.warm().with_cores(None)
    # recorded now, not kept: the replay charges the recording's trace CPU and the
    # simulator the CPU its traces take as it runs, so both must see the machine at one
    # speed (a kept recording's CPU was 1.40x this machine's a day later, and replay_error
    # moved with it from 0.13 to 0.89 between runs)
    start = time.perf_counter()
    crossings, _ = record_crossings(store, CHECK)
    print(f"\n  the check's frame recorded now ({time.perf_counter() - start:.0f} s)")
    nodes_checked = CHECK_NODES_QUICK if quick else CHECK_NODES
    domains = Domains(store, shading_inputs(store, SceneConfig(), CHECK.integrator)[1])
    rows = []
    try:
        # the product's caches (every domain) and each checked node count's tile
        decisions = decisions_of(store, CHECK, None,
                                 sorted({max(1, CHECK.paths // n) for n in nodes_checked}),
                                 domains)
        # the own-code fits (which the replay needs) and the real-code simulations (which
        # do not) side by side on fresh processes, a core each: a simulation and a fit
        # charge CPU time, not wall time, so two side by side charge what one alone would
        start = time.perf_counter()
        fits = (own_fit_jobs(store, scaling_options)
                if own.node_cpu_scale and str(store.path) not in _own_costs else [])
        sims = [("sim", str(store.path), scheduler, nodes,
                 scaling_options(scheduler, nodes, CHECK.paths), own)
                for scheduler in REPLAY_SCHEDULERS for nodes in nodes_checked]
        done = list(in_parallel(_check_job, fits + sims, "spawn"))
        if fits:
            took_own_fits(store, done[:len(fits)], time.perf_counter() - start)
        replay = replay_of(store, crossings, own, Network(), None, decisions=decisions,
                           domains=domains, whole_caches=True)
        print(f"\nreplay vs the real-code simulator ({len(store.domains)} domains, "
              f"{CHECK.paths:,} paths, a core per node):")
        print("| scheduler | P | real-code sim s | replay s | error | sim wall s "
              "| replay wall s |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for (_, _, scheduler, nodes, _, _), (sim_s, sim_wall) in zip(
                sims, done[len(fits):], strict=True):
            replayed = replay.run(scheduler, nodes)
            error = replayed.seconds / sim_s - 1
            rows.append({"scheduler": scheduler, "nodes": nodes, "sim_s": sim_s,
                         "replay_s": replayed.seconds, "error": error})
            print(f"| {scheduler} | {nodes} | {sim_s:.4f} | {replayed.seconds:.4f} | "
                  f"{error:+.3f} | {sim_wall:.1f} | {replayed.wall_s:.2f} |", flush=True)
    finally:
        domains.close()
    worst = max(abs(r["error"]) for r in rows)
    print(f"replay_error_max={worst:.3f}  (replay vs the real-code simulator, "
          f"{CHECK.paths:,} paths)")
    return rows


#: Tile sizes a sort-first node's decisions are measured at for the scaling (a node's tile
#: is paths / P: 2^18 / 1,024 = 256 up; interpolated between, the nearest beyond).
SCALING_DECISION_TILES = (256, 4096)
_scaling_decisions: dict = {}


def scaling_decisions(store, settings: RenderSettings) -> dict:
    """The scaling's sort-first decision costs (a node caching a quarter of the domains),
    measured once per store."""
    key = str(store.path)
    if key not in _scaling_decisions:
        _scaling_decisions[key] = decisions_of(store, settings,
                                               node_cache(len(store.domains), CACHE_SHARE, "spec-ooc"),
                                               SCALING_DECISION_TILES)
    return _scaling_decisions[key]


def strong(store, costs: CostModel, quick: bool, node_counts) -> tuple[dict, dict]:
    """{scheduler: {P: seconds}} of the strong-scaling frame, and each scheduler's
    breakdown at the largest P."""
    settings = STRONG_QUICK if quick else STRONG
    crossings = recording(store, settings)
    replay = replay_of(store, crossings, costs.warm().with_cores(None),
                       decisions=scaling_decisions(store, settings))
    print(f"\nstrong scaling by replay: {settings.paths:,} paths "
          f"({settings.width}x{settings.height}, {settings.spp} spp, {settings.integrator} "
          f"{settings.bounces} bounce), {len(store.domains)} domains, a node caching "
          f"D/{CACHE_SHARE} domains (a domain decomposition's node max(D/{CACHE_SHARE}, D/P): "
          f"what it owns), storage {STORAGE_MB_S:.0f} MB/s, network "
          f"{NETWORK.bandwidth / 1e9:.2f} GB/s + {NETWORK.latency_s * 1e6:.0f} us:")
    times, breakdown = {}, {}
    jobs = [(scheduler, nodes, node_cache(len(store.domains), nodes, scheduler))
            for scheduler in REPLAY_SCHEDULERS for nodes in node_counts]
    for (scheduler, nodes, _), result in zip(jobs, replayed(replay, jobs), strict=True):
        times.setdefault(scheduler, {})[nodes] = result.seconds
        print(f"  {scheduler:11s} P={nodes:5d}: {result.seconds:9.4f} s virtual "
              f"({result.wall_s:.1f} s to replay; {result.counters['messages']:,} messages, "
              f"{result.counters['loads']:,} loads, {result.counters['rounds']:,} "
              "synchronisations)", flush=True)
        if nodes == max(node_counts):
            breakdown[scheduler] = result.breakdown
    if 1 in node_counts:  # the base before session 51, printed beside the speed-ups
        for scheduler in SORT_FIRST:
            WHOLE_CACHE_T1["strong"][scheduler] = replay.run(scheduler, 1).seconds
    return times, breakdown


def weak_setup(store, costs: CostModel, quick: bool):
    """(recording, costs, activation costs) of the weak scaling: the strong frame's recording,
    the costs warm with a core a node, and the activation costs fitted once for every size."""
    settings = STRONG_QUICK if quick else STRONG
    base = recording(store, settings)
    own = costs.warm().with_cores(None)
    fitted = replay_of(store, base, own, decisions=scaling_decisions(store, settings)).activation
    return base, own, fitted


def weak_frame(base: Crossings, nodes: int) -> Crossings:
    """``WEAK_PATHS_PER_NODE`` paths a node on ``nodes`` nodes: an interleaved subset of
    ``base``'s paths below its size, ``base`` repeated above it."""
    paths = WEAK_PATHS_PER_NODE * nodes
    return (base.subset(base.n_paths // paths) if paths <= base.n_paths
            else base.repeated(-(-paths // base.n_paths)))


def weak(store, costs: CostModel, quick: bool, node_counts) -> dict:
    """{scheduler: {P: seconds}} with ``WEAK_PATHS_PER_NODE`` paths per node."""
    base, own, fitted = weak_setup(store, costs, quick)
    print(f"\nweak scaling by replay: {WEAK_PATHS_PER_NODE:,} paths per node, the same "
          "caches, storage and network:")
    times: dict = {}
    for nodes in node_counts:
        frame = weak_frame(base, nodes)
        replay = replay_of(store, frame, own, activations=fitted)
        jobs = [(scheduler, nodes, node_cache(len(store.domains), nodes, scheduler))
                for scheduler in REPLAY_SCHEDULERS]
        for scheduler, result in zip(REPLAY_SCHEDULERS, replayed(replay, jobs), strict=True):
            times.setdefault(scheduler, {})[nodes] = result.seconds
            print(f"  {scheduler:11s} P={nodes:5d} ({frame.n_paths:,} paths): "
                  f"{result.seconds:9.4f} s virtual ({result.wall_s:.1f} s to replay)",
                  flush=True)
            if nodes == max(node_counts):
                WEAK_BUSIEST[scheduler] = result.busiest
        if nodes == 1:  # the base before session 51, printed beside the efficiencies
            for scheduler in SORT_FIRST:
                WHOLE_CACHE_T1["weak"][scheduler] = replay.run(scheduler, 1).seconds
    return times


#: The sort-first schedulers' one-node times caching every domain, the base until session 51,
#: by scaling ("strong", "weak"; filled by ``strong`` and ``weak``).
WHOLE_CACHE_T1: dict = {"strong": {}, "weak": {}}
#: Each scheduler's busiest node at the weak scaling's largest P (``ReplayResult.busiest``).
WEAK_BUSIEST: dict = {}


def scaling_tables(strong_times: dict, breakdown: dict, weak_times: dict | None,
                   node_counts, weak_counts=()) -> None:
    """The strong and weak scaling tables, the breakdown at the largest P, and the
    ``speedup_64=`` / ``speedup_1024=`` lines."""
    shown = [p for p in node_counts if p != 1]
    print("\n| scheduler | T(1) s | " + " | ".join(f"speed-up {p}" for p in shown) + " |")
    print("| --- | --- |" + " --- |" * len(shown))
    for scheduler, by in strong_times.items():
        print(f"| {scheduler} | {by[1]:.3f} | "
              + " | ".join(f"{by[1] / by[p]:.2f}" for p in shown) + " |")
    top = max(node_counts)
    for scheduler, t1 in WHOLE_CACHE_T1["strong"].items():
        print(f"  {scheduler}'s one node caching every domain (four times the memory of the "
              f"others, the base until session 51): T(1) {t1:.3f} s, speed-up at {top} "
              f"against it {t1 / strong_times[scheduler][top]:.2f}")
    best = min(by[1] for by in strong_times.values())
    print("\nspeed-up over the fastest scheduler on one node (T_best(1) / T(P): a scheduler "
          "slow on one node does not flatter itself):")
    print("| scheduler | " + " | ".join(f"P={p}" for p in shown) + " |")
    print("| --- |" + " --- |" * len(shown))
    for scheduler, by in strong_times.items():
        print(f"| {scheduler} | " + " | ".join(f"{best / by[p]:.2f}" for p in shown) + " |")
    print(f"\nwhere the time goes at P={top} (mean per node, s):")
    print("| scheduler | total | trace | load | messages | reduction | own code | wait |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for scheduler, parts in breakdown.items():
        print(f"| {scheduler} | {strong_times[scheduler][top]:.4f} | " + " | ".join(
            f"{parts.get(k, 0.0):.4f}"
            for k in ("trace", "load", "messages", "reduction", "own", "wait")) + " |")
    weak_shown = [p for p in weak_counts if p != 1]
    if weak_times:
        print(f"\nweak scaling efficiency T(1)/T(P), {WEAK_PATHS_PER_NODE:,} paths per node:")
        print("| scheduler | T(1) s | " + " | ".join(f"P={p}" for p in weak_shown) + " |")
        print("| --- | --- |" + " --- |" * len(weak_shown))
        for scheduler, by in weak_times.items():
            print(f"| {scheduler} | {by[1]:.3f} | "
                  + " | ".join(f"{by[1] / by[p]:.2f}" for p in weak_shown) + " |")
        last = max(weak_counts)
        if WEAK_BUSIEST:
            print(f"\nthe busiest node at P={last} of the weak scaling (s; the frame is its "
                  "busy time and its waits):")
            print("| scheduler | frame | rank | trace | load | messages | reduction | own code |")
            print("| --- | --- | --- | --- | --- | --- | --- | --- |")
            for scheduler, b in WEAK_BUSIEST.items():
                print(f"| {scheduler} | {weak_times[scheduler][last]:.4f} | {b['rank']} | "
                      + " | ".join(f"{b[k]:.4f}" for k in ("trace", "load", "messages",
                                                          "reduction", "own")) + " |")
        for scheduler, t1 in WHOLE_CACHE_T1["weak"].items():
            print(f"  {scheduler}'s one node caching every domain (four times the memory of "
                  f"the others, the base until session 51): T(1) {t1:.3f} s, efficiency at "
                  f"{last} against it {t1 / weak_times[scheduler][last]:.2f}")
    for p in shown:
        print(f"speedup_{p}=" + ",".join(f"{s}:{by[1] / by[p]:.2f}"
                                         for s, by in strong_times.items()))
    if weak_times:
        last = max(weak_counts)
        print(f"weak_efficiency_{last}=" + ",".join(f"{s}:{by[1] / by[last]:.2f}"
                                                   for s, by in weak_times.items()))
