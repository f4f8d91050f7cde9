"""Where the operating system runs a busy process beside bound node processes: the measurements
behind ``sim.cores.SharedCores(bound_nodes=)`` (``IDLE_PULL_S``, ``BUSY_MOVE_S``).

1. A ping-pong: two processes pass a message back and forth with ``--work`` ms of CPU at each
   end, bound to one core each or unbound, quiet and beside one busy process: the round trip
   beyond the work (bound beside a busy process, each woken end shares its core with it).
2. Two processes working without a pause (fixed work, 3 s), bound or unbound, alone and
   beside one busy process: how much slower each is beside it (a fair third of the two
   cores would make them 1.5x slower).
3. Real 2-node renders of the validation's out-of-sample stores (``bench/simulate.py``) beside
   one busy process, its core sampled every 0.5 ms: how often it moves and how long it stays
   (over each render's whole span, the processes' start-up included), and the render's
   ``busy_max`` against the same render with no busy process (interleaved).

    python bench/hog_placement.py [--runs 2] [--work 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from multiprocessing import Pipe, Process
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hogs import SPINNER, busy_processes  # noqa: E402

#: The 2-node renders sampled: (scheduler, out-of-sample case of ``simulate.oos_cases``).
RENDERS = (("image", 0), ("async", 0), ("temporal", 0), ("domain", 0), ("spec-ooc", 1),
           ("spec-insitu", 1), ("dynamic", 1))


def spin(seconds: float) -> None:
    """Burn ``seconds`` of this thread's CPU."""
    start = time.thread_time()
    while time.thread_time() - start < seconds:
        pass


def _pong(conn, cpu: int | None, work: float) -> None:
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    while (message := conn.recv()) is not None:
        spin(work)
        conn.send(message)


def ping_pong(bound: bool, hogs: int, work: float, rounds: int = 300) -> float:
    """Median round trip beyond the far end's ``work`` (s), bound to CPUs 0 and 1 or not."""
    here, there = Pipe()
    before = os.sched_getaffinity(0)
    with busy_processes(hogs):
        far = Process(target=_pong, args=(there, 1 if bound else None, work))
        far.start()
        if bound:
            os.sched_setaffinity(0, {0})
        trips = []
        try:
            for i in range(rounds):
                start = time.perf_counter()
                here.send(i)
                here.recv()
                trips.append(time.perf_counter() - start)
                spin(work)
        finally:
            here.send(None)
            far.join()
            os.sched_setaffinity(0, before)
    return float(np.median(trips[20:])) - work


def _worker(cpu: int | None, seconds: float, out) -> None:
    """Fixed chunks of work for ``seconds``: sends the mean wall time of a chunk."""
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    walls, end = [], time.perf_counter() + seconds
    while time.perf_counter() < end:
        start = time.perf_counter()
        total = 0
        for i in range(200_000):
            total += i
        walls.append(time.perf_counter() - start)
    out.send(float(np.mean(walls)))


def side_by_side(bound: bool, hogs: int, seconds: float = 3.0) -> list[float]:
    """Two processes working without a pause: each one's mean wall time a chunk (s)."""
    with busy_processes(hogs):
        pipes = [Pipe() for _ in range(2)]
        workers = [Process(target=_worker, args=(i if bound else None, seconds, pipes[i][1]))
                   for i in range(2)]
        for worker in workers:
            worker.start()
        walls = [pipe[0].recv() for pipe in pipes]
        for worker in workers:
            worker.join()
    return walls


def core_of(pid: int) -> int:
    """The CPU ``pid`` last ran on (``/proc/PID/stat`` field 39)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[36])


def sampled_render(scheduler: str, case: int, hog: bool) -> dict:
    """One 2-node render (with a busy process beside it, its core sampled, where ``hog``)."""
    import simulate as bench

    from vastray.actors.coordinator import render_distributed

    _, store, settings, cache = bench.oos_cases(True)[case]
    options = replace(bench.scaling_options(scheduler, 2, settings.paths), threads=1,
                      cache=cache)
    if not hog:
        result = render_distributed(store.path, None, settings, 2, options=options, timeout=300)
        return {"busy": result.seconds["busy_max"]}
    spinner = subprocess.Popen([sys.executable, "-c", SPINNER])
    try:
        time.sleep(0.3)
        stop, samples = threading.Event(), []

        def sample():
            while not stop.is_set():
                samples.append((time.perf_counter(), core_of(spinner.pid)))
                time.sleep(0.0005)

        sampler = threading.Thread(target=sample)
        sampler.start()
        try:
            result = render_distributed(store.path, None, settings, 2, options=options,
                                        timeout=300)
        finally:
            stop.set()
            sampler.join()
    finally:
        spinner.kill()
        spinner.wait()
    times = np.array([t for t, _ in samples])
    cores = np.array([c for _, c in samples])
    moves = np.flatnonzero(np.diff(cores)) + 1
    stays = np.diff(times[np.concatenate([[0], moves, [len(cores) - 1]])])
    return {"busy": result.seconds["busy_max"], "span": times[-1] - times[0],
            "moves": len(moves), "stay": float(np.median(stays))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=2, help="renders of each kind (default 2)")
    parser.add_argument("--work", type=float, default=2.0,
                        help="ms of CPU at each end of the ping-pong (default 2)")
    args = parser.parse_args()
    if len(os.sched_getaffinity(0)) < 2:
        sys.exit("hog_placement.py needs at least 2 CPUs")
    work = args.work / 1e3
    print(f"ping-pong, {args.work:g} ms of work at each end: round trip beyond the work, ms")
    print("| placement | quiet | beside one busy process |")
    print("| --- | ---: | ---: |")
    for bound in (True, False):
        quiet, beside = ping_pong(bound, 0, work), ping_pong(bound, 1, work)
        print(f"| {'bound' if bound else 'unbound'} | {quiet * 1e3:.2f} | {beside * 1e3:.2f} |",
              flush=True)
    print()
    print("two processes working without a pause: how much slower beside one busy process")
    print("| placement | slower (each) | mean |")
    print("| --- | --- | ---: |")
    for bound in (True, False):
        alone, beside = side_by_side(bound, 0), side_by_side(bound, 1)
        slower = [b / a for a, b in zip(alone, beside, strict=True)]
        print(f"| {'bound' if bound else 'unbound'} | "
              f"{', '.join(f'{x:.2f}x' for x in slower)} | {np.mean(slower):.2f}x |", flush=True)
    print()
    print("2-node renders (nodes bound), a busy process beside them: its moves and stays "
          "over the render's whole span; busy_max against the same render alone")
    print("| scheduler | moves / s | median stay ms | busy_max alone s | beside s | slower |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for scheduler, case in RENDERS:
        alone, beside = [], []
        for _ in range(args.runs):
            alone.append(sampled_render(scheduler, case, False))
            beside.append(sampled_render(scheduler, case, True))
        rate = sum(r["moves"] for r in beside) / sum(r["span"] for r in beside)
        stay = float(np.median([r["stay"] for r in beside]))
        quiet = float(np.median([r["busy"] for r in alone]))
        busy = float(np.median([r["busy"] for r in beside]))
        print(f"| {scheduler} | {rate:.0f} | {stay * 1e3:.0f} | {quiet:.3f} | {busy:.3f} | "
              f"{busy / quiet:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
