"""What a node costs once beyond the model's traces, loads and messages: what is left of a
fresh process's first use after its warm-up (``actors.node_warm_up``: numba's set-up and
every kernel's first call, before its first hello), its worker and loader threads, first
sockets, the first turns of its event loop.
Measured with a real render of a few pixels on ``SETUP_NODES`` fresh node processes sharing
the machine's cores (real sockets) against the simulator's prediction of the same render
without it, for each runtime: an ``async`` render for the node runtimes, an ``image`` render
for the sort-first nodes, which run the one-process runtime, a ``spec-insitu`` render for
the in-situ nodes. The calibration takes the least of the three as ``warmup_s`` and the rest
as ``node_setup_s``, ``tile_setup_s`` and ``insitu_setup_s``."""

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

#: Node processes of the renders that measure it. A cost a node pays once is charged to every
#: node, and a validation runs up to 8 nodes on 2 cores: measured on one node it was what
#: that lone node paid beyond its simulation, 0.007-0.066 s from one calibration to the next,
#: growing with the node's work (about 9 % of it) and absent when 8 nodes shared the same
#: render (the same 16x12 pixels of rm 64³, 3 pairs each, session 44: a lone ``async`` node
#: -0.018 to +0.066 s, each of 8 nodes -0.012 to +0.019 s), so 8 x that lone node's excess
#: over-charged the scan's 8-node rows by up to 75 %. Eight nodes pay 8 set-ups in one
#: difference, so its noise per node is an eighth's.
SETUP_NODES = 8
#: Seconds the real render may take before the calibration gives up on it.
NODE_RENDER_TIMEOUT_S = 300.0
#: Simulations of the few-pixel render per real one (each about 0.2 s of wall time): the
#: simulations are the noisy side (``setup_cost``).
SIMULATIONS_PER_RENDER = 3


def setup_cost(store_path: str | os.PathLike, costs: CostModel, config: SceneConfig,
               settings: RenderSettings, scheduler: str, repeats: int = 1,
               nodes: int = SETUP_NODES) -> float:
    """What each node of a real ``nodes``-node ``scheduler`` render pays beyond the simulation
    of it (with no set-up cost, the nodes sharing ``costs.cores`` as here), >= 0: the median
    over ``repeats`` pairs of a real render and the median of ``SIMULATIONS_PER_RENDER``
    simulations right after it, their difference over what one node's set-up adds to the
    simulated span (``span_per_setup``).

    Parameters
    ----------
    store_path : the store rendered.
    costs : every other constant, measured already.
    config, settings : the render (one pass, one thread, as the nodes of a job run it).
    scheduler : ``async`` (``node_setup_s``), ``image`` (``tile_setup_s``) or
        ``spec-insitu`` (``insitu_setup_s``).
    nodes : node processes of each render (``SETUP_NODES``).
    repeats : real renders (each on fresh node processes). None is left untimed: the first
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

    On one node what it measured was not all a node's own: on rm 64³ the difference was
    about 0 in one domain (one load) and grew with the loads and activations, about 9 % of
    the lone node's work (sessions 33 and 43), which 8 nodes sharing the cores did not pay
    (``SETUP_NODES``).
    """
    from vastray.sim.simulate import simulate

    options = JobOptions(scheduler=scheduler, threads=1)
    unset = replace(costs, node_setup_s=0.0, tile_setup_s=0.0, insitu_setup_s=0.0
                    ).with_cores(costs.cores)
    store = Store(store_path)
    differences = []
    for _ in range(max(repeats, 1)):
        busy = render_distributed(store_path, None, settings, nodes, options=options,
                                  config=config, timeout=NODE_RENDER_TIMEOUT_S
                                  ).seconds["busy_max"]
        simulated = float(np.median([
            simulate(store, options, nodes, unset, settings, config,
                     max_pass_spp=None).seconds
            for _ in range(SIMULATIONS_PER_RENDER)]))
        differences.append(busy - simulated)
    return max(0.0, float(np.median(differences)) / span_per_setup(costs, nodes))


def span_per_setup(costs: CostModel, nodes: int) -> float:
    """Seconds a cost every one of ``nodes`` busy nodes pays once adds to their span: 1 where
    each has a core (``costs.cores`` None, or ``nodes`` and ``costs.others`` within the
    cores), else one over each node's share of the aggregate throughput of ``nodes`` and the
    others' busy processes on the cores (``CostModel.throughput_at``)."""
    if costs.cores is None or nodes + costs.others <= costs.cores:
        return 1.0
    busy = nodes + costs.others
    return busy / max(costs.throughput_at(busy), 1e-9)
