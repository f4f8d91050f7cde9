"""The simulator (``vastray.sim``) against real runs, and the papers' scaling figures in it.

    python bench/simulate.py --quick   # <= 10 min: validation, the replay's check, and
                                       # the speed-ups at 64 and 1024 nodes (2^18 paths)
    python bench/simulate.py           # also weak scaling, 2^20 paths, every P, and the
                                       # figures (docs/sim_*.png) with their tables
    python bench/simulate.py --quick --validation-only --hog 1   # on a machine not idle

Validation: every scheduler renders the same small scene on P = 1, 2, 4 (``--quick``: 2, one
pair a row) real node processes (this machine; ``--threads 1``, as the cost model is per core) and in the
simulator with the constants ``vastray calibrate`` measures here first, the virtual nodes
sharing this machine's cores as the real processes do. Measured is the real run's ``busy_max``
(the busiest node's rendering, start-up and film gathering left out); simulated the same span
in virtual time. A point is up to ``--repeats`` (3) pairs of a real run and a simulation right
after it (``--quick``: at least two, and a third unless their errors agree within 10 points
and their real runs add up to 0.5 s, ``enough_pairs``; the row prints how many); its error is
the median over its pairs of each simulation's (simulated - measured) / measured against the
real run of its own pair, as ``tests/test_simulate.py`` judges it (the
machine's speed moves between pairs, and a simulation shares its moment with its own run only;
the error of the two sides' medians is printed beside it). ``sim_error_max=`` is the worst
|error|. The constants that move most with this machine's moment, what a message and a hand-off
to a worker thread cost (``receive_s``, ``offload_s``), are measured again before each
scheduler's real runs (``MachineProbe``, about 3 s; printed per row; ``--quick``'s in-sample
rows: once), and so is a round of the throughput of busy processes (one alone, and 2, 4 and 8
side by side), charged from the medians of the latest six rounds (one round moves by a sixth
with the host's speed). The host's "steal" to other virtual machines while a real run ran
(``sim.steal.StealMeter``) is charged as cores the run did not have (``CostModel.stolen``), and
the other processes on this machine that wanted a core around it (``sim.steal.others_running``:
about 1 beside ``--hog 1``) run as that many busy processes beside the virtual nodes
(``CostModel.beside``), both printed per row; every other constant is the calibration's.
``--no-probe`` charges the calibration's throughout, and nothing taken by others.

Out of sample: the same against real runs on stores and settings the constants were not
calibrated on (``sim_error_oos_max=``), on 1, 2, 4 and 8 nodes (``--quick``: every scheduler on
2 nodes on one store and on 8 on the other, ``quick_node_counts``). Their pairs come in sweeps,
every point's first pair, then every point's second, then the third pairs (``validate_oos``),
so that a slow minute of the host falls on one pair of several points, not on all of one; each
pair is charged the probe's latest measurement, taken again once 30 s have passed
(``PROBE_EVERY_S``). Each row also prints the
real nodes' trace CPU over the simulation's (``trace_cpu_s``, the same traces;
``trace_cpu_real_over_sim=`` its range): this machine's speed moves by up to a fifth within
seconds (a fixed kernel's CPU time, 2-second windows: 0.039-0.059 s), which no probe before a
run sees, so a row's error far from 0 with this ratio far from 1 is mostly that. (Until session
32 a fresh node also loaded each compiled kernel in its first activations: 1.15-2.2x on the
scan; nodes now call them as they start, ``actors.node_warm_up``.)

Scaling, by replay (``bench/replay_scaling.py``, ``vastray.sim.replay``): one frame of a store
of 1,439 domains traced once for real, every scheduler's policy replayed over its crossings on
1 to 1,024 virtual nodes with a core each, warm (what the papers time is rendering), the
constants of this machine, a stated storage bandwidth and network; speed-up = T(1) / T(P).
The replay is first checked against the simulator that runs the nodes' own code
(``replay_error_max=``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import replay_scaling
from bench_scenes import CACHE, cached_cosmo, cached_rm, cached_scan
from bytecode import compile_vastray
from hogs import busy_processes
from pair_noise import chance_within, pooled_sd

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render, shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.sim.cache import Domains
from vastray.sim.calibrate import MachineProbe, calibrate
from vastray.sim.costs import CostModel
from vastray.sim.simulate import SIM_SCHEDULERS, simulate
from vastray.sim.steal import Contention

DOCS = Path(__file__).resolve().parent.parent / "docs"
VALIDATION_NODES = (1, 2, 4)
#: ``--quick``: the in-sample figure at one node count (the out-of-sample rows are the goal's)
VALIDATION_NODES_QUICK = (2,)
#: validation scene and settings: rm at 64^3 in 3x3x2 domains, 160x120 px, 4 spp in one pass
#: (as ``render_distributed`` renders without a progression)
VALIDATION = RenderSettings(width=160, height=120, spp=4, integrator="pt", bounces=1)
#: and, in full mode, 4 times the paths: a case where tracing outweighs start-up
HEAVY = RenderSettings(width=320, height=240, spp=4, integrator="pt", bounces=1)
#: the scaling store: cosmo at 160^3 in 16x16x8 cells = 1,439 domains (the empty cells have
#: none; SpRay's DNS2 has 1,427)
SCALING_GRID = (16, 16, 8)


def scaling_options(scheduler: str, nodes: int, paths: int) -> JobOptions:
    """The options of a scaling run of ``paths`` on ``nodes``: the product's defaults (until
    session 42 the sort-first schedules got a tile per node here, as their default tile of
    65,536 paths left every node but one idle on a small frame; they now deal the frame's
    blocks to every node themselves, ``ownership.sort_first_tile_paths``)."""
    return JobOptions(scheduler=scheduler)


def costs_here(quick: bool, store) -> CostModel:
    """This machine's constants, measured now (and kept in ``.bench_cache/costs.json``)."""
    print(f"+ calibrate {'--quick ' if quick else ''}on {store.path.name}", flush=True)
    costs = calibrate(store.path, quick=quick)
    costs.save(CACHE / "costs.json")
    print("  " + ", ".join(f"{k}={v:.3g}" for k, v in costs.as_dict().items()
                           if isinstance(v, float)) + f", cores={costs.cores}, throughput="
          + "/".join(f"{t:.2f}" for t in costs.throughput), flush=True)
    return costs


#: ``--quick``: a validation point repeats its (real run, simulation) pair, up to the rounds
#: asked for, until its real runs add up to this many seconds: one real run of a fraction of
#: a second moves by up to 2x from the next here (the scan's 2-node ``domain``: 0.34-0.76 s
#: over ten validations), a run of several seconds by 20-30 % (1 s until session 73, when
#: every point took at least two pairs)
QUICK_BUDGET_S = 0.5
#: ...and never on fewer than this many pairs: a single pair lets one slow run decide its
#: row (session 73: rm 128³'s ``domain`` on 2 nodes, identical real runs of 4.19 and 2.63 s
#: back to back), and the seconds budget gave the slowest moments the fewest pairs
QUICK_MIN_PAIRS = 2
#: ...and a further pair where the pairs' errors spread wider than this: the median of
#: three then sets aside the one that disagrees (the rule looks at the spread only, never
#: at how large the errors are)
PAIRS_AGREE = 0.10
#: ...but beside this many other processes wanting a core, a point takes every pair it may:
#: where three processes share two cores the operating system's placement moves a run far
#: more than the work does (rm 128³'s ``image`` on 2 nodes beside a spinner: 1.08-1.29 s
#: in four runs, one node as fast as alone while the other shared a core with the spinner;
#: the simulation, charging each its fair share, 1.18 s)
BUSY_HOST_OTHERS = 0.5


class PointPairs:
    """One validation point's (real run, simulation) pairs so far: ``take`` adds one, a
    real run on ``nodes`` processes (``options``) and, right after it, a simulation charged
    the costs given and, with ``charge_others``, the host's steal during that run and the
    other processes that wanted a core around it (``sim.steal.Contention``: run beside the
    virtual nodes), so both see the machine's moment; ``summary`` judges them."""

    def __init__(self, store, settings: RenderSettings, nodes: int, options: JobOptions,
                 config: SceneConfig, domains: Domains):
        self.store, self.settings, self.nodes, self.options = store, settings, nodes, options
        self.config, self.domains = config, domains
        self.reals: list[float] = []
        self.sims: list[float] = []
        self.lost: list[float] = []
        self.others: list[float] = []
        self.ratios: list[float] = []
        #: the costs each pair's simulation was charged (before the steal and the others)
        self.charged: list[CostModel] = []
        self.result = self.sim = None

    def enough(self, rounds: int, budget_s: float) -> bool:
        """Whether the point has its pairs (``enough_pairs``)."""
        return enough_pairs(self.reals, self.sims, self.others, rounds, budget_s)

    def take(self, costs: CostModel, charge_others: bool) -> None:
        """One more pair, its simulation charged ``costs``."""
        # without charge_others, nothing is measured (Contention samples 0.5 s a run)
        with Contention() if charge_others else contextlib.nullcontext() as seen:
            self.result = render_distributed(self.store.path, None, self.settings, self.nodes,
                                             options=self.options, timeout=300)
        self.charged.append(costs)
        self.lost.append(seen.share if seen else 0.0)
        self.others.append(seen.others if seen else 0.0)
        self.reals.append(self.result.seconds["busy_max"])
        self.sim = simulate(self.store, replace(self.options, threads=None), self.nodes,
                            seen.charged(costs) if seen else costs, self.settings,
                            self.config, max_pass_spp=None, domains=self.domains)
        self.sims.append(self.sim.seconds)
        real_trace = sum(n["counters"].get("trace_cpu_s", 0.0)
                         for n in self.result.counters["per_node"])
        if real_trace > 0 and self.sim.counters.get("trace_cpu_s", 0.0) > 0:
            self.ratios.append(real_trace / self.sim.counters["trace_cpu_s"])

    def summary(self) -> dict:
        """The point judged over its pairs.

        Returns
        -------
        dict with ``real_s``, ``sim_s`` (the medians), ``error`` (the median over the pairs
        of each simulation's error against the real run of its own pair: the machine's speed
        moves between pairs, and a simulation shares its moment with its own run only),
        ``error_of_medians`` (``sim_s / real_s - 1``, the rule before session 48),
        ``rounds``, ``lost`` (the largest share of the host's steal charged), ``others``
        (the median of the others' busy processes charged, ``sim.steal.Contention``),
        ``trace_ratio`` (the median over the pairs of the real nodes' trace CPU over the
        simulation's, ``trace_cpu_s``: the same traces, so its distance from 1 is the
        machine's speed moving between the two, or what a real node's traces pay that the
        simulator's do not; None where the runtime does not count it), ``receive_s``,
        ``offload_s`` and ``throughput`` (the medians of the pairs' charged costs),
        ``result`` (the last real run's) and ``sim`` (the last simulation's).
        """
        real_s, sim_s = float(np.median(self.reals)), float(np.median(self.sims))
        throughput = np.median([c.throughput for c in self.charged], axis=0)
        errors = pair_errors(self.reals, self.sims)
        return {"real_s": real_s, "sim_s": sim_s, "error": float(np.median(errors)),
                "pair_errors": errors,
                "error_of_medians": sim_s / real_s - 1.0, "rounds": len(self.reals),
                "lost": max(self.lost), "others": float(np.median(self.others)),
                "trace_ratio": float(np.median(self.ratios)) if self.ratios else None,
                "receive_s": float(np.median([c.receive_s for c in self.charged])),
                "offload_s": float(np.median([c.offload_s for c in self.charged])),
                "throughput": tuple(float(t) for t in throughput),
                "result": self.result, "sim": self.sim}


def paired(store, settings: RenderSettings, nodes: int, options: JobOptions, costs: CostModel,
           charge_others: bool, rounds: int, budget_s: float, config: SceneConfig,
           domains: Domains) -> dict:
    """One validation point's pairs taken one after the other (``PointPairs``): ``rounds``
    of them (with a finite ``budget_s`` fewer, as ``enough_pairs`` says), each simulation
    charged ``costs``; ``PointPairs.summary``."""
    point = PointPairs(store, settings, nodes, options, config, domains)
    while not point.enough(rounds, budget_s):
        point.take(costs, charge_others)
    return point.summary()


def pair_errors(reals: list[float], sims: list[float]) -> list[float]:
    """Each pair's error: its simulation's seconds over its real run's, less 1."""
    return [s / r - 1.0 for r, s in zip(reals, sims, strict=True)]


def pair_spread(reals: list[float], sims: list[float]) -> float:
    """How far apart the pairs' errors are (``pair_errors``; 0 for fewer than two)."""
    errors = pair_errors(reals, sims)
    return max(errors) - min(errors) if len(errors) > 1 else 0.0


def enough_pairs(reals: list[float], sims: list[float], others: list[float], rounds: int,
                 budget_s: float) -> bool:
    """Whether a validation point (``paired``) has its pairs: ``rounds`` of them; with a
    finite ``budget_s`` (``--quick``) fewer, once there are ``QUICK_MIN_PAIRS``, their
    errors (simulated / real - 1, pair by pair) spread no wider than ``PAIRS_AGREE``, their
    real runs add up to ``budget_s`` and no other process wanted a core
    (``BUSY_HOST_OTHERS``)."""
    if len(reals) >= max(rounds, 1):
        return True
    if len(reals) < min(QUICK_MIN_PAIRS, rounds) or budget_s == float("inf"):
        return False
    return (pair_spread(reals, sims) <= PAIRS_AGREE and sum(reals) >= budget_s
            and max(others) < BUSY_HOST_OTHERS)


#: ``sim_error_oos_max=``'s goal
OOS_GOAL = 0.20


def _noise(rows: list[dict]) -> None:
    """Print how much of the worst out-of-sample row the machine's noise can make
    (``pair_noise``): a pair's spread about its point's mean, and the chance that a simulator
    without bias would print a worst row within the goal with the pairs taken (and with 4 a
    point)."""
    sd = pooled_sd([r["pair_errors"] for r in rows])
    if sd is None:
        return
    counts = [len(r["pair_errors"]) for r in rows]
    print(f"sim_error_oos_pair_sd={sd:.3f}  (a pair's error about its point's mean, pooled "
          f"over {len(rows)} points' {sum(counts)} pairs: the machine's moment)")
    print(f"sim_error_oos_chance_unbiased="
          f"{chance_within(OOS_GOAL, sd, counts):.2f}  (the "
          f"chance that a simulator with no bias prints sim_error_oos_max <= {OOS_GOAL:.2f} "
          f"at this noise with these pairs; 4 pairs a point: "
          f"{chance_within(OOS_GOAL, sd, [4] * len(rows)):.2f})")


def _ratio(point: dict) -> str:
    return "–" if point["trace_ratio"] is None else f"{point['trace_ratio']:.2f}"


def validate(store, costs: CostModel, rounds: int, settings: RenderSettings = VALIDATION,
             node_counts=VALIDATION_NODES, probe: MachineProbe | None = None,
             budget_s: float = float("inf"), probe_each: bool = True) -> list[dict]:
    """Every scheduler at ``node_counts``, real and simulated (cores shared as here), each
    point ``paired`` (``rounds``, ``budget_s``); with ``probe``, each scheduler's rows charge
    the message and hand-off costs measured just before its real runs (``MachineProbe``; not
    ``probe_each``: once, before the first scheduler's) and the CPU time others took during
    each real run."""
    config = SceneConfig()
    reference = render(store, config, settings, progress=False).film.image()
    domains = Domains(store, shading_inputs(store, config, settings.integrator)[1])
    rows = []
    print(f"\n{settings.width}x{settings.height}, {settings.spp} spp; of the simulated seconds "
          f"a node pays {costs.warmup_s + costs.node_setup_s:.3f} s once "
          f"({costs.warmup_s + costs.tile_setup_s:.3f} s for image, spec-ooc; "
          f"{costs.warmup_s + costs.insitu_setup_s:.3f} s for spec-insitu); traces charged "
          + ("at the CPU time they take here" if costs.trace_scale else "by the constants"))
    print("| scheduler | nodes | receive / hand-off ms | throughput 2 / 4 | others running "
          "/ steal | rounds | trace CPU real / sim | measured s | simulated s | error (pairs) "
          "| error of medians | images = reference |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    now = costs
    for index, scheduler in enumerate(SIM_SCHEDULERS):
        if probe is not None and (probe_each or index == 0):
            now = probe.now(costs)
        shared = now.with_cores(now.cores)
        for nodes in node_counts:
            point = paired(store, settings, nodes, JobOptions(scheduler=scheduler, threads=1),
                           shared, probe is not None, rounds, budget_s, config, domains)
            real_s, sim_s = point["real_s"], point["sim_s"]
            same = bool((point["sim"].film.image() == reference).all()
                        and (point["result"].film.image() == reference).all())
            error = point["error"]
            rows.append({"scheduler": scheduler, "nodes": nodes, "width": settings.width,
                         "spp": settings.spp, **_row(point), "same_image": same})
            print(f"| {scheduler} | {nodes} | {_messaging(point)} | "
                  f"{_throughput(point['throughput'])} | "
                  f"{_others(point)} | {point['rounds']} | {_ratio(point)} | {real_s:.3f} | "
                  f"{sim_s:.3f} | {error:+.1%} | {point['error_of_medians']:+.1%} | "
                  f"{'yes' if same else 'NO'} |", flush=True)
    domains.close()
    return rows


#: Out-of-sample node counts (8 processes share the 2 cores; the model shares them too).
OOS_NODES = (1, 2, 4, 8)
#: ``--quick``: each scheduler at one of these on each case, the other on the next case
#: (``quick_node_counts``): every scheduler on 2 and on 8 nodes, on one case each, so that
#: every point takes at least two pairs within the 10 minutes
OOS_NODES_QUICK = (2, 8)


def quick_node_counts(case: int, scheduler: int) -> tuple[int]:
    """The ``--quick`` validation's node count for the ``scheduler``-th of ``SIM_SCHEDULERS``
    on the ``case``-th out-of-sample case: 2 and 8 alternating along the schedulers, the
    other way round on the next case."""
    return (OOS_NODES_QUICK[(case + scheduler) % len(OOS_NODES_QUICK)],)


def oos_cases(quick: bool = False) -> list[tuple[str, object, RenderSettings, int | None]]:
    """Validation cases the constants were not calibrated on (they come from rm 64³ in 3x3x2
    domains, 160x120, one bounce, every domain cached): (name, store, settings, cache in
    domains a process). ``quick``: rm 128³ at 64x48 x 1 spp rather than 96x72 x 4 (3,072
    paths, 384 a node on 8 nodes; at 6,912 paths its 128 domains through a cache of 32 made
    1,200 loads on 2 nodes and its 14 rows took 7.5 minutes): every row takes at least two
    pairs (``QUICK_MIN_PAIRS``)."""
    cases = []
    scan = cached_scan("turbine_blade_199k.ply", (2, 2, 2))
    if scan is not None:  # a real CT isosurface, 199 k triangles
        # 8 spp (98,304 paths): at 4 the scan's runs took 0.2-0.5 s, most of it fixed costs,
        # and its rows were the worst of every run of session 73 and 74; five pairs each of
        # its 2-node ``temporal`` and 8-node ``dynamic`` errors, interleaved: mean +0.3 % and
        # +17.0 %, standard deviation 8.8 and 8.4 points at 4 spp, +4.7 % and +9.1 %, 7.1
        # and 4.9 points at 8, for about 0.3 s more a pair
        cases.append(("turbine blade scan 2x2x2", scan,
                      RenderSettings(width=128, height=96, spp=8, integrator="pt", bounces=2),
                      None))
    size = dict(width=64, height=48, spp=1) if quick else dict(width=96, height=72, spp=4)
    cases.append(("rm 128³ 8x8x2 (128 domains), cache 32 a process", cached_rm(128, (8, 8, 2)),
                  RenderSettings(**size, integrator="pt", bounces=3), 32))
    return cases


#: The out-of-sample validation measures the machine again (``MachineProbe.now``, about 3 s)
#: before a pair once this many seconds have passed since the last measurement: the charged
#: medians of the probe's latest six rounds then span about three minutes (at 20 s, 15 probes
#: took 45 s of ``--quick``'s 612 s, session 74)
PROBE_EVERY_S = 30.0


def validate_oos(costs: CostModel, node_counts, rounds: int,
                 probe: MachineProbe | None = None,
                 budget_s: float = float("inf"), quick: bool = False) -> list[dict]:
    """Every scheduler on the out-of-sample cases (``oos_cases(quick)``) at ``node_counts``
    (``quick``: one of them a case, ``quick_node_counts``), real and simulated (cores shared
    as here), each point ``rounds`` pairs (``budget_s``: as ``enough_pairs`` says); each row
    says how many nodes traced (``busy``). With ``probe``, each pair charges the message
    and hand-off costs and the throughput measured last (at most ``PROBE_EVERY_S`` before it)
    and the CPU time others took during its real run.

    The pairs are taken in sweeps: every point's first, then every point's second, then a
    third for the points that need one. A slow spell of this machine (a minute in which the
    same real runs take 1.4 times as long; the simulation, measured a second later, does not
    follow it) then falls on one pair of many points rather than on every pair of one, and
    the median of a point's three pairs sets it aside (the scan's 8-node ``spec-ooc`` at
    4 spp: both its back-to-back pairs -37 % in session 73's last run, real 0.54 s where
    24 pairs in session 74 took 0.33-0.45 s and read -24 to +9 %)."""
    config = SceneConfig()
    cases, points = [], []
    for case, (name, store, settings, cache) in enumerate(oos_cases(quick)):
        reference = render(store, config, settings, progress=False).film.image()
        domains = Domains(store, shading_inputs(store, config, settings.integrator)[1])
        cases.append((name, store, settings, reference, domains))
        for index, scheduler in enumerate(SIM_SCHEDULERS):
            for nodes in quick_node_counts(case, index) if quick else node_counts:
                options = replace(scaling_options(scheduler, nodes, settings.paths),
                                  threads=1, cache=cache)
                points.append((case, scheduler, PointPairs(store, settings, nodes, options,
                                                           config, domains)))
    try:
        _take_in_sweeps(points, costs, rounds, probe, budget_s,
                        QUICK_OOS_SECONDS if quick else float("inf"))
        return [row for index, case in enumerate(cases)
                for row in _case_rows(case, [(s, p) for c, s, p in points if c == index])]
    finally:
        for *_, domains in cases:
            domains.close()


#: ``--quick``: the out-of-sample validation takes no pair beyond a point's first
#: ``QUICK_MIN_PAIRS`` once it has run this long, so that the bench keeps within its 10
#: minutes however many points disagree (session 74: 12 of 14 took a third pair in a slow
#: hour, and the run took 615 s); the third pairs go to the points whose pairs spread
#: widest first
QUICK_OOS_SECONDS = 270.0


def _take_in_sweeps(points: list, costs: CostModel, rounds: int, probe: MachineProbe | None,
                    budget_s: float, seconds: float = float("inf")) -> None:
    """Take every point's pairs (``validate_oos``'s sweeps), printing each as it comes;
    after ``seconds``, only the first ``QUICK_MIN_PAIRS`` of each (``QUICK_OOS_SECONDS``)."""
    start = time.perf_counter()
    now, probed = costs, -float("inf")
    for sweep in range(max(rounds, 1)):
        todo = [p for p in points if not p[2].enough(rounds, budget_s)]
        if sweep >= QUICK_MIN_PAIRS:  # the widest spread first
            todo.sort(key=lambda p: -pair_spread(p[2].reals, p[2].sims))
        if not todo:
            break
        print(f"\nout of sample, pairs {sweep + 1}: {len(todo)} point(s)", flush=True)
        for _, scheduler, point in todo:
            if sweep >= QUICK_MIN_PAIRS and time.perf_counter() - start >= seconds:
                print(f"  (no more pairs beyond {QUICK_MIN_PAIRS} a point: the validation's "
                      f"{seconds:.0f} s are spent)", flush=True)
                return
            if probe is not None and time.perf_counter() - probed >= PROBE_EVERY_S:
                now, probed = probe.now(costs), time.perf_counter()
            point.take(now.with_cores(now.cores), probe is not None)
            print(f"  {point.store.path.name} {scheduler} on {point.nodes}: real "
                  f"{point.reals[-1]:.3f} s, simulated {point.sims[-1]:.3f} s "
                  f"({pair_errors(point.reals, point.sims)[-1]:+.1%})", flush=True)


def _case_rows(case: tuple, points: list) -> list[dict]:
    """The rows of one out-of-sample case's points, printed as its table."""
    name, store, settings, reference, _ = case
    print(f"\nout of sample: {name}, {len(store.domains)} domains, {settings.width}x"
          f"{settings.height} x {settings.spp} spp, {settings.bounces} bounces "
          f"({settings.paths:,} paths)")
    print("| scheduler | nodes | busy nodes | real CPU / busy | receive / hand-off ms "
          "| throughput 2 / 4 | others running / steal | pairs | trace CPU real / sim "
          "| measured s | simulated s | error (pairs) | error of medians "
          "| real image = reference | sim image = reference |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- "
          "| --- | --- |")
    rows = []
    for scheduler, pairs in points:
        point = pairs.summary()
        real_s, sim_s, nodes = point["real_s"], point["sim_s"], pairs.nodes
        per_node = point["result"].counters["per_node"]
        busy = sum(1 for n in per_node if n["counters"].get("shade_s", 0.0) > 0)
        # the real nodes' CPU over their busy spans (all their threads): the model charges
        # CPU on shared cores; a share well under 1 is time spent waiting
        cpu_share = (sum(n["counters"].get("busy_cpu_s", 0.0) for n in per_node)
                     / max(sum(n.get("busy_s", 0.0) for n in per_node), 1e-9))
        real_same = bool((point["result"].film.image() == reference).all())
        sim_same = bool((point["sim"].film.image() == reference).all())
        error = point["error"]
        rows.append({"case": name, "scheduler": scheduler, "nodes": nodes,
                     "busy": busy, "cpu_share": cpu_share, **_row(point),
                     "same_image": real_same and sim_same})
        print(f"| {scheduler} | {nodes} | {busy} | {cpu_share:.2f} | "
              f"{_messaging(point)} | {_throughput(point['throughput'])} | {_others(point)} | "
              f"{point['rounds']} | {_ratio(point)} | {real_s:.3f} | {sim_s:.3f} | "
              f"{error:+.1%} | {point['error_of_medians']:+.1%} | "
              f"{'yes' if real_same else 'NO'} | {'yes' if sim_same else 'NO'} |", flush=True)
    return rows


def _row(point: dict) -> dict:
    """What a validation row keeps of its point (``PointPairs.summary``)."""
    return {"measured_s": point["real_s"], "simulated_s": point["sim_s"],
            "rounds": point["rounds"], "error": point["error"],
            "pair_errors": point["pair_errors"], "error_of_medians": point["error_of_medians"],
            "receive_s": point["receive_s"], "offload_s": point["offload_s"],
            "throughput": point["throughput"],
            "stolen": point["lost"], "others": point["others"],
            "trace_ratio": point["trace_ratio"]}


def _others(point: dict) -> str:
    """Other processes wanting a core (median over the pairs) / the host's largest steal."""
    return f"{point['others']:.2f} / {point['lost']:.0%}"


def _messaging(point: dict) -> str:
    """A point's charged ``receive_s`` / ``offload_s``, in ms (``PointPairs.summary``)."""
    return f"{point['receive_s'] * 1e3:.2f} / {point['offload_s'] * 1e3:.2f}"


def _throughput(t: tuple[float, ...]) -> str:
    """The throughput charged with 2 and with 4 busy processes, in single-process speeds."""
    return " / ".join(f"{t[k - 1]:.2f}" if len(t) >= k else "-" for k in (2, 4))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="validation and the speed-ups at 64 and 1024 nodes only")
    parser.add_argument("--repeats", type=int, default=3,
                        help="most (real run, simulation) pairs per validation point, medians "
                             f"of each (default 3; --quick stops after {QUICK_MIN_PAIRS} whose "
                             f"errors agree within {PAIRS_AGREE:.0%} and whose real runs add "
                             f"up to {QUICK_BUDGET_S:g} s)")
    parser.add_argument("--json", metavar="FILE", help="write every figure as JSON")
    parser.add_argument("--costs", metavar="FILE",
                        help="use this calibration file instead of calibrating now (the "
                             "scaling and figures only depend on it, not on the machine's load)")
    parser.add_argument("--skip-validation", action="store_true",
                        help="no real runs: the scaling and figures only")
    parser.add_argument("--validation-only", action="store_true",
                        help="the validation only (no scaling, no figures)")
    parser.add_argument("--no-probe", action="store_true",
                        help="charge the calibration's message and hand-off costs and "
                             "throughput throughout (default: measured again before each "
                             "scheduler's real runs, as this machine's speed moves within "
                             "minutes)")
    parser.add_argument("--hog", type=int, default=0, metavar="N",
                        help="run everything (the calibration too) beside N busy processes: "
                             "the validation on a machine that is not idle, as a cluster "
                             "node beside a simulation (default 0)")
    args = parser.parse_args()
    if args.hog < 0:
        parser.error(f"--hog takes a count of busy processes, 0 or more, not {args.hog}")
    with busy_processes(args.hog):
        run(args)


def run(args: argparse.Namespace) -> None:
    """The bench ``main`` parsed the options of (see the module docstring)."""
    start = time.perf_counter()
    compile_vastray()  # its ~60 jobs' node processes start as an installed vastray's do
    print("simulator vs real runs (busy_max, same scene/settings/threads), then virtual "
          "scaling with this machine's calibrated costs"
          + (f", all of it beside {args.hog} busy processes (--hog)" if args.hog else ""))
    small = cached_rm(64, (3, 3, 2))
    costs = CostModel.load(args.costs) if args.costs else costs_here(args.quick, small)
    probe = None if args.no_probe or args.skip_validation else MachineProbe(small.path)
    if probe is not None:
        print("the message and hand-off costs (receive_s, offload_s) and the throughput of "
              "busy processes charged in the validation are measured again before each "
              "scheduler's real runs in sample and every "
              f"{PROBE_EVERY_S:.0f} s out of sample (MachineProbe); every other constant is the "
              "calibration's")
    budget_s = QUICK_BUDGET_S if args.quick else float("inf")
    # --quick: one pair a row in sample, probed once (the goal is out of sample's, and its
    # rows need the minutes: a probe of 8 busy processes takes about 3 s)
    rows = [] if args.skip_validation else validate(
        small, costs, 1 if args.quick else args.repeats,
        node_counts=VALIDATION_NODES_QUICK if args.quick else VALIDATION_NODES, probe=probe,
        budget_s=budget_s, probe_each=not args.quick)
    if rows and not args.quick:  # work rather than start-up: 4 times the paths
        rows += validate(small, costs, 1, HEAVY, (1, 4), probe=probe)
    if rows:
        worst = max(abs(r["error"]) for r in rows)
        print(f"\nsim_error_max={worst:.3f}  (in sample: the store and settings the "
              "constants were calibrated on" + ("; one pair a row" if args.quick else "") + ")")
        print(f"sim_images_equal_reference={all(r['same_image'] for r in rows)}")
    oos = [] if args.skip_validation else validate_oos(
        costs, OOS_NODES_QUICK if args.quick else OOS_NODES, args.repeats, probe, budget_s,
        args.quick)
    if probe is not None:
        probe.close()
    if oos:
        worst = max(abs(r["error"]) for r in oos)
        print(f"\nsim_error_oos_max={worst:.3f}  (out of sample: other stores, a real scan, "
              f"other resolutions, bounces and caches; goal {OOS_GOAL:.2f})")
        print(f"sim_error_oos_median={float(np.median([abs(r['error']) for r in oos])):.3f}")
        print(f"sim_error_oos_max_of_medians="
              f"{max(abs(r['error_of_medians']) for r in oos):.3f}  (the same rows judged by "
              "the error of each side's medians, the rule before session 48)")
        _noise(oos)
        ratios = [r["trace_ratio"] for r in oos if r["trace_ratio"] is not None]
        if ratios:  # the same traces took this much more CPU in the real runs than simulated
            print(f"trace_cpu_real_over_sim={min(ratios):.2f}..{max(ratios):.2f} (median "
                  f"{float(np.median(ratios)):.2f}, over the rows that count it: the same "
                  "traces' CPU in the real nodes over the simulation's)")
        print(f"oos_images_equal_reference={all(r['same_image'] for r in oos)}")
        rows = rows + oos
    if args.validation_only:
        if args.json:
            Path(args.json).write_text(json.dumps({"costs": costs.as_dict(),
                                                   "validation": rows}, indent=1))
        print(f"\n{time.perf_counter() - start:.0f} s in all")
        return
    big = cached_cosmo(160, SCALING_GRID)
    checked = replay_scaling.check_against_code(big, costs, scaling_options,
                                                quick=args.quick)
    counts = (1, 64, 1024) if args.quick else replay_scaling.STRONG_NODES
    times, breakdown = replay_scaling.strong(big, costs, args.quick, counts)
    weak = None if args.quick else replay_scaling.weak(big, costs, False,
                                                       replay_scaling.WEAK_NODES)
    replay_scaling.scaling_tables(times, breakdown, weak, counts, replay_scaling.WEAK_NODES)
    figures = {}
    if not args.quick:
        from sim_figures import paper_figures

        figures = paper_figures(costs, times, len(big.domains))
    if args.json:
        Path(args.json).write_text(json.dumps({"costs": costs.as_dict(), "validation": rows,
                                               "replay_check": checked, "scaling": times,
                                               "breakdown": breakdown, "weak": weak,
                                               "figures": figures},
                                              indent=1, default=str))
    print(f"\n{time.perf_counter() - start:.0f} s in all")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
