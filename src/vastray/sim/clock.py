"""An asyncio event loop whose clock is virtual: when every task waits, time jumps to the next
timer instead of sleeping. Virtual nodes are then plain coroutines, and ``await
asyncio.sleep(cost)`` charges ``cost`` seconds of virtual time at no real cost."""

from __future__ import annotations

import asyncio
import selectors
from collections.abc import Coroutine


class Deadlock(RuntimeError):
    """Every virtual node waits and no timer or message is pending: the simulated schedule
    cannot finish."""


class _JumpingSelector(selectors.SelectSelector):
    """A selector that, asked to wait ``timeout`` seconds, advances the loop's virtual clock
    by that much and polls its real file descriptors (the loop's own wake-up pipe) without
    waiting."""

    def __init__(self):
        super().__init__()
        self.loop: VirtualClockLoop | None = None

    def select(self, timeout=None):
        if timeout is None:  # nothing is scheduled: no task can ever run again
            raise Deadlock("every virtual node waits for a message and none is in flight")
        if timeout > 0:
            self.loop.advance(timeout)
        return super().select(0)


class VirtualClockLoop(asyncio.SelectorEventLoop):
    """An event loop on virtual time (see the module docstring); starts at 0 s."""

    def __init__(self):
        selector = _JumpingSelector()
        super().__init__(selector)
        selector.loop = self
        self._virtual_now = 0.0

    def time(self) -> float:
        return self._virtual_now

    def advance(self, seconds: float) -> None:
        self._virtual_now += seconds


def run_virtual(main: Coroutine):
    """Run ``main`` to completion on a fresh virtual-clock loop; returns (its result, the
    virtual seconds it took). Must not be called from inside a running event loop."""
    loop = VirtualClockLoop()
    stopped = False  # Ctrl-C or SIGTERM (``KeyboardInterrupt``) mid-run
    try:
        result = loop.run_until_complete(main)
        return result, loop.time()
    except BaseException as exc:
        stopped = not isinstance(exc, Exception)
        raise
    finally:
        # A deadlock leaves tasks waiting: cancel them so none outlives its loop. After a
        # stop the loop is not run again: its timers would fire into futures the interrupt
        # left half-done (InvalidStateError, logged for each of thousands of virtual nodes).
        tasks = asyncio.all_tasks(loop)
        for task in tasks:
            task.cancel()
        if tasks and not stopped:
            loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
        loop.close()
