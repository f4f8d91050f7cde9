"""What a node costs once beyond the model's traces, loads and messages: what is left of a
fresh process's first use after its warm-up (``actors.node_warm_up``: numba's set-up and
every kernel's first call, before its first hello), its worker and loader threads, first
sockets, the first turns of its event loop.
Measured with a real 1-node render of a few pixels (a fresh node process over real sockets)
against the simulator's prediction of the same render without it, for each runtime: an
``async`` render for the node runtimes, an ``image`` render for the sort-first nodes, which
run the one-process runtime, a ``spec-insitu`` render for the in-situ nodes. The calibration
takes the least of the three as ``warmup_s`` and the rest as ``node_setup_s``,
``tile_setup_s`` and ``insitu_setup_s``."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene.store import Store
from vastray.sim.costs import CostModel

#: Seconds the real 1-node render may take before the calibration gives up on it.
NODE_RENDER_TIMEOUT_S = 300.0
#: Simulations of the few-pixel render per real one (each about 0.2 s of wall time): the
#: simulations are the noisy side (``setup_cost``).
SIMULATIONS_PER_RENDER = 3


def setup_cost(store_path: str | os.PathLike, costs: CostModel, config: SceneConfig,
               settings: RenderSettings, scheduler: str, repeats: int = 1) -> float:
    """What a real 1-node ``scheduler`` render's busy seconds exceed its simulation's (with
    no set-up cost) by, >= 0: the median over ``repeats`` pairs of a real render and the
    median of ``SIMULATIONS_PER_RENDER`` simulations right after it.

    Parameters
    ----------
    store_path : the store rendered.
    costs : every other constant, measured already.
    config, settings : the render (one pass, one thread, as the nodes of a job run it).
    scheduler : ``async`` (``node_setup_s``), ``image`` (``tile_setup_s``) or
        ``spec-insitu`` (``insitu_setup_s``).
    repeats : real renders (each a fresh node process). None is left untimed: the first
        process to run the kernels on a machine compiles them into numba's cache (2.8 s for
        ``spec-insitu``'s on a fresh machine), which every node now does before its first
        hello (``actors.node_warm_up``), outside the busy span timed here; the calibration
        has read the store's files before (``time_loads``).

    Notes
    -----
    The cost is a difference of two renders of about 0.2 s, and a simulation charges the CPU
    time its traces and decisions take here, which moves by a third from one to the next
    (0.109-0.187 s against real renders' 0.152-0.156 s, rm 64³, session 32). Three real
    renders and then nine simulations still gave 0, 0.048 and 0.066 s in three calibrations
    of one evening (session 33), charged to each of 8 nodes on 2 cores: the scan's 8-node rows
    +45 to +75 % at 0.066. Each real render is now paired with the simulations right after
    it, so both sides of a difference see the machine at one moment.

    What it measures is not all a node's own: on rm 64³ the difference is about 0 in one
    domain (one load) and grows about 2.5-3 ms a load (18 and 32 loads, session 33), what a
    load costs inside a render beyond the calibration's isolated loads (``time_loads``).
    Charged per node, it over-charges nodes that load few domains.
    """
    from vastray.sim.simulate import simulate

    options = JobOptions(scheduler=scheduler, threads=1)
    unset = replace(costs, node_setup_s=0.0, tile_setup_s=0.0, insitu_setup_s=0.0)
    store = Store(store_path)
    differences = []
    for _ in range(max(repeats, 1)):
        busy = render_distributed(store_path, None, settings, 1, options=options,
                                  config=config, timeout=NODE_RENDER_TIMEOUT_S
                                  ).seconds["busy_max"]
        simulated = float(np.median([
            simulate(store, options, 1, unset, settings, config, max_pass_spp=None).seconds
            for _ in range(SIMULATIONS_PER_RENDER)]))
        differences.append(busy - simulated)
    return max(0.0, float(np.median(differences)))
