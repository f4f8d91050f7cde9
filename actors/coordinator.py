"""The coordinator (rank 0's driver): starts node processes, hands out the job, watches that
every node stays alive, receives the reduced film and the per-node reports.

Every wait has a timeout; a node that fails to start or join fails the run with a message
naming it, and the caller writes no output. A node lost mid-frame (it exits, or stops answering
for the heartbeat timeout) is survived: the frame is rendered again on one node fewer, started
again here, or regrouped from the nodes started elsewhere (see ``render_distributed``).

This module is the Python API and the attempts (one per node loss). One attempt on the nodes
is ``actors.attempt``; the watch over them ``actors.watch``; what is gathered from them
``actors.gather``; termination detection ``actors.termination``; the result from their
reports ``actors.results``.
"""

from __future__ import annotations

import asyncio
import logging
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

from vastray.actors.attempt import coordinate
from vastray.actors.gather import Passes
from vastray.actors.job_options import JobOptions, JobOptionsError, default_tile
from vastray.actors.node_failure import NodeFailure, NodeLost
from vastray.actors.node_logs import NodeLogs
from vastray.actors.results import render_result
from vastray.processes import stoppable
from vastray.render.driver import RenderResult, store_camera
from vastray.render.integrators import RenderSettings
from vastray.render.progress import RenderBar
from vastray.render.progressive import Progression, StopRules
from vastray.render.scene_config import SceneConfig, load_scene_config
from vastray.scene.cpus import available_cpus
from vastray.scene.errors import InputError
from vastray.scene.store import Store
from vastray.schedule import registry
from vastray.transport.join_secret import new_secret
from vastray.transport.keys import CoordinatorKeys

log = logging.getLogger(__name__)


def render_distributed(store_path: str | os.PathLike, scene_path: str | os.PathLike | None,
                       settings: RenderSettings, nodes: int, options: JobOptions | None = None,
                       timeout: float = 120.0, listen: str | None = None,
                       keys: CoordinatorKeys | None = None,
                       launched: dict[str, tuple[subprocess.Popen, Path]] | None = None,
                       progress: bool = False, config: SceneConfig | None = None,
                       rendezvous: str | os.PathLike | None = None,
                       heartbeat_timeout: float | None = None,
                       survive_node_loss: bool = True, frames: list[int] | None = None,
                       on_frame: Callable[[int, RenderResult], None] | None = None,
                       progression_of: Callable[[int | None], Progression] | None = None,
                       log_dir: str | os.PathLike | None = None) -> RenderResult:
    """Render with ``nodes`` node processes talking ZeroMQ.

    Parameters
    ----------
    options : the job's options, sent whole to every node (default: ``JobOptions()``, the
        ``image`` schedule on sort-first tiles). Where they leave them unset, the tile
        (``max_samples_in_flight``) is ``job_options.default_tile``'s (65536 paths a
        sort-first node; a domain-decomposition job's, shared by its nodes, 65536 or 4096
        a node past 16 nodes, at most 2^22), and ``threads`` this machine's
        cores shared among the nodes started here (with ``listen``: each node's own cores).
    timeout : seconds any single wait may take (start-up, silence of a node, shutdown).
    listen : ``HOST:PORT`` to wait for ``nodes`` nodes started elsewhere (docker compose,
        SSH); default: start them here as child processes, on loopback.
    keys : the coordinator's keys (``load_coordinator_keys``); with ``listen``, nodes join
        only with a key on their allow-list. Required to listen beyond loopback. Without
        keys, only nodes started here, or with ``listen`` (on loopback) nodes of this user on
        this machine (they read this render's join secret from ``join_secret_path``), join.
    launched : with ``listen``, processes started for the nodes elsewhere (name -> process,
        log file), e.g. ssh sessions: one that exits early fails the run with its name.
    max_batch_rays : most rays in one batch between two nodes (domain, async).
    progress : a progress bar on stderr fed by the nodes' finished tiles; with ``listen``,
        also a line for the wait and for every node that joins.
    config : the scene configuration (default: read from ``scene_path``); nodes receive its
        TOML text, so they need no copy of the file.
    rendezvous : with ``listen``, a file (on a file system the nodes share) to write this
        coordinator's address into once it listens, for ``vastray node --rendezvous``;
        removed when the render ends.
    heartbeat_timeout : a node silent this long mid-frame counts as lost (a stall); default
        ``timeout``.
    survive_node_loss : a node that dies or stalls mid-frame is survived: the frame is
        rendered again on the others (domains reassigned, every path re-traced from its
        deterministic seeds, nothing counted twice), so the image equals the fault-free one.
        Nodes started here are started again, one fewer; nodes started elsewhere
        (``listen``) are told to regroup: each drops the job and joins the same address again,
        and the coordinator waits for one node fewer (``timeout``, and the progress lines)
        before it sends the job again with new ranks. False: the run fails naming the node.
    frames : an animation's frame numbers: every node renders them all in one job (caches
        and statistics carry over from frame to frame), each frame with the camera and lights
        ``config.at_frame`` gives and the seed ``frame_seed(settings.seed, frame)``. None:
        one image with ``config`` and ``settings`` as they are.
    on_frame : with ``frames``, called as ``on_frame(frame, result)`` as each frame arrives
        (a node loss re-renders only the frames not yet delivered).
    progression_of : ``progression_of(frame)`` (frame None for one image), called once per
        frame: the sample-major passes to render it in and when to stop
        (``render.progressive``); node 0's film of each pass is merged there as it arrives,
        and with a rule that may stop early (``StopRules.paced``) each pass waits for the
        verdict on the one before. A node loss re-renders only the passes not yet merged.
        None: each frame in one pass of all its samples.
    log_dir : a folder to keep the logs of the nodes started here in (``nodeR.log``; a
        repeat after a node loss ``nodeR.attemptK.log``), named in the result's counters
        (``node_logs``). None: they are removed when the render ends.
    Returns
    -------
    The result of the image, or with ``frames`` of the last frame (its counters list every
    frame's under ``"frames"``).
    """
    options = JobOptions() if options is None else options
    scheduler = options.scheduler
    sched = registry.find(scheduler)
    if sched is None or not sched.runtime.on_nodes:
        raise JobOptionsError(f"--nodes runs the schedulers "
                              f"{', '.join(registry.names(lambda s: s.runtime.on_nodes))}; got "
                              f"{scheduler!r}")
    if nodes < 1:
        raise ValueError("--nodes must be at least 1")
    options = replace(
        options, max_samples_in_flight=(options.max_samples_in_flight
                                        or default_tile(scheduler, nodes)),
        threads=options.threads or (None if listen else max(1, available_cpus() // nodes)))
    store = Store(store_path)
    if sched.frame_statistics:
        from vastray.actors.temporal import check_temporal_domains

        check_temporal_domains(store)
    if options.simplified not in (None, "none") and store.simplified is None:
        raise InputError(store.path, "has no simplified model for --simplified; make one with "
                                     f"`vastray simplify {store.path} --ratio 0.01`")
    if options.simplified == "portal":
        from vastray.schedule.portals import check_portal_size

        try:
            check_portal_size(len(store.domains), options.portal_resolution)
        except ValueError as exc:
            raise InputError(store.path, str(exc)) from None
    config = config if config is not None else load_scene_config(scene_path)
    if config.text is None:
        raise ValueError("render_distributed needs a SceneConfig read from TOML: its text is "
                         "what the nodes receive")
    camera = store_camera(config, store, settings.width, settings.height)
    job = {
        "store": str(Path(store_path).resolve()),
        "scene_toml": config.text, "scene_source": config.source,
        "frame": config.frame,  # nodes resolve the scene's camera and lights at this frame
        "settings": asdict(settings), "options": options.to_wire(),
        "domains": len(store.domains),
    }
    secret = new_secret()  # the join secret without keys: one for every attempt
    logs = NodeLogs(log_dir if listen is None else None)
    try:
        return _render_attempts(job, store, config, camera, settings, nodes, options,
                                timeout, listen, keys, launched, progress, rendezvous,
                                heartbeat_timeout, survive_node_loss, frames, on_frame,
                                progression_of, secret, logs)
    finally:
        logs.close()


def _render_attempts(job, store, config, camera, settings, nodes, options, timeout, listen,
                     keys, launched, progress, rendezvous, heartbeat_timeout,
                     survive_node_loss, frames, on_frame, progression_of, secret: bytes,
                     logs: NodeLogs) -> RenderResult:
    """``render_distributed`` from its first attempt to the last (one per node loss)."""
    scheduler = options.scheduler
    start = time.perf_counter()
    total = settings.width * settings.height * settings.spp * len(frames or [None])
    progressions: dict[int | None, Progression] = {}

    def progression(frame: int | None) -> Progression:
        if frame not in progressions:
            progressions[frame] = (progression_of(frame) if progression_of is not None else
                                   Progression(settings.width, settings.height,
                                               StopRules(settings.spp, one_pass=True)))
        return progressions[frame]
    failures: list[str] = []
    recoveries: list[dict] = []  # per node lost: who, how, and which frames were done again
    size = nodes
    delivered: dict[int, RenderResult] = {}
    bound: dict[str, str] = {}  # the listen address as bound (its port, where 0 was asked)
    spare_exits = 0  # launched sessions of lost nodes still to exit (not failures)
    attempt = 0

    def frame_done(frame: int, film, reports: list[dict], seconds: float) -> None:
        lo, hi = store.world_bounds
        frame_camera = store_camera(config.at_frame(frame, lo, hi, settings.width,
                                                    settings.height),
                                    store, settings.width, settings.height)
        result = render_result(film, frame_camera, reports, scheduler, size, nodes,
                               failures, seconds, recoveries)
        result.counters["frame"] = frame
        if logs.kept:
            result.counters["node_logs"] = str(logs.folder)
        if progression_of is not None:
            result.progress = progression(frame).report()
        delivered[frame] = result
        if on_frame is not None:
            on_frame(frame, result)

    while True:
        remaining = None if frames is None else [f for f in frames if f not in delivered]
        for frame in [None] if frames is None else remaining:
            # the frame under way rules on its next pass anew: the pass granted was lost with
            # a node (time went by since), or it goes on from a checkpoint
            progression(frame).retake()
        for frame in remaining or ():  # merged whole before a loss, its reports lost with it
            if progression(frame).stopped_by is not None:
                frame_done(frame, progression(frame).film, [], 0.0)
        remaining = None if frames is None else [f for f in frames if f not in delivered]
        todo = [None] if frames is None else remaining
        units = [(frame, first, stop) for frame in todo
                 for first, stop in progression(frame).remaining()]
        if not units and listen is None:  # every frame is whole: no node to start for it
            film, reports = progression(None).film if frames is None else None, []
            break
        paced = any(progression(frame).rules.paced for frame in todo)
        # measured against a reference, each pass's error is wanted as it ends (a curve of
        # error against time): nodes then render the passes apart, not in one sweep of tiles
        apart = any(progression(frame).reference is not None for frame in todo)
        # what the time rule knows of the first unit's pass: nodes trace ahead only the
        # passes it may still grant (``node_ahead``; each grant brings it anew)
        clock = progression(units[0][0]).pass_clock() if units else (None, None)
        try:
            with RenderBar(total=total, unit="path", unit_scale=True, delay=2.0,
                          disable=not progress, desc=f"render ({scheduler}, {size} nodes)",
                          leave=False) as bar:
                passes = Passes(units, progression, paced, image=frames is None)
                film, reports = asyncio.run(stoppable(coordinate(
                    dict(job, frames=remaining, units=units, paced=paced,
                         passes_apart=apart, pass_clock=list(clock)), size, settings,
                    timeout, listen, keys, launched or {}, bar, progress, rendezvous,
                    heartbeat_timeout or timeout, frame_done,
                    regroup=survive_node_loss and size > 1, bound=bound,
                    spare_exits=spare_exits, passes=passes, secret=secret, logs=logs,
                    attempt=attempt)))
            break
        except NodeLost as lost:
            if not survive_node_loss or size == 1:
                raise NodeFailure(str(lost)) from None
            failures.append(str(lost))
            attempt += 1
            recoveries.append({"node": lost.rank, "cause": lost.cause, "frames": [0] if (
                frames is None) else [f for f in frames if f not in delivered]})
            size -= 1
            if listen is not None:  # the survivors regroup on the address bound first
                listen = bound["listen"]
                bound["regrouping"] = True
                launched, spare_exits = _without_exited(launched or {}, spare_exits)
            what = "the frame" if frames is None else "the frames not yet delivered"
            again = "" if listen is None else " once they have joined again"
            message = f"{lost}; rendering {what} again on the {size} other node(s){again}"
            if progress:  # the CLI's user sees it as a plain line, not as a log record
                print(message, file=sys.stderr)
            else:
                log.warning("%s", message)
    wall = time.perf_counter() - start
    if frames is None:
        result = render_result(film, camera, reports, scheduler, size, nodes,
                               failures, wall, recoveries)
        if logs.kept:
            result.counters["node_logs"] = str(logs.folder)
        if progression_of is not None:
            result.progress = progression(None).report()
        return result
    last = delivered[frames[-1]]
    last.counters["frames"] = [delivered[f].counters for f in frames]
    last.seconds["animation_total"] = round(wall, 4)
    return last


def _without_exited(launched: dict[str, tuple[subprocess.Popen, Path]], spare_exits: int
                    ) -> tuple[dict[str, tuple[subprocess.Popen, Path]], int]:
    """After a node loss: the launched sessions still running (those that exited are not
    waited for again), and how many of them belong to lost nodes and may still exit (a
    stalled node's session ends once its node notices the coordinator's silence)."""
    running = {name: entry for name, entry in launched.items() if entry[0].poll() is None}
    exited = len(launched) - len(running)
    return running, max(0, spare_exits + 1 - exited)


__all__ = ["render_distributed"]
