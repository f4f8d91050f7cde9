"""The simplified model and virtual portals on a node (the temporal-coherence paper's §6):
each frame's routing to the simplified model, and after the frame the portals merged over the
nodes and the routing's counters reported."""

from __future__ import annotations

from vastray.actors.job_options import JobOptions
from vastray.actors.node_state import NodeState


def simplified_routing(store, setup, options: JobOptions, state: NodeState):
    """This frame's routing to the simplified model (``options.simplified``: a policy of
    ``schedule.simplified``), or None. The model is loaded once per node and never evicted;
    the portals recorded in the last recording frame are kept in ``state.portals``.

    ``options.portal_accuracy`` (portal policy) makes the run an instrumented one, for ACC:
    every frame is traced as a recording frame with a crossing log, and the crossings are
    classified with the portals a timed run would predict the frame with; only the frames a
    timed run records replace those portals (``finish_simplified``).

    With ``options.portal_memory`` a predicting frame records, into fresh portals, the
    depth-1 rays it traces fine; ``finish_simplified`` folds them into the kept ones."""
    policy = options.simplified
    if policy is None:
        return None
    from vastray.scene.bvh import DomainBVH
    from vastray.schedule.portals import CrossingLog, Portals, records_portals
    from vastray.schedule.simplified import SimplifiedRouting

    if state.simplified_bvh is None and policy != "none":
        state.simplified_bvh = DomainBVH(len(store.domains), store.load_simplified(), setup.keep,
                                         state.pool)
    lo, hi = store.domain_boxes()
    interval = options.portal_interval
    recording = policy == "portal" and records_portals(state.frame, interval,
                                                       state.portals is not None)
    measuring = policy == "portal" and options.portal_accuracy
    portals = None
    if policy == "portal":
        portals = (Portals(len(store.domains), options.portal_resolution)
                   if recording or measuring else state.portals)
    routing = SimplifiedRouting(state.simplified_bvh, len(store.domains), policy, lo,
                                hi, portals=portals, recording=recording or measuring,
                                threshold=float(options.portal_threshold))
    if policy == "portal" and options.portal_memory and not (recording or measuring):
        routing.fresh = Portals(len(store.domains), options.portal_resolution)
    if measuring:
        routing.log = CrossingLog(setup.total_paths)
        routing.reference = state.portals
        routing.keeps_portals = recording
    return routing


async def finish_simplified(routing, tree, state: NodeState, stats: dict, rank: int = 0,
                            memory: int = 0) -> None:
    """After a frame: merge a recording frame's portals over the nodes (MAX, by the
    tree-reduce actor) for the frames that follow, and report the routing's counters.

    An instrumented frame (``routing.log``) merges its crossing log in the same all-reduce,
    and node 0 reports, for every node (the counts are global), the crossings classified
    with the portals a timed run would predict the frame with (``acc_*``, on the frames a
    timed run predicts, not on its recording frames) and with the portals recorded in this
    very frame (``replay_*``: no false lows, since cells keep maxima).

    With ``memory`` (``--portal-memory``) an accumulating frame's fresh portals are merged
    over the nodes and folded into ``state.portals`` (``Portals.refresh``); an instrumented
    run folds into its reference the crossings that reference predicts high (those the timed
    run traces fine and records), so it predicts each frame with the timed run's portals."""
    if routing is None:
        return
    stats.update(routing.counters)
    stats["portal_recording"] = int(routing.recording and routing.keeps_portals)
    if routing.portals is not None:
        stats["portal_resolution"] = routing.portals.resolution
    if routing.fresh is not None:  # an accumulating frame: fold its records in
        from vastray.schedule.portals import Portals

        arrays = routing.fresh.to_arrays()
        if tree is not None:
            arrays = await tree.allreduce(arrays, dict(Portals.REDUCE))
        state.portals.refresh(Portals.from_arrays(arrays), memory)
    if routing.recording:
        from vastray.schedule.portals import CrossingLog, Portals, prediction_accuracy

        arrays, ops = routing.portals.to_arrays(), dict(Portals.REDUCE)
        if routing.log is not None:
            arrays.update(routing.log.to_arrays())
            ops.update(CrossingLog.REDUCE)
        merged = await tree.allreduce(arrays, ops) if tree is not None else arrays
        recorded = Portals.from_arrays(merged)
        if routing.keeps_portals:
            state.portals = recorded
        if routing.log is None:
            return
        cells, actual = CrossingLog.from_arrays(merged).crossings()
        reference = routing.reference if not routing.keeps_portals else None
        if rank == 0:
            stats.update(prediction_accuracy(recorded.predict(cells), actual,
                                             routing.threshold).counters("replay_"))
            if reference is not None:
                stats.update(prediction_accuracy(reference.predict(cells), actual,
                                                 routing.threshold).counters("acc_"))
        if reference is not None and memory:
            # what the timed run's frame records: the crossings it traces fine
            fine = reference.predict(cells) > routing.threshold
            fresh = Portals(reference.n_domains, reference.resolution)
            fresh.record(cells[fine], actual[fine])
            reference.refresh(fresh, memory)
