"""One render node: an asyncio process with a management actor (the node's ZeroMQ endpoint),
a render worker (Embree and numpy off the event loop) and a tree-reduce actor.

Run by the coordinator (``vastray render --nodes N``), by ``vastray launch`` over SSH, or by
hand: ``vastray node --coordinator tcp://HOST:PORT`` (the coordinator assigns ranks).
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import logging
import math
import os
import socket
import sys
import threading
import time
from types import SimpleNamespace

import zmq
import zmq.asyncio

from vastray.actors import protocol
from vastray.actors.decomposition import render_owned_domains
from vastray.actors.film_wire import film_frames
from vastray.actors.insitu import render_spec_insitu
from vastray.actors.job_options import JobOptions
from vastray.actors.management import ManagementActor
from vastray.actors.node_ahead import GrantedPasses, traces_ahead
from vastray.actors.node_state import NodeState
from vastray.actors.node_warm_up import warm_node
from vastray.actors.rendezvous import (
    RESOLVE_WAIT_S,
    coordinator_address,
    launcher_rank,
    read_address,
)
from vastray.actors.tree_reduce import TreeReduceActor
from vastray.processes import Terminated, peak_rss_bytes, stoppable
from vastray.render.film import FILM_BYTES_PER_PIXEL
from vastray.render.progressive import StopRules
from vastray.render.scene_config import SceneConfig, parse_scene_config
from vastray.request import positive_float
from vastray.scene.cpu_binding import bind_process, parse_cpus
from vastray.scene.cpus import CpuClock, cgroup_cpu_quota
from vastray.scene.errors import InputError
from vastray.schedule import registry
from vastray.schedule.registry import Runtime
from vastray.transport.codec import encode
from vastray.transport.join_secret import read_secret_fd, wait_for_join_secret
from vastray.transport.keys import load_node_keys
from vastray.transport.security import Credentials, Gate, check_bind

log = logging.getLogger(__name__)


class RankFormatter(logging.Formatter):
    """``node RANK: message``: ``?`` until the rank is known (given, or assigned in the job)."""

    rank: int | str = "?"

    def format(self, record: logging.LogRecord) -> str:
        return f"node {RankFormatter.rank}: {super().format(record)}"


class JobAborted(RuntimeError):
    """The coordinator called a regroup: the work of the current job is dropped."""


async def run_node(coordinator: str, rank: int, timeout: float, bind_host: str = "127.0.0.1",
                   advertise: str | None = None, credentials: Credentials | None = None
                   ) -> None:
    """Serve render jobs from ``coordinator``: say hello, render this node's share, reduce
    films, stop.

    ``rank`` -1 lets the coordinator assign one (nodes started by docker compose or SSH).
    ``credentials``: this node's keys, or the coordinator's join secret (default: read from
    the file a coordinator of this user on this machine leaves, ``join_secret_path``).
    When the coordinator loses another node mid-frame it tells the survivors to regroup: this
    node drops the job (its work, sockets and caches) and joins the same coordinator again,
    with the same credentials, for the job on one node fewer (new ranks, domains reassigned).
    A node that hears nothing from the coordinator mid-job (no regroup, no heartbeat) still
    exits on its own after ``protocol.COORDINATOR_SILENCE_S``.
    """
    # a fresh process's first use of the render kernels (``node_warm_up.warm_node``: numba's
    # set-up and each kernel's first call), on a thread while the node waits for its
    # coordinator and makes its sockets, and done before its first hello: the coordinator
    # starts a job once every node has said hello, so every node starts its work at once
    # (finished after the job came, it held back some nodes' starts: 8 nodes on 2 cores then
    # ran staggered, which no node's busy time shows and the simulator does not model)
    warming = asyncio.ensure_future(asyncio.to_thread(warm_node))
    warming.add_done_callback(_log_warm)
    if credentials is None:
        port = int(coordinator.rpartition(":")[2])
        log.info("waiting up to %.0f s for a coordinator of this user on port %d", timeout,
                 port)
        credentials = Credentials(secret=await wait_for_join_secret(port, timeout))
    check_bind(bind_host, credentials)
    ctx = zmq.asyncio.Context()
    gate = Gate(ctx, secret=credentials.secret, what="this node")
    if advertise is None:
        advertise = _outbound_address(coordinator) if bind_host in ("0.0.0.0", "*") else bind_host
    warn_of_a_quota_below_a_core()
    try:
        await warming
        while await _serve_job(ctx, gate, coordinator, rank, timeout, bind_host, advertise,
                               credentials):
            log.info("joining %s again", coordinator)
    finally:
        gate.close()
        ctx.destroy(linger=0)


def warn_of_a_quota_below_a_core(quota: float | None = None) -> None:
    """Say so where this node's cgroup holds it to less than one CPU (``quota``: read from
    its cgroup when None). Such a node runs at full speed until its quota for the period is
    spent, then not at all until the period ends; a bulk-synchronous round waits on it."""
    quota = cgroup_cpu_quota() if quota is None else quota
    if quota is not None and quota < 1.0:
        log.warning("this node's cgroup holds it to %.2g CPU (a CPU quota): where its quota "
                    "for a period (100 ms by default) is spent it waits for the next, and "
                    "rounds over the nodes wait on it (the report's cpu_throttled_s); give "
                    "each node at least 1 CPU, or share the cores without a quota", quota)


def _log_warm(warming: asyncio.Future) -> None:
    """Say when the warm-up is done (its seconds) and how this node queries Embree, so a log
    shows how long a node took and whether its host traces packets (``library.description``:
    a render's report describes the coordinator's process, not each host's)."""
    if not warming.cancelled() and warming.exception() is None:
        from vastray.scene.embree.library import description

        embree = description() or {}
        how = (f"Embree {embree['version']}, {embree['queries']}" if "queries" in embree
               else embree.get("binding", "Embree not loaded"))
        log.info("render kernels warm (%.1f s; %s)", warming.result(), how)


async def _serve_job(ctx, gate: Gate, coordinator: str, rank: int, timeout: float,
                     bind_host: str, advertise: str, credentials: Credentials) -> bool:
    """Join the coordinator and serve one job on fresh sockets; True when the coordinator
    called a regroup (join again), False once the job is done and stopped."""
    if credentials.curve:
        gate.close_until_known()  # peers of this job: known from its job message
    management = ManagementActor(ctx, coordinator, bind_host, advertise, timeout, credentials,
                                 gate)
    log.info("listening for peers on %s", management.endpoint)
    advertised = peer_endpoint(management)
    watchers = []
    try:
        handshake = asyncio.ensure_future(management.watch_handshake(coordinator))
        watchers.append(handshake)
        hello = encode(protocol.HELLO, {}, {
            "rank": rank, "endpoint": advertised, "host": socket.gethostname(),
            "pid": os.getpid()})
        job = (await join(management, hello, handshake)).meta
        RankFormatter.rank = int(job["rank"])  # assigned (compose, SSH), or new after a regroup
        log.info("joined %s as node %d of %d", coordinator, int(job["rank"]), int(job["size"]))
        management.coordinator_heard = time.monotonic()
        watchers.append(asyncio.ensure_future(
            management.watch_coordinator(protocol.COORDINATOR_SILENCE_S)))
        aborted = threading.Event()
        work = asyncio.ensure_future(_serve(management, job, watchers, aborted))
        regroup = asyncio.ensure_future(management.mailbox(protocol.REGROUP).get())
        await asyncio.wait([work, regroup], return_when=asyncio.FIRST_COMPLETED)
        if work.done() and work.exception() is None:  # done and stopped
            regroup.cancel()
            return False
        if work.done() and not regroup.done():
            # Failed: say why, then give the coordinator a moment to call a regroup instead
            # (the failure may follow from a node lost elsewhere, such as a wait on it).
            await _report_failure(management, int(job["rank"]), work.exception())
            for task in watchers:  # the wait is bounded: no exit on the coordinator's silence
                task.cancel()
            await asyncio.wait([regroup], timeout=protocol.COORDINATOR_SILENCE_S)
            if not regroup.done():
                regroup.cancel()
                work.result()  # raises what failed the job
        # The regroup is the coordinator's last word on this job: it is silent from now on
        # until the next job, so its silence while the job is dropped (a pool or loader thread
        # still finishing a long trace or load) is no loss of it.
        for task in watchers:
            task.cancel()
        aborted.set()  # a render thread still running stops at its next tile
        await drop_job(work)
        log.warning("the coordinator regroups (%s); dropping this job",
                    regroup.result().meta["lost"])
        return True
    finally:
        for task in watchers:
            task.cancel()
        management.close()


async def join(management: ManagementActor, hello: list, handshake: asyncio.Future):
    """Say ``hello`` to the coordinator until its job comes, and return the job message;
    raise ``AuthenticationFailed`` as soon as ``handshake`` (``watch_handshake``) does.

    Every wait races the handshake's watch, the first send too: ZeroMQ drops the connection
    of a refused handshake, so a hello sent after the refusal waits for a connection that
    never comes (on a busy machine the refusal can come first: the node waited out its
    timeout and said ``TimeoutError``, not "authentication failed")."""
    async def first(work):
        task = asyncio.ensure_future(work)
        await asyncio.wait([task, handshake], return_when=asyncio.FIRST_COMPLETED)
        if not task.done():
            task.cancel()
            handshake.result()  # raises AuthenticationFailed
        return task.result()

    await first(management.to_coordinator(hello))
    # Say hello again every heartbeat until the job comes. A hello that reached a
    # coordinator socket about to close (the last job's, after a regroup) is lost with it;
    # the repeat reaches the next one.
    repeating = asyncio.ensure_future(management.repeat_to_coordinator(hello))
    try:
        return await first(management.receive(protocol.JOB, "job from the coordinator"))
    finally:
        repeating.cancel()


def peer_endpoint(management: ManagementActor) -> str:
    """The endpoint this node tells its peers (in its hello) to send to: its own.
    (``bench/fault_node.py`` replaces it to put a fault-injecting proxy in between.)"""
    return management.endpoint


async def drop_job(work: asyncio.Future) -> None:
    """Cancel the work of a job the coordinator regrouped away from, and wait for it to end.
    (``bench/fault_node.py`` slows it down to test that the coordinator's silence meanwhile
    is not taken for its loss.)"""
    work.cancel()
    try:
        await work
    except (asyncio.CancelledError, Exception):  # noqa: BLE001 - the job is dropped
        pass


async def _report_failure(management: ManagementActor, rank: int, exc: BaseException) -> None:
    """Tell the coordinator why this node's job failed, before the node exits: it names the
    node and the error at once (a node started elsewhere has no log the coordinator reads),
    and counts it lost like any node that exits mid-frame. Best effort: a second at most."""
    message = encode(protocol.FAILED, {}, {"rank": rank,
                                          "error": f"{type(exc).__name__}: {exc}"[:300],
                                          "input": isinstance(exc, InputError)})
    management.coordinator.setsockopt(zmq.LINGER, 1000)  # let it leave before the close
    try:
        await asyncio.wait_for(management.coordinator.send_multipart(
            [management.token or b"", *message], copy=False), 1.0)
    except (TimeoutError, zmq.ZMQError):
        pass


async def _serve(management: ManagementActor, job: dict, watchers: list,
                 aborted: threading.Event) -> None:
    """Render this node's share of ``job`` (every frame), reduce the films, report, and wait
    for the stop. Once ``aborted`` is set, progress reports raise ``JobAborted`` (in a render
    thread: at its next tile)."""
    from vastray.render.integrators import RenderSettings
    from vastray.scene.store import Store

    rank, size = int(job["rank"]), int(job["size"])
    options = JobOptions.from_wire(job["options"])  # refuses another version, unknown fields
    settings = RenderSettings(**job["settings"])
    store = Store(job["store"])
    config = (SceneConfig() if not job.get("scene_toml")
              else parse_scene_config(job["scene_toml"], job.get("scene_source") or "scene"))
    if job.get("frames") is None:  # one image: the scene where the job's frame puts it
        config = config.at_frame(int(job.get("frame", 0)), *store.world_bounds,
                                 settings.width, settings.height)
    loop = asyncio.get_running_loop()
    done = {"paths": 0}

    def report(paths: int) -> None:
        """Tell the coordinator this node finished ``paths`` more paths (any thread)."""
        if aborted.is_set():
            raise JobAborted("the coordinator called a regroup")
        done["paths"] += paths
        message = encode(protocol.PROGRESS, {}, {"rank": rank, "paths": done["paths"]})
        loop.call_soon_threadsafe(
            lambda: asyncio.ensure_future(management.to_coordinator(message)))

    async def heartbeat() -> None:
        while True:
            await asyncio.sleep(protocol.HEARTBEAT_S)
            # cpu_s: the process's CPU time, so the coordinator can tell a node whose render
            # thread hangs (no CPU) while this loop still beats from one that works
            await management.to_coordinator(encode(protocol.HEARTBEAT, {}, {
                "rank": rank, "waiting_s": management.waiting_s(),
                "cpu_s": round(time.process_time(), 3)}))

    beating = asyncio.ensure_future(heartbeat())
    tree = TreeReduceActor(management, rank, size)
    state = NodeState()
    units = job_units(job)
    totals: dict = {}
    frame_totals: dict = {}
    busy_total = reduce_total = frame_busy = frame_reduce = 0.0
    inputs: dict = {}  # frame -> its settings and scene (resolved once per frame)
    rendered = 0  # units rendered so far: they label tiles, statuses and films in order

    async def deliver(unit: int, film, time_rule: dict | None = None) -> None:
        """Reduce the film of ``unit`` (the next one rendered) over the nodes; node 0 sends
        it to the coordinator, with what its time rule predicts from where passes were
        traced ahead (``Progression.add_pass``'s ``ahead_seconds`` and ``traced_ahead``)."""
        nonlocal rendered, reduce_total, frame_reduce
        frame = units[unit][0]
        state.ordinal, state.frame = rendered, frame or 0
        rendered += 1
        reduce_start = time.perf_counter()
        film = await tree.reduce_film(film, settings.width, settings.height, state.ordinal)
        reduce_s = time.perf_counter() - reduce_start
        reduce_total, frame_reduce = reduce_total + reduce_s, frame_reduce + reduce_s
        if rank == 0:
            meta = {"rank": rank, "unit": unit, **(time_rule or {})}
            await management.to_coordinator(film_frames(
                film, meta if frame is None else dict(meta, frame=frame)))

    async def delivered_and_granted(unit: int, film,
                                    time_rule: dict | None = None) -> tuple[int, tuple]:
        """``deliver``, then the unit to render next: the coordinator's grant where a rule
        may stop the render (paced), else the following one (-1: none); with the time
        rule's clock of it (``Progression.pass_clock``; (None, None) without a limit)."""
        await deliver(unit, film, time_rule)
        if job["paced"]:
            return await _granted_with_clock(management, unit, len(units))
        return (unit + 1 if unit + 1 < len(units) else -1), (None, None)

    async def render_units(unit: int, frame, first: int, stop: int, frame_settings,
                           frame_config, start: float, cpu_start: tuple) -> int:
        """Render ``unit`` (with the units that go in one sweep with it, ``units_together``),
        deliver their films, and return the unit to render next (-1: none)."""
        nonlocal busy_total, frame_busy
        group = units_together(units, unit, options,
                               job["paced"] or job.get("passes_apart", False),
                               len(store.domains), settings.width * settings.height)
        if len(group) > 1:  # every pass in one sweep of tiles (issue 40)
            films, counters = await render_passes_together(
                options, rank, size, store, frame_config, frame_settings,
                [units[u][1:] for u in group], report, state)
        else:
            # the ordinal counts the units rendered, not their number: a rule that stops a
            # frame early skips its other passes, and labels follow one another
            state.ordinal, state.frame = rendered, frame or 0
            film, counters = await render_share(
                management, tree, options, rank, size, store, frame_config,
                frame_settings.window(first, stop), report, state)
            films = [film]
        busy = time.perf_counter() - start
        busy_total, frame_busy = busy_total + busy, frame_busy + busy
        # the process's CPU seconds (all its threads) over the same span: what of the busy
        # time used the cores, and what waited (the simulator's split); and what a CPU
        # quota held it back
        counters = {**counters, **cpu_clock.since(cpu_start)}
        for unit, film in zip(group, films, strict=True):
            counters = _report_counters(counters, management)
            accumulate_counters(totals, counters)
            accumulate_counters(frame_totals, counters)
            counters = {}  # a sweep's counters go with its first pass
            await deliver(unit, film)
        if job["paced"]:  # the coordinator rules on this pass before the next
            return await _granted(management, unit, len(units))
        return unit + 1 if unit + 1 < len(units) else -1

    ahead = traces_ahead(job, options, len(store.domains))
    cpu_clock = CpuClock()
    # what the time rule knows of the unit under way (``Progression.pass_clock``): the job's
    # first unit's, then each grant's
    clock = _clock_of(job.get("pass_clock"))
    try:
        try:
            unit = 0 if units else -1
            while unit >= 0:
                frame, first, stop = units[unit]
                if frame not in inputs:
                    inputs.clear()
                    inputs[frame] = frame_inputs(settings, config, store, frame)
                frame_settings, frame_config = inputs[frame]
                start, cpu_start = time.perf_counter(), cpu_clock.mark()
                if ahead:
                    # passes apart, each delivered and granted as it ends, while the render
                    # thread traces the next ones ahead (issue 40)
                    unit, clock, counters, waiting = await render_units_ahead(
                        options, rank, size, store, frame_config, frame_settings, units, unit,
                        delivered_and_granted, report, state, aborted, clock)
                    busy = time.perf_counter() - start - waiting
                    busy_total, frame_busy = busy_total + busy, frame_busy + busy
                    counters = _report_counters({**counters, **cpu_clock.since(cpu_start)},
                                                management)
                    accumulate_counters(totals, counters)
                    accumulate_counters(frame_totals, counters)
                else:
                    unit = await render_units(unit, frame, first, stop, frame_settings,
                                              frame_config, start, cpu_start)
                if frame is not None and (unit < 0 or units[unit][0] != frame):
                    # the frame's last pass: its counters on their own
                    await management.to_coordinator(encode(protocol.FRAME, {}, {
                        "rank": rank, "frame": frame, "busy_s": round(frame_busy, 4),
                        "reduce_s": round(frame_reduce, 4), "counters": frame_totals}))
                    frame_totals, frame_busy, frame_reduce = {}, 0.0, 0.0
        finally:
            state.close()
        stats = {"rank": rank, "busy_s": round(busy_total, 4),
                 "reduce_s": round(reduce_total, 4),
                 "counters": _report_counters(totals, management)}
        await management.to_coordinator(encode(protocol.DONE, {}, stats))
        for task in watchers:  # the work is delivered: a slow stop is no loss of the coordinator
            task.cancel()
        # Heartbeats go on until the stop: a node done with its share is still in the job (a
        # regroup may call it back), and the coordinator tells a lost node by its silence.
        await management.receive(protocol.STOP, "stop from the coordinator")
    finally:
        beating.cancel()
    log.info("finished: busy %.2f s, %d domain loads", busy_total, int(totals.get("loads", 0)))


def job_units(job: dict) -> list[tuple[int | None, int, int]]:
    """The job's units of work in order: (frame or None, first sample, stop sample), one per
    pass of each frame."""
    return [(None if u[0] is None else int(u[0]), int(u[1]), int(u[2])) for u in job["units"]]


async def _granted(management, unit: int, count: int) -> int:
    """The unit the coordinator grants after ``unit`` (-1: none, the job is done)."""
    return (await _granted_with_clock(management, unit, count))[0]


async def _granted_with_clock(management, unit: int, count: int) -> tuple[int, tuple]:
    """The unit the coordinator grants after ``unit`` (-1: none, the job is done) and the
    time rule's (budget_s, per_sample_s) of it (``Progression.pass_clock``), each None where
    the grant does not say."""
    message = await management.receive(protocol.GRANT, "pass grant from the coordinator")
    granted = int(message.meta["next"])
    if granted != -1 and not unit < granted < count:
        raise RuntimeError(f"the coordinator granted unit {granted} after unit {unit} of "
                           f"{count}")
    return granted, _clock_of([message.meta.get(key) for key in ("budget_s", "per_sample_s")])


def _clock_of(values) -> tuple:
    """(budget_s, per_sample_s) from a job's ``pass_clock``: each None where not told."""
    values = values if isinstance(values, list | tuple) and len(values) == 2 else (None, None)
    return tuple(_seconds_or_none(v) for v in values)


def _seconds_or_none(value) -> float | None:
    """A grant's optional seconds: a finite number, else None (not told)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


async def render_units_ahead(options: JobOptions, rank: int, size: int, store, config, settings,
                             units: list, unit: int, deliver, report, state: NodeState,
                             aborted: threading.Event, clock: tuple
                             ) -> tuple[int, tuple, dict, float]:
    """This node's share of the passes of ``units[unit]``'s frame from ``unit`` on, later
    passes traced ahead (``node_ahead``): each pass, as it ends, is delivered
    (``deliver(unit, film)``, awaited on this event loop while the render thread waits) and
    ruled on by the coordinator. ``clock``: the time rule's (budget_s, per_sample_s) of
    ``units[unit]`` (``Progression.pass_clock``). Returns the unit granted after the last
    one delivered (-1: none) and its clock, the render's counters and the seconds spent
    delivering and waiting for grants."""
    from vastray.actors.local import render_out_of_core

    loop = asyncio.get_running_loop()
    frame = units[unit][0]
    mine = [u for u in range(unit, len(units)) if units[u][0] == frame]
    waiting = 0.0

    def delivered(u: int, film, time_rule: dict) -> tuple[int, tuple]:  # on the render thread
        nonlocal waiting
        start = time.perf_counter()
        try:
            return waited_on(loop, deliver(u, film, time_rule), aborted)
        finally:
            waiting += time.perf_counter() - start

    passes = GrantedPasses(mine, [units[u][1:] for u in mine], delivered, clock)
    result = await asyncio.to_thread(
        render_out_of_core, store, config, settings, options, progress=False,
        share=(rank, size), on_tile=report, progression=passes, state=state)
    return passes.granted, passes.clock, result.counters, waiting


#: Seconds between a render thread's looks at the job's abort while it waits on the loop.
ABORT_POLL_S = 0.25


def waited_on(loop: asyncio.AbstractEventLoop, work, aborted: threading.Event):
    """Run the coroutine ``work`` on ``loop`` from another thread and return its result;
    once ``aborted`` is set (a regroup), cancel it and raise ``JobAborted``."""
    future = asyncio.run_coroutine_threadsafe(work, loop)
    while True:
        try:
            return future.result(timeout=ABORT_POLL_S)
        except concurrent.futures.TimeoutError:
            if aborted.is_set():
                future.cancel()
                raise JobAborted("the coordinator called a regroup") from None


async def render_share(management, tree, options: JobOptions, rank: int, size: int, store,
                       config, settings, report, state: NodeState):
    """This node's partial film of one frame and its counters, by the runtime of the job's
    scheduler (``schedule.registry``)."""
    # (the tile runtime refuses the others, naming the schedulers it runs)
    runner = NODE_RUNTIMES.get(registry.spec(options.scheduler).runtime, _tiles_share)
    return await runner(management, tree, options, rank, size, store, config, settings,
                        report, state)


async def _in_situ_share(management, tree, options, rank, size, store, config, settings,
                         report, state):
    return await render_spec_insitu(management, tree, options, rank, size, store, config,
                                    settings, on_tile=report, state=state)


async def _domains_share(management, tree, options, rank, size, store, config, settings,
                         report, state):
    return await render_owned_domains(management, options, rank, size, store, config,
                                      settings, on_tile=report, state=state, tree=tree)


async def _tiles_share(management, tree, options, rank, size, store, config, settings,
                       report, state):
    from vastray.actors.local import render_out_of_core

    result = await asyncio.to_thread(
        render_out_of_core, store, config, settings, options, progress=False,
        share=(rank, size), on_tile=report, state=state)
    return result.film, result.counters


#: The runner of each runtime that runs on nodes (``Runtime.on_nodes``).
NODE_RUNTIMES = {Runtime.IN_SITU: _in_situ_share, Runtime.DOMAINS: _domains_share,
                 Runtime.TILES: _tiles_share}


#: Most bytes of pass films a node's sweep over several passes holds (each pass's film waits
#: for the sweep's end before it is reduced): past it, fewer passes go together.
SWEEP_FILM_BYTES = 256 << 20


def units_together(units: list, unit: int, options: JobOptions, apart: bool, domains: int,
                   pixels: int) -> list[int]:
    """The units from ``unit`` on that a node renders in one sweep: out of core (a cache
    smaller than the store's ``domains``) and unless the passes are wanted ``apart`` (a rule
    may stop the render between them, or each pass's error against a reference is wanted as
    it ends), the passes of one frame in a tile schedule (``image``, ``spec-ooc``) run on from
    one into the next, so a domain is loaded once per tile, not once per pass (as one process
    does, ``sort_first.PassSpans``); as many as keep their films (of ``pixels`` pixels each) within
    ``SWEEP_FILM_BYTES``. Else ``unit`` alone. In core the node's cache keeps every domain
    from pass to pass, so passes apart cost no loads. Every node groups alike (the job and
    options are the same), so their reductions pair."""
    if (apart or not options.out_of_core(domains)
            or registry.spec(options.scheduler).runtime is not Runtime.TILES):
        return [unit]
    most = max(1, SWEEP_FILM_BYTES // max(1, pixels * FILM_BYTES_PER_PIXEL))
    frame = units[unit][0]
    group = [unit]
    while (len(group) < most and group[-1] + 1 < len(units)
           and units[group[-1] + 1][0] == frame):
        group.append(group[-1] + 1)
    return group


class UnitPasses:
    """The passes of a node's units of one frame, as ``local.render_out_of_core`` asks a
    progression for them (``sort_first.PassSpans``): the windows, and each pass's film kept as it is
    merged. Nothing is ruled on: the coordinator's progression rules on the films."""

    def __init__(self, windows: list[tuple[int, int]]):
        self.windows = list(windows)
        self.films: list = []
        self.rules = StopRules(int(self.windows[-1][1]))  # unpaced
        self.snapshot = SimpleNamespace(passes_done=0)

    def remaining(self) -> list[tuple[int, int]]:
        return self.windows

    def start(self) -> None:
        pass

    def next_pass(self) -> tuple[int, int, int] | None:
        k = len(self.films)
        return (k, *self.windows[k]) if k < len(self.windows) else None

    def add_pass(self, index: int, film) -> None:
        self.films.append(film)

    @property
    def film(self):
        return self.films[-1] if self.films else None


async def render_passes_together(options: JobOptions, rank: int, size: int, store, config,
                                 settings, windows: list[tuple[int, int]], report,
                                 state: NodeState) -> tuple[list, dict]:
    """This node's partial film of each pass in ``windows`` (sample ranges of one frame),
    traced in one sweep of sort-first tiles, and the sweep's counters."""
    from vastray.actors.local import render_out_of_core

    passes = UnitPasses(windows)
    result = await asyncio.to_thread(
        render_out_of_core, store, config, settings, options, progress=False,
        share=(rank, size), on_tile=report, progression=passes, state=state)
    return passes.films, result.counters


def frame_inputs(settings, config: SceneConfig, store, frame: int | None):
    """The settings and scene of one frame of an animation (``frame`` None: the job's own):
    the camera and lights where the frame puts them, the seed hashed with the frame."""
    if frame is None:
        return settings, config
    from vastray.animation import frame_settings

    lo, hi = store.world_bounds
    return (frame_settings(settings, frame),
            config.at_frame(frame, lo, hi, settings.width, settings.height))


def _report_counters(counters: dict, management: ManagementActor) -> dict:
    """A frame's (or the job's) counters as the node reports them: numbers and names only,
    plus the connections refused at the handshake, the messages dropped and its peak
    memory."""
    rejected = management.rejections
    return {**{k: v for k, v in counters.items() if isinstance(v, (int, float, str))},
            "refused_connections": management.gate.refusals + management.gate.failed_handshakes,
            "rejected_messages": rejected.total,
            "peak_rss_bytes": peak_rss_bytes(),
            **{f"rejected_{k}": v for k, v in rejected.counts.items()}}


#: Counters that are settings, not counts: a job's total keeps the latest frame's (pass's).
SETTING_COUNTERS = frozenset({"threads", "cache_capacity", "cache_bytes", "portal_resolution",
                       "load_bandwidth_mb_s", "max_samples_in_flight", "domains"})


def accumulate_counters(totals: dict, counters: dict) -> None:
    """Sum numeric counters over frames (names, peaks and settings: the latest)."""
    for key, value in counters.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool) \
                and not key.startswith("peak") and key not in SETTING_COUNTERS:
            totals[key] = totals.get(key, 0) + value
        else:
            totals[key] = value


def _outbound_address(coordinator: str) -> str:
    """This host's address on the route to the coordinator (what peers can reach)."""
    host, _, port = coordinator.removeprefix("tcp://").rpartition(":")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect((host, int(port)))  # UDP: picks a route, sends nothing
        return probe.getsockname()[0]


NODE_EPILOG = """\
examples:
  vastray node --coordinator tcp://head:5555 --bind 0.0.0.0 --keys vastray-keys
      (vastray-keys: this host's bundle, a copy of the coordinator's KEYS/bundles/NAME)
  srun vastray node --rendezvous /shared/job.addr --bind 0.0.0.0 --keys /local/vastray-keys
      (/local/vastray-keys: each host's own bundle, copied to its own disk beforehand)

in a Slurm batch script, the coordinator in the background, then one node per task:
  vastray render /shared/s.store -o o.exr --nodes "$SLURM_NTASKS" --listen 0.0.0.0:0 \\
      --rendezvous /shared/job.addr --keys ~/.vastray/keys &
  srun sh -c 'vastray node --rendezvous /shared/job.addr --bind 0.0.0.0 \\
      --keys ~/.vastray/keys/bundles/$(hostname -s)'
(the source repository's examples/slurm.sbatch is a complete script)
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vastray node", description=__doc__, epilog=NODE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--coordinator", metavar="tcp://HOST:PORT",
                       help="the coordinator's address (as it prints it; tcp:// may be left "
                            "out)")
    where.add_argument("--rendezvous", metavar="FILE",
                       help="read the coordinator's address from FILE on a shared file "
                            "system, waiting for it to appear (the coordinator's --rendezvous)")
    parser.add_argument("--rank", type=int,
                        help="this node's rank (default: the launcher's, from SLURM_PROCID, "
                             "PMI_RANK, PMIX_RANK or OMPI_COMM_WORLD_RANK; else assigned by "
                             "the coordinator)")
    parser.add_argument("--timeout", type=positive_float, default=120.0,
                        help="seconds a wait may last without a word from the coordinator "
                             "before the node gives up; a node done with its share waits as "
                             "long as the coordinator speaks (default: %(default)s)")
    parser.add_argument("--bind", default="127.0.0.1",
                        help="address to listen on for peers (beyond loopback needs --keys)")
    parser.add_argument("--advertise", help="address peers reach this node at (default: "
                                            "--bind, or for 0.0.0.0 this host's address on "
                                            "the route to the coordinator)")
    parser.add_argument("--keys", metavar="DIR",
                        help="this node's bundle from `vastray keys` (KEYS/bundles/NAME, "
                             "copied to this host: its own key pair and the coordinator's "
                             "public key; CURVE), or a key folder with --key-name; without "
                             "it, the node joins only a coordinator of this user on this "
                             "machine")
    parser.add_argument("--key-name", metavar="NAME",
                        help="which node key in DIR/nodes is this node's (`vastray keys "
                             "--node NAME`; default: a bundle's one key, else this host's "
                             "short name)")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="debug log output (the node logs at info level without it)")
    parser.add_argument("--cpus", metavar="LIST",
                        help="bind this node (every thread it runs) to these CPUs, e.g. 0-3 or "
                             "0,2; `vastray render --nodes N` gives each local node its share "
                             "of the CPUs where there are at least N (VASTRAY_BIND_NODES=0: "
                             "none); default: unbound")
    parser.add_argument("--secret-fd", type=int, metavar="FD", help=argparse.SUPPRESS)
    return parser


def die_with_parent() -> None:
    """For a node started by a coordinator on this machine: have the kernel kill this process
    the moment the coordinator exits, whatever kills it (Linux; elsewhere the heartbeat
    watch ends the node a few seconds later)."""
    parent = os.environ.get(protocol.PARENT_PID_ENV)
    if parent is None or not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != int(parent):  # the coordinator died before the request took effect
        os._exit(4)


def main(argv: list[str] | None = None, verbose: int = 0) -> int:
    """``vastray node``; ``verbose``: the ``-v`` flags given before ``node``."""
    args = build_parser().parse_args(argv)
    die_with_parent()
    rank = args.rank if args.rank is not None else launcher_rank()
    RankFormatter.rank = "?" if rank is None else rank
    logging.basicConfig(level=logging.DEBUG if verbose + args.verbose else logging.INFO)
    for handler in logging.getLogger().handlers:
        handler.setFormatter(RankFormatter("%(message)s"))
    if args.cpus:  # before any thread starts (ZeroMQ's, Embree's): they inherit it
        try:
            bound = bind_process(parse_cpus(args.cpus))
        except (ValueError, OSError) as exc:
            why = str(exc) if isinstance(exc, ValueError) else "none of them may be used here"
            print(f"node {RankFormatter.rank}: error: --cpus {args.cpus}: {why} (the CPUs "
                  f"this process may use: {','.join(map(str, sorted(os.sched_getaffinity(0))))})",
                  file=sys.stderr)
            return 2
        log.info("bound to CPU%s %s", "s" if len(bound) > 1 else "", ",".join(map(str, bound)))
    try:
        import uvloop
        uvloop.install()
    except ImportError:
        pass
    try:
        if args.key_name and not args.keys:
            raise InputError(None, "--key-name needs --keys DIR")
        credentials = None  # without keys: the join secret the coordinator left for its user
        if args.keys:
            credentials = Credentials(keys=load_node_keys(args.keys, args.key_name))
        elif args.secret_fd is not None:  # started by the coordinator: a pipe from it
            credentials = Credentials(secret=read_secret_fd(args.secret_fd))
        for flag, given in (("--coordinator", args.coordinator),
                            ("--rendezvous", args.rendezvous)):
            if given is not None and not given.strip():
                raise InputError(None, f"{flag} is empty; give the coordinator's "
                                       + ("address" if flag == "--coordinator" else "file"))
        coordinator = coordinator_address(args.coordinator
                                          or read_address(args.rendezvous, args.timeout),
                                          wait=min(args.timeout, RESOLVE_WAIT_S))
        host = coordinator.removeprefix("tcp://").rpartition(":")[0].strip("[]")
        if credentials is None and not (host.startswith("127.") or host in ("localhost",
                                                                             "::1")):
            raise InputError(None, f"joining {coordinator} needs --keys DIR: without keys a "
                                   "node joins only a coordinator of its user on its machine "
                                   "(on loopback)")
        asyncio.run(stoppable(run_node(coordinator, -1 if rank is None else rank,
                                       args.timeout, args.bind, args.advertise, credentials)))
    except InputError as exc:
        print(f"node {RankFormatter.rank}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM through the CLI: nothing to keep
        said, status = (("terminated", 143) if isinstance(stop, Terminated)
                        else ("interrupted", 130))
        print(f"node {RankFormatter.rank}: {said}", file=sys.stderr)
        return status
    except TimeoutError as exc:  # the coordinator silent for --timeout: said as it is
        print(f"node {RankFormatter.rank}: gave up: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # report, then fail: the coordinator names this node
        print(f"node {RankFormatter.rank}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
