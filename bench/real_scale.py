"""The most real node processes this machine runs, beside the simulator's prediction for the
same runs (issue 38, part 4).

Every distributed scheduler renders one scene on ``--nodes`` (default 16) local node
processes with ``--threads 1`` each (16 processes share the 2 cores), and the simulator runs
the same job with this machine's calibrated constants, its virtual nodes sharing the cores as
the real processes do. Per scheduler: the real run's wall time (the whole
``render_distributed`` call: start-up, rendering, gathering) and ``busy_max`` (the busiest
node's rendering), the simulated ``busy_max``, ray batches per node, real and simulated,
messages through the coordinator, and whether the real image equals the single-process
reference (it must: every scheduler here is lossless).

The scene gives every node work: rm at 64^3 in 4x4x2 = 32 domains (two a node), 320x240 px
x 4 spp (307,200 paths), one bounce. Every scheduler runs with the nodes' defaults (the
sort-first schedules deal the image's blocks to every node; until session 42 their default
tile of 65,536 paths left 11 of 16 nodes idle here, and this bench gave them a tile a node).

    python bench/real_scale.py                 # 16 nodes, every scheduler (~10 min)
    python bench/real_scale.py --nodes 8 --quick   # 8 nodes, 160x120 (~3 min)
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from bench_scenes import CACHE, cached_rm

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render, shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.sim.cache import Domains
from vastray.sim.calibrate import calibrate
from vastray.sim.costs import CostModel
from vastray.sim.simulate import SIM_SCHEDULERS, simulate

FULL = RenderSettings(width=320, height=240, spp=4, integrator="pt", bounces=1)
QUICK = RenderSettings(width=160, height=120, spp=4, integrator="pt", bounces=1)


def machine_costs(store, costs_file: str | None, saved_as: str) -> CostModel:
    """This machine's constants: read from ``costs_file``, else calibrated now (quick) on
    ``store`` and kept in ``.bench_cache/saved_as``."""
    if costs_file:
        return CostModel.load(costs_file)
    print(f"+ calibrate --quick on {store.path.name}", flush=True)
    costs = calibrate(store.path, quick=True)
    costs.save(CACHE / saved_as)
    return costs


def options(scheduler: str, nodes: int, paths: int) -> JobOptions:
    """One thread a node, the nodes' defaults otherwise."""
    return JobOptions(scheduler=scheduler, threads=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--nodes", type=int, default=16, help="node processes (default 16)")
    parser.add_argument("--quick", action="store_true", help="160x120 px instead of 320x240")
    parser.add_argument("--costs", metavar="FILE",
                        help="a calibration file (default: calibrate now, as simulate.py does)")
    parser.add_argument("--schedulers", default=",".join(SIM_SCHEDULERS),
                        help="comma-separated (default: every one the simulator runs)")
    args = parser.parse_args()
    start = time.perf_counter()
    settings = QUICK if args.quick else FULL
    store = cached_rm(64, (4, 4, 2))
    costs = machine_costs(store, args.costs, "costs-real-scale.json")
    shared = costs.with_cores(costs.cores)
    config = SceneConfig()
    reference = render(store, config, settings, progress=False).film.image()
    domains = Domains(store, shading_inputs(store, config, settings.integrator)[1])
    p = args.nodes
    print(f"\n{store.path.name}: {len(store.domains)} domains, {settings.width}x"
          f"{settings.height} px x {settings.spp} spp ({settings.paths:,} paths), "
          f"{p} node processes x 1 thread on {os.cpu_count()} cores\n")
    print("| scheduler | real wall s | real busy_max s | simulated busy_max s | error "
          "| ray batches / node real | simulated | coordinator messages / node "
          "| busy nodes | image = reference |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    failures = 0
    for scheduler in args.schedulers.split(","):
        job = options(scheduler, p, settings.paths)
        began = time.perf_counter()
        real = render_distributed(store.path, None, settings, p, options=job, timeout=600)
        wall = time.perf_counter() - began
        nodes = real.counters["per_node"]
        batches = sum(n["counters"].get("batches_sent", 0) for n in nodes) / p
        busy = sum(1 for n in nodes if n["counters"].get("shade_s", 0.0) > 0)  # shaded hits
        # what the coordinator received, by kind (the same dictionary in every node's report)
        coordinator = sum(nodes[0]["counters"].get("coordinator_messages", {}).values()) / p
        same = bool(np.array_equal(real.film.image(), reference))
        failures += not same
        sim = simulate(store, job, p, shared, settings, config, max_pass_spp=None,
                       domains=domains)
        sim_batches = sim.counters.get("batches_sent", 0) / p
        error = (sim.seconds - real.seconds["busy_max"]) / real.seconds["busy_max"]
        print(f"| {scheduler} | {wall:.2f} | {real.seconds['busy_max']:.2f} | "
              f"{sim.seconds:.2f} | {error:+.0%} | {batches:.1f} | {sim_batches:.1f} | "
              f"{coordinator:.1f} | {busy} of {p} | {'yes' if same else 'NO'} |", flush=True)
    domains.close()
    print(f"\nreal_nodes={p} images_equal_reference={failures == 0} "
          f"seconds={time.perf_counter() - start:.0f}")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
