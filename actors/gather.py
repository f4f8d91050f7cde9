"""What the coordinator gathers from its nodes during one attempt: progress, node 0's film of
each pass merged into its frame's progression (and, paced, the grant of the next pass), each
animation frame handed on once its film and every node's report are in, and the nodes' last
reports."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from tqdm import tqdm

from vastray.actors import protocol
from vastray.actors.film_wire import film_from
from vastray.actors.node_failure import NodeFailure
from vastray.actors.watch import Watch
from vastray.render.integrators import RenderSettings
from vastray.transport.codec import encode


class Passes:
    """The job's units, (frame, first sample, stop sample), one per pass of each frame, as
    node 0's film of each arrives (in unit order): merged into its frame's progression; a
    frame is whole once its progression stops. Paced (a rule may stop a frame early), every
    unit waits for a grant: the next pass of the frame, the first of the next frame, or -1,
    with the time rule's clock of the pass granted (``Progression.pass_clock``).

    Parameters
    ----------
    units : the units of this attempt.
    progression : ``progression(frame)``, the frame's ``Progression``.
    paced : whether nodes wait for a grant after each unit.
    image : whether the job is one image (frame None), not an animation's frames.
    """

    def __init__(self, units: list[tuple], progression: Callable, paced: bool,
                 image: bool = True):
        self.units, self.progression, self.paced = units, progression, paced
        self.image = image
        self.expected = 0  # the unit whose film comes next
        self.send_grant = None

    @property
    def done(self) -> bool:
        return not self.units

    def image_film(self):
        """The image's film (None for an animation's frames, each handed on by itself)."""
        return self.progression(None).film if self.image else None

    def begin(self, send_grant) -> None:
        """Start the first unit's frame (its clock, its first pass)."""
        self.send_grant = send_grant
        if self.units:
            self._start(self.units[0])

    def _start(self, unit: tuple) -> None:
        frame, first, stop = unit
        step = self.progression(frame).next_pass()
        if step is None or step[1:] != (first, stop):
            raise RuntimeError(f"frame {frame}: pass {first}:{stop} is not its next")

    async def film(self, unit: int, pass_film, **time_rule) -> tuple | None:
        """Merge the film of ``unit`` (``time_rule``: node 0's ``ahead_seconds`` and
        ``traced_ahead`` of the pass, ``Progression.add_pass``); returns (frame, its film)
        when that frame is whole."""
        if unit != self.expected or unit >= len(self.units):
            raise NodeFailure(f"node 0 sent the film of unit {unit}; unit {self.expected} "
                              "was due")
        frame, first, stop = self.units[unit]
        progression = self.progression(frame)
        progression.add_pass(progression.passes.index((first, stop)), pass_film, **time_rule)
        step = progression.next_pass()
        if step is not None:
            following = unit + 1
        else:  # the frame is whole: its next units (if a rule stopped it) are skipped
            following = next((u for u in range(unit + 1, len(self.units))
                              if self.units[u][0] != frame), len(self.units))
            if following < len(self.units):
                self._start(self.units[following])
        self.expected = following
        if self.paced:
            if following < len(self.units):  # with what the time rule knows of it
                await self.send_grant(following,
                                      self.progression(self.units[following][0]).pass_clock())
            else:
                await self.send_grant(-1, (None, None))
        return None if step is not None else (frame, progression.film)


class Frames:
    """An animation's frames as they arrive: a frame is done when node 0's film and every
    node's report of it are in; then ``frame_done(frame, film, reports, seconds)``
    runs on a writer thread, frame after frame in order, while the event loop goes on (the
    heartbeats above all: writing a 4K frame's EXR and PNG takes seconds, and nodes that hear
    nothing for ``protocol.COORDINATOR_SILENCE_S`` exit). ``drain`` waits for the writes; a
    write that failed raises there, or at the next frame done.

    Without frames (one image) it does nothing: the film and the done reports are the result.
    """

    def __init__(self, size: int, frames: list[int] | None, frame_done):
        self.size, self.frame_done = size, frame_done
        self.expected = None if frames is None else list(frames)
        self.films: dict[int, object] = {}
        self.reports: dict[int, dict[int, dict]] = {}
        self.started = time.perf_counter()
        self.writer = None if frames is None else ThreadPoolExecutor(
            1, thread_name_prefix="frame-done")
        self.writing: list[asyncio.Future] = []

    def _raise_failed_write(self) -> None:
        for future in self.writing:
            if future.done() and future.exception() is not None:
                raise future.exception()
        self.writing = [f for f in self.writing if not f.done()]

    async def drain(self) -> None:
        """Wait for every frame handed to ``frame_done``; raise the first failure."""
        if self.writer is None:
            return
        try:
            for future in self.writing:
                await future
        finally:
            self.writing = []
            self.writer.shutdown(wait=True)

    def film(self, frame: int | None, film) -> None:
        if self.expected is None:
            return
        if frame not in self.expected or frame in self.films:
            raise NodeFailure(f"node 0 sent a film for frame {frame}, which it did not "
                              "have to render or had sent already")
        self.films[frame] = film
        self._finish(frame)

    def report(self, meta: dict) -> None:
        frame = int(meta["frame"])
        if self.expected is None or frame not in self.expected:
            raise NodeFailure(f"node {meta['rank']} reported frame {frame}, which is not "
                              "one of this job's")
        self.reports.setdefault(frame, {})[int(meta["rank"])] = meta
        self._finish(frame)

    def _finish(self, frame: int) -> None:
        if frame not in self.films or len(self.reports.get(frame, {})) < self.size:
            return
        self._raise_failed_write()
        now = time.perf_counter()
        reports = self.reports.pop(frame)
        self.writing.append(asyncio.get_running_loop().run_in_executor(
            self.writer, self.frame_done, frame, self.films.pop(frame),
            [reports[r] for r in range(self.size)], now - self.started))
        self.started = now

    def check_complete(self) -> None:
        if self.expected is not None and (self.films or self.reports):
            raise NodeFailure(f"the nodes finished with frames {sorted(self.reports)} "
                              "incomplete")


async def gather(router, watch: Watch, settings: RenderSettings, bar: tqdm,
                  frames: Frames, size: int, passes: Passes):
    """Receive the job's messages until the film and every node's report are in: progress,
    films of passes and frame reports (nothing per round: rounds and termination are the
    nodes', over the tree of ranks); a node's failure raises ``NodeLost``."""
    film, reports = None, {}
    done_paths: dict[int, int] = {}
    whole = passes.done  # nothing left to render (every pass merged before a node loss)
    if whole:
        film = passes.image_film()
    while not whole or len(reports) < size:
        _, message = await watch.receive(router)
        if message.kind == protocol.PROGRESS:
            rank = int(message.meta["rank"])
            paths = int(message.meta["paths"])
            bar.update(paths - done_paths.get(rank, 0))
            done_paths[rank] = paths
        elif message.kind == protocol.FILM:
            try:
                pass_film = film_from(message, settings.width, settings.height)
            except ValueError as exc:
                raise NodeFailure(f"node 0 sent a film that does not fit the image: "
                                  f"{exc}") from None
            finished = await passes.film(int(message.meta.get("unit", 0)), pass_film,
                                         **time_rule_of(message.meta))
            if finished is not None:  # a frame is whole (for an animation, the latest)
                (frame, film), whole = finished, True
                if frame is not None:
                    frames.film(frame, film)
        elif message.kind == protocol.FRAME:
            frames.report(message.meta)
        elif message.kind == protocol.DONE:
            reports[int(message.meta["rank"])] = message.meta
        elif message.kind == protocol.FAILED:
            raise watch.failed(int(message.meta["rank"]), message.meta["error"],
                               message.meta.get("input") is True)
    return film, reports


def time_rule_of(meta: dict) -> dict:
    """A film message's ``ahead_seconds`` and ``traced_ahead`` (node 0's, for the time rule:
    ``Progression.add_pass``), each read only where it is finite seconds (else none)."""
    def seconds(value) -> float | None:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return float(value) if ok and math.isfinite(value) and value >= 0 else None

    ahead = seconds(meta.get("ahead_seconds"))
    traced = meta.get("traced_ahead")
    traced = [seconds(t) for t in traced] if isinstance(traced, list) else []
    return {"ahead_seconds": ahead or 0.0,
            "traced_ahead": [] if None in traced else traced}


async def grant(router, identities: dict[int, bytes], token: bytes, next_unit: int,
                clock: tuple = (None, None)) -> None:
    """Tell every node the unit to render next (``-1``: none; paced runs only), with the time
    rule's ``clock`` of it (``Progression.pass_clock``: what a node traces ahead by)."""
    budget, per_sample = clock
    meta = {"next": next_unit, "budget_s": budget, "per_sample_s": per_sample}
    for rank in sorted(identities):
        await router.send_multipart([identities[rank], token,
                                     *encode(protocol.GRANT, {}, meta)])
