"""Run a blocking job on a thread of its own that the caller can interrupt.

``vastray.render`` uses it when its caller's thread already runs an asyncio event loop
(Jupyter, an async application), where the job's own ``asyncio.run`` (the distributed
coordinator's) cannot run; ``vastray.render_async`` uses it always. An interrupt of the caller
(Ctrl-C, a cancelled task) is passed on as a ``KeyboardInterrupt`` raised inside the job, which
unwinds through the job's cleanup (its node processes stopped) exactly as Ctrl-C does in a
plain script; the caller waits for that cleanup before it re-raises.
"""

from __future__ import annotations

import asyncio
import ctypes
import threading
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def _raise_in(thread_id: int, exc: type[BaseException] | None) -> None:
    """Raise ``exc`` in the thread at its next Python instruction (a native call, such as an
    Embree query, finishes first); None drops one not yet raised."""
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id),
                                               ctypes.py_object(exc) if exc else None)


class _Job(threading.Thread):
    def __init__(self, fn: Callable[[], T], on_done: Callable[[], None] | None = None):
        super().__init__(name="vastray-job", daemon=True)
        self._fn = fn
        self._on_done = on_done
        self.result = None
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._open = True  # interrupts go in while fn runs, and never after _close
        # Waited on instead of join(): in Python 3.11 a join() interrupted by Ctrl-C marks the
        # thread as stopped while it still runs (its cleanup would go unwaited for).
        self.finished = threading.Event()

    def run(self) -> None:
        try:
            self.result = self._fn()
        except BaseException as exc:  # handed to the caller's thread, re-raised there
            self.error = exc
        finally:
            self._close()

    def _close(self) -> None:
        while True:  # an interrupt sent as fn ended may land here: it is dropped
            try:
                with self._lock:
                    self._open = False
                    _raise_in(self.ident, None)
                break
            except KeyboardInterrupt as exc:
                self.error = self.error or exc
        self.finished.set()
        if self._on_done is not None:
            try:
                self._on_done()
            except RuntimeError:  # the caller's loop has closed: nobody is waiting
                pass

    def interrupt(self) -> None:
        """Raise ``KeyboardInterrupt`` in ``fn``, unless it has ended."""
        with self._lock:
            if self._open:
                _raise_in(self.ident, KeyboardInterrupt)

    def outcome(self) -> T:
        if self.error is not None:
            raise self.error
        return self.result


def run_in_thread(fn: Callable[[], T]) -> T:
    """``fn()`` on a new thread, waited for; an interrupt of the waiting caller
    (``KeyboardInterrupt``) interrupts ``fn`` too, and is re-raised once ``fn`` has unwound.

    Raises
    ------
    Whatever ``fn`` raises.
    """
    job = _Job(fn)
    job.start()
    try:
        while not job.finished.wait(0.1):
            pass
    except KeyboardInterrupt:
        job.interrupt()
        job.finished.wait()
        raise
    return job.outcome()


async def run_in_thread_async(fn: Callable[[], T]) -> T:
    """``fn()`` on a new thread, awaited without blocking the running loop; cancelling the
    awaiting task interrupts ``fn`` (``KeyboardInterrupt`` inside it), and the cancellation
    goes on once ``fn`` has unwound.

    Raises
    ------
    Whatever ``fn`` raises; ``asyncio.CancelledError`` when cancelled.
    """
    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    job = _Job(fn, on_done=lambda: loop.call_soon_threadsafe(done.set))
    job.start()
    try:
        await done.wait()
    except asyncio.CancelledError:
        job.interrupt()
        await asyncio.shield(done.wait())
        raise
    return job.outcome()
