"""Running a query kernel on a batch of rays: its inputs checked, split over threads.

A query of several threads splits its rays into contiguous pieces, which threads of one
process-wide pool take in turn and trace with the serial kernel (``launch``); render workers
that trace on one thread each run their kernels side by side. No kernel is
``parallel=True``: numba's threading layer, whose default (workqueue) is not safe to enter
from two Python threads at once, is never used (issue 20: heap corruption under load was
reported only with two threads in compiled code; with no kernel sharing native state, that
class is ruled out).
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor, wait

import numpy as np


def rays(origins, directions, t_far) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' inputs: C-contiguous, writable float32 (n, 3), (n, 3), (n,), checked (the
    kernels do not check bounds)."""
    org, dirs, tf = (_writable(np.ascontiguousarray(a, dtype=np.float32))
                     for a in (origins, directions, t_far))
    n = len(org)
    if org.shape != (n, 3) or dirs.shape != (n, 3) or tf.shape != (n,):
        raise ValueError(f"rays must be (n, 3), (n, 3), (n,): got {org.shape}, {dirs.shape}, "
                         f"{tf.shape}")
    return org, dirs, tf


def _writable(a: np.ndarray) -> np.ndarray:
    # One kernel signature only (numba types read-only arrays apart: another compilation).
    return a if a.flags.writeable else a.copy()


#: Fewest rays per part when a query is split over several threads.
_SPLIT_MIN = 4096
#: Threads of the split pool at most (a thread is started only when a part finds none idle,
#: so a process that splits into two parts has two).
_SPLIT_THREADS = max(64, os.cpu_count() or 1)
_splitter: ThreadPoolExecutor | None = None
_splitter_lock = threading.Lock()


def split_pool() -> ThreadPoolExecutor:
    """The process's pool that runs the parts of split queries: made once and never shut
    down. (It used to be replaced by a larger one on demand, and the old one shut down, which
    could race another thread's submit to it: "cannot schedule new futures after
    shutdown".)"""
    global _splitter
    with _splitter_lock:
        if _splitter is None:
            _splitter = ThreadPoolExecutor(_SPLIT_THREADS, thread_name_prefix="embree-part")
        return _splitter


def launch(kernel, threads: int, n: int, *args) -> None:
    """Run the serial ``kernel`` on ``n`` rays on at most ``threads`` threads of
    ``split_pool``, each taking contiguous pieces of the rays in turn (``run_in_parts``; one
    thread: on the calling thread).

    Every kernel (``kernels``) is serial and releases the GIL: numba's threading layer (whose
    default, workqueue, must not be entered by two Python threads at once) is never used, so any
    number of Python threads may query at the same time. Each piece writes only its own rows of the
    outputs (array arguments are sliced along their first axis; the others, such as the scene
    handle, are passed whole); the caller holds every array until all pieces have returned.
    """
    parts = max(1, min(int(threads), n // _SPLIT_MIN))
    if parts == 1:
        kernel(*args)
        return
    run_in_parts(lambda lo, hi: kernel(*(a[lo:hi] if isinstance(a, np.ndarray) else a
                                         for a in args)), n, parts)


def run_in_parts(part, n: int, parts: int) -> None:
    """Run ``part(lo, hi)`` over ``0..n`` on ``parts`` threads of ``split_pool`` (one part: on
    the calling thread), and wait for all of them. The rows are cut into contiguous pieces,
    ``_PIECES_PER_PART`` a thread, which the threads take in turn as each finishes its last:
    rays of unequal cost (an image's empty half against its object) keep every thread busy
    to the end, where one piece per thread left one thread idle (camera rays of a scan whose
    object fills a corner: 2 threads 1.4x one instead of 1.9x). Each piece must write only its
    own rows, so the result does not depend on ``parts`` nor on which thread took a piece. The
    pieces' CPU time is added to the calling thread's ``cpu_time``.

    Raises
    ------
    Exception
        The first piece's error, once every thread has returned (a piece still running must
        not outlive the arrays its caller frees on the error); no piece starts after it.
    """
    if parts <= 1:
        part(0, n)
        return
    size = max(1, -(-n // (parts * _PIECES_PER_PART)))
    pieces = iter(range(0, n, size))
    take = threading.Lock()
    failed = threading.Event()

    def worker() -> float:
        start = cpu_time()
        try:
            while not failed.is_set():
                with take:
                    lo = next(pieces, None)
                if lo is None:
                    break
                part(lo, min(lo + size, n))
        except BaseException:
            failed.set()
            raise
        return cpu_time() - start

    pool = split_pool()
    futures = [pool.submit(worker) for _ in range(min(parts, -(-n // size)))]
    wait(futures)
    spent = sum(f.result() for f in futures if f.exception() is None)
    _helped.cpu_s = getattr(_helped, "cpu_s", 0.0) + spent
    for future in futures:
        future.result()


#: Pieces a thread takes on average in ``run_in_parts`` (the last ones balance the threads;
#: the callers split only work of thousands of rows, ``launch`` at least ``_SPLIT_MIN`` a
#: thread, so a piece's hand-over, microseconds, stays small beside it).
_PIECES_PER_PART = 4


_helped = threading.local()  # per thread: CPU seconds its pieces took on split_pool


def cpu_time() -> float:
    """CPU seconds of the calling thread, counting the pieces of its queries that ran on
    ``split_pool`` threads (``run_in_parts``): what a query or a scheduling decision cost
    whichever threads ran it. ``time.thread_time`` alone missed those pieces: the simulator,
    which charges a virtual node the CPU its real code takes, charged spec-insitu's
    occupancy tests and every split query as nothing."""
    return time.thread_time() + getattr(_helped, "cpu_s", 0.0)
