"""What a fresh node pays to touch its memory for the first time.

A node process is fresh for every job. The arrays its render thread fills (paths, ray
batches, queues, the film) come from memory the process has never touched, and the first
touch of each 4 KiB page is a minor page fault: the kernel maps and zeroes the page. Real
nodes took 10,000-30,000 such faults a node in a 0.2-0.5 s busy span on the turbine-blade
scan and on rm 64³, 2.6-3.6 us each on this virtual machine: 30-80 ms a node. The simulator
runs every virtual node's code in one long-lived process, whose heap was touched long before
(0-100 faults a simulation), so its measured CPU leaves that cost out; the calibration's
few-pixel set-up renders (``node_cost``) see only its fixed part.

Two constants charge it (``CostModel.first_touch_s``):

- ``page_fault_s``: CPU seconds of one fault, measured by touching a fresh anonymous mapping
  page by page (``page_fault_seconds``);
- ``fresh_pages_per_path``: pages a fresh process's render thread first touches per path in
  flight, the slope between two fresh processes rendering the calibration store at two sizes
  (``python -m vastray.sim.first_touch STORE``: the ``image`` schedule on one thread, as a
  sort-first node renders; ``fresh_pages``). The builds' pages are left out: they fall on
  the loading threads, and a load's timing (``sim.cache.Domains``) already includes them.

The slope is the calibration store's. It moves little with the store: 0.29 pages a path on
rm 64³, 0.25 on the turbine-blade scan and 0.29 on rm 128³ in 8x4x4 domains (this machine,
session 72, ``--quick``'s sizes: 6,144 and 24,576 paths).
"""

from __future__ import annotations

import json
import mmap
import resource
import subprocess
import sys
import time

import numpy as np

from vastray.scene.errors import InputError

#: Bytes of one page (the unit of a first touch).
PAGE_BYTES = mmap.PAGESIZE
#: Seconds one measuring process may take (Python's start, the node's warm-up, one render).
PROCESS_TIMEOUT_S = 300.0


def thread_faults() -> int:
    """Minor page faults of the calling thread so far."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt


def page_fault_seconds(megabytes: int = 32, rounds: int = 3) -> float:
    """CPU seconds of one minor page fault here: a fresh anonymous mapping of ``megabytes``
    touched once a page, its CPU time over its faults, the median of ``rounds``."""
    seconds = []
    for _ in range(rounds):
        mapping = mmap.mmap(-1, megabytes << 20)
        try:
            pages = np.frombuffer(mapping, np.uint8)
            faults, cpu = thread_faults(), time.thread_time()
            pages[::PAGE_BYTES] = 1
            cpu, faults = time.thread_time() - cpu, thread_faults() - faults
            del pages
        finally:
            mapping.close()
        if faults > 0:
            seconds.append(cpu / faults)
    return float(np.median(seconds)) if seconds else 0.0


def fresh_pages(store_path: str, quick: bool, tile: bool) -> tuple[int, int]:
    """(paths, pages): a fresh process's render of the calibration store (``--tile``: the
    calibration tile, else the measuring processes' render, ``calibrate.node_settings``) and
    the pages its render thread first touched.

    Raises
    ------
    InputError
        The measuring process failed or did not answer in ``PROCESS_TIMEOUT_S`` (its error).
    """
    command = [sys.executable, "-m", "vastray.sim.first_touch", str(store_path)] + (
        ["--quick"] if quick else []) + (["--tile"] if tile else [])
    try:
        done = subprocess.run(command, capture_output=True, text=True,
                              timeout=PROCESS_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise InputError(store_path, f"the first-touch measurement did not finish in "
                                     f"{PROCESS_TIMEOUT_S:.0f} s") from None
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        why = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        why = why.split("Error: ", 1)[-1]  # an exception's text, not its class
        why = why.removeprefix("vastray.sim.first_touch: ").removeprefix(f"{store_path}: ")
        raise InputError(store_path, f"the first-touch measurement failed: {why}")
    answer = json.loads(lines[-1])
    return int(answer["paths"]), int(answer["pages"])


def pages_per_path(samples: list[tuple[int, int]]) -> float:
    """Pages a path in flight adds (>= 0): the least-squares slope of pages over paths of
    ``samples`` ((paths, pages), at two sizes or more); 0 with a single size."""
    paths = np.array([p for p, _ in samples], np.float64)
    pages = np.array([n for _, n in samples], np.float64)
    if len(samples) < 2 or np.ptp(paths) == 0:
        return 0.0
    slope = np.polyfit(paths, pages, 1)[0]
    return max(0.0, float(slope))


def measure(store_path: str, quick: bool) -> tuple[float, float]:
    """(page_fault_s, fresh_pages_per_path) of this machine and the calibration store: a
    fresh process at each of the two sizes, twice over unless ``quick`` (the slope moved by
    2 % between two such pairs on rm 64³, about 2.5 s a process here)."""
    samples = [fresh_pages(store_path, quick, tile) for _ in range(1 if quick else 2)
               for tile in (True, False)]
    return page_fault_seconds(), pages_per_path(samples)


def main(argv: list[str]) -> int:
    from vastray.actors.job_options import JobOptions
    from vastray.actors.local import render_out_of_core
    from vastray.actors.node_warm_up import warm_node
    from vastray.render.scene_config import SceneConfig
    from vastray.sim.warmup import measuring_render

    store, settings = measuring_render("python -m vastray.sim.first_touch", argv,
                                       "render the calibration tile (else twice its width "
                                       "and height)")
    warm_node()  # as a node does before its first hello
    before = thread_faults()
    # one thread, as a node's: its traces run on this thread, its loads on the preloader's
    render_out_of_core(store, SceneConfig(text=""), settings,
                       JobOptions(scheduler="image", threads=1), progress=False)
    print(json.dumps({"paths": settings.paths, "pages": thread_faults() - before}), flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except InputError as exc:
        sys.exit(f"vastray.sim.first_touch: {exc}")
