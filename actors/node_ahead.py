"""A sort-first node's passes apart with later passes traced ahead (issue 40): the node
renders its share of a frame's passes in one call of the out-of-core runtime
(``SortFirstTiles.render_ahead``), and each pass, as it ends, is reduced over the nodes and
ruled on by the coordinator while the render thread waits for the grant of the next.

Passes apart swept the domains anew on every node for every pass: 1.7-2.5x one pass's
loads at a quarter cache (``vastray render --nodes N --reference``). Traced ahead, each
node's next passes ride on its current pass's loads, as in one process. Under a time limit
a node traces ahead only the passes the coordinator's time rule may still grant: each grant
brings the rule's clock of the pass granted (the seconds left when it was granted and the
last pass's seconds a sample), and the node predicts from it as the rule does
(``progressive.passes_in_time``), on its own clock from the grant's arrival."""

from __future__ import annotations

import time
from collections.abc import Callable
from types import SimpleNamespace

from vastray.actors.job_options import JobOptions
from vastray.render.progressive import passes_in_time
from vastray.schedule import registry
from vastray.schedule.registry import Runtime


def traces_ahead(job: dict, options: JobOptions, domains: int) -> bool:
    """Whether a node renders the job's passes with later ones traced ahead: passes apart (a
    rule may stop between them, or a reference wants each one's error) in a tile schedule
    out of core, unless the options say each pass alone (``trace_ahead``). A job from a
    coordinator that does not send the time rule's clock (``pass_clock``) has each pass
    swept alone: its time limit, if any, could not be predicted."""
    return ((job["paced"] or job.get("passes_apart", False))
            and "pass_clock" in job and options.trace_ahead
            and options.out_of_core(domains)
            and registry.spec(options.scheduler).runtime is Runtime.TILES)


class GrantedPasses:
    """A node's units of one frame as the progression ``SortFirstTiles.render_ahead`` asks
    for: pass k is unit ``units[k]``, merged by ``deliver(unit, film, time_rule)`` (called
    on the render thread: it reduces the film over the nodes, node 0 sends it with what the
    time rule predicts from, ``Progression.add_pass``'s ``ahead_seconds`` and
    ``traced_ahead``, and it returns the unit the coordinator grants next, -1 for none, and
    that unit's clock). The passes go on while the grant is this
    frame's next unit.

    Parameters
    ----------
    units : the job's units of this frame, from the first this node renders now, in order.
    windows : each unit's (first sample, stop sample).
    deliver : as above; blocks the render thread until the grant.
    clock : the time rule's (budget_s, per_sample_s) of ``units[0]``
        (``Progression.pass_clock``; budget None: no time limit).
    """

    def __init__(self, units: list[int], windows: list[tuple[int, int]],
                 deliver: Callable[[int, object, dict], tuple[int, tuple]],
                 clock: tuple = (None, None)):
        self.units, self.passes, self.deliver = list(units), list(windows), deliver
        self.rules = SimpleNamespace(paced=True, time_limit=None)
        self.reference = None
        self.film = None  # the coordinator's progression holds the image
        self.stopped_by: str | None = None
        #: the unit granted after the last one merged (None before the first), and its clock
        self.granted: int | None = None
        self.clock = tuple(clock)
        self._granted_at = time.perf_counter()
        self._next = 0

    def next_pass(self) -> tuple[int, int, int] | None:
        if self.stopped_by is not None:
            return None
        return (self._next, *self.passes[self._next])

    def may_grant(self, index: int, ahead_seconds: float = 0.0,
                  traced_ahead: list[float] = ()) -> bool:
        """Whether the coordinator's time rule may still grant pass ``index``, by the rule's
        own prediction from the current pass's clock (``Progression.may_grant``)."""
        if self.stopped_by is not None or index >= len(self.passes):
            return False
        if index <= self._next:
            return True
        budget, per_sample = self.clock
        spp = [stop - first for first, stop in self.passes[self._next:index + 1]]
        running = time.perf_counter() - self._granted_at
        return (passes_in_time(budget, running, per_sample, spp, ahead_seconds, traced_ahead)
                >= index - self._next)

    def add_pass(self, index: int, film, **time_rule) -> None:
        self.granted, self.clock = self.deliver(self.units[index], film, time_rule)
        self._granted_at = time.perf_counter()
        if index + 1 < len(self.units) and self.granted == self.units[index + 1]:
            self._next = index + 1
        else:  # the job's next unit is another frame's, or none
            self.stopped_by = "granted"
