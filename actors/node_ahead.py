"""A sort-first node's passes apart with later passes traced ahead (issue 40): the node
renders its share of a frame's passes in one call of the out-of-core runtime
(``SortFirstTiles.render_ahead``), and each pass, as it ends, is reduced over the nodes and
ruled on by the coordinator while the render thread waits for the grant of the next.

Passes apart swept the domains anew on every node for every pass: 1.7-2.5x one pass's
loads at a quarter cache (``vastray render --nodes N --reference``). Traced ahead, each
node's next passes ride on its current pass's loads, as in one process."""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

from vastray.actors.job_options import JobOptions
from vastray.schedule import registry
from vastray.schedule.registry import Runtime


def traces_ahead(job: dict, options: JobOptions, domains: int) -> bool:
    """Whether a node renders the job's passes with later ones traced ahead: passes apart (a
    rule may stop between them, or a reference wants each one's error) in a tile schedule
    out of core, and no time limit (whose rule predicts a pass's time from the last one's
    time per sample, which passes traced ahead would not give). A job from a coordinator
    that does not say whether it is time-limited is taken as one."""
    return ((job["paced"] or job.get("passes_apart", False))
            and not job.get("time_limited", True)
            and options.out_of_core(domains)
            and registry.spec(options.scheduler).runtime is Runtime.TILES)


class GrantedPasses:
    """A node's units of one frame as the progression ``SortFirstTiles.render_ahead`` asks
    for: pass k is unit ``units[k]``, merged by ``deliver(unit, film)`` (called on the render
    thread: it reduces the film over the nodes and returns the unit the coordinator grants
    next, -1 for none). The passes go on while the grant is this frame's next unit.

    Parameters
    ----------
    units : the job's units of this frame, from the first this node renders now, in order.
    windows : each unit's (first sample, stop sample).
    deliver : as above; blocks the render thread until the grant.
    """

    def __init__(self, units: list[int], windows: list[tuple[int, int]],
                 deliver: Callable[[int, object], int]):
        self.units, self.passes, self.deliver = list(units), list(windows), deliver
        self.rules = SimpleNamespace(paced=True, time_limit=None)
        self.reference = None
        self.film = None  # the coordinator's progression holds the image
        self.stopped_by: str | None = None
        #: the unit granted after the last one merged (None before the first)
        self.granted: int | None = None
        self._next = 0

    def next_pass(self) -> tuple[int, int, int] | None:
        if self.stopped_by is not None:
            return None
        return (self._next, *self.passes[self._next])

    def add_pass(self, index: int, film) -> None:
        self.granted = self.deliver(self.units[index], film)
        if index + 1 < len(self.units) and self.granted == self.units[index + 1]:
            self._next = index + 1
        else:  # the job's next unit is another frame's, or none
            self.stopped_by = "granted"
