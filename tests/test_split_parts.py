"""The split pool's pieces: their CPU counted for the thread that split the work, and no piece
left running when another fails."""

from __future__ import annotations

import threading
import time

import pytest

from vastray.scene.embree.launch import cpu_time, run_in_parts


def _spin(seconds: float) -> None:
    """Use ``seconds`` of this thread's CPU (CPU, not wall time: it holds on a busy machine)."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_cpu_time_counts_the_pieces_run_on_other_threads():
    own, total = time.thread_time(), cpu_time()
    run_in_parts(lambda lo, hi: _spin(0.05 * (hi - lo)), 4, 2)
    own, total = time.thread_time() - own, cpu_time() - total
    assert own < 0.05  # the caller only waited
    assert total >= 0.2 - 0.01  # four pairs' worth of spinning, on the two pieces


def test_cpu_time_counts_nested_pieces_and_is_per_thread():
    def outer(lo, hi):
        run_in_parts(lambda a, b: _spin(0.03), 2, 2)

    other = []
    watcher = threading.Thread(target=lambda: other.append(cpu_time()))
    start = cpu_time()
    run_in_parts(outer, 2, 2)
    spent = cpu_time() - start
    watcher.start()
    watcher.join()
    assert spent >= 4 * 0.03 - 0.01  # two pieces, each splitting in two
    assert other[0] < 0.05  # another thread's clock has none of it


def test_a_failing_piece_is_raised_only_after_every_piece_returned():
    # a piece that started before the failure runs to its end before the error is raised; none
    # starts after it (the threads take pieces in turn and stop at the first failure)
    started, finished = [], []

    def part(lo, hi):
        if lo == 0:
            raise ValueError("piece 0 failed")
        started.append(lo)
        time.sleep(0.2)
        finished.append(lo)

    with pytest.raises(ValueError, match="piece 0 failed"):
        run_in_parts(part, 2, 2)
    assert finished == started and set(started) <= {1}
    started.clear()
    finished.clear()
    with pytest.raises(ValueError, match="piece 0 failed"):
        run_in_parts(part, 64, 2)  # 8 pieces of 8 rows: at most the one in flight ran
    assert finished == started and len(started) <= 1
