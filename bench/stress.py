"""Renders under a CPU hog: any native crash, even one a node-loss recovery hides, and any image
that is not the reference's is a failure (issue 20).

Every render is a separate ``vastray render`` process, as a user runs it, on a small generated
store: single-process renders in core (1-3 threads, several render workers side by side), out of
core with caches that force evictions (``image``, ``spec-ooc``) and an in-core animation (every
domain closed and reloaded each frame), out of core and on nodes with Embree's fast BVH
(``--bvh fast``, against a reference built with it), then distributed renders on 2-3 nodes with
every scheduler (``async`` in three runs of five: it must be bit-identical run to run).
Meanwhile a hog of busy processes (4 per core by default) keeps the machine loaded, which
widens races.

Each run is compared, bit for bit, with the reference render (``--threads 1``, no hog): every
lossless schedule gives the same image. A run counts as a native crash when its process, or one
of its nodes, died of a signal (SIGSEGV, SIGABRT, ...), or its output names glibc's or Python's
fatal errors; a node that went silent under the load and was rendered around counts as a stall.

Usage::

    python bench/stress.py              # 50 single-process + 50 distributed renders (~15 min)
    python bench/stress.py --quick      # 8 + 8
    python bench/stress.py --local 10 --distributed 0 --hog 2

Prints one line per run, then ``native_crashes=N wrong_images=N stalls=N failures=N runs=N``;
exits 1 unless the first two are 0 and every run finished.
"""

from __future__ import annotations

import argparse
import itertools
import os
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hogs import cpu_hog
from numba_env import checked_env

from vastray.render.imageio import read_image

#: What glibc, the kernel and CPython print when native code corrupts memory or crashes.
NATIVE = re.compile(r"Fatal Python error|Segmentation fault|double free|corrupted|"
                    r"malloc\(\)|free\(\): |munmap_chunk|core dumped|died \(SIG|"
                    r"exited with code -\d+")
SIZE = ["--width", "64", "--height", "48", "--spp", "4"]
ORBIT = """[camera]
position = [1.6, -0.7, 1.2]
look_at = [0.5, 0.5, 0.45]
up = [0, 0, 1]
[camera.orbit]
degrees_per_frame = 10
axis = [0, 0, 1]
"""
FRAMES = 3

#: Single-process configurations, cycled: in core with 1-3 threads, out of core with caches
#: that evict, and an in-core animation.
LOCAL = [
    ["--threads", "2"],
    ["--threads", "3"],
    ["--threads", "1"],
    ["--cache", "2", "--scheduler", "image", "--threads", "2"],
    ["--cache", "25%", "--scheduler", "spec-ooc", "--threads", "2"],
    ["--cache", "3", "--scheduler", "spec-ooc", "--threads", "3"],
    ["--frames", str(FRAMES), "--threads", "2"],
    ["--cache", "3", "--scheduler", "spec-ooc", "--threads", "2", "--bvh", "fast"],
]
#: Distributed configurations: ``async`` (which must be bit-identical run to run) three runs in
#: five, in these variants, cycled ...
ASYNC = [
    ["--nodes", "2", "--scheduler", "async"],
    ["--nodes", "3", "--scheduler", "async", "--cache", "3"],
    ["--nodes", "2", "--scheduler", "async", "--threads", "2"],
    ["--nodes", "2", "--scheduler", "async", "--cache", "2"],
    ["--nodes", "3", "--scheduler", "async"],
    # one node: its small activations traced on the event loop's thread (INLINE_RAYS)
    ["--nodes", "1", "--scheduler", "async", "--cache", "3"],
]
#: ... and every other scheduler in the other runs, cycled.
OTHERS = [
    ["--nodes", "2", "--scheduler", "image", "--cache", "2"],
    ["--nodes", "2", "--scheduler", "spec-ooc", "--cache", "25%"],
    ["--nodes", "3", "--scheduler", "domain"],
    ["--nodes", "2", "--scheduler", "dynamic", "--cache", "4"],
    ["--nodes", "2", "--scheduler", "spec-insitu"],
    ["--nodes", "3", "--scheduler", "temporal", "--cache", "3"],
    ["--nodes", "2", "--scheduler", "image", "--cache", "2", "--bvh", "fast"],
    ["--nodes", "2", "--scheduler", "domain", "--cache", "3"],
]


def distributed_plan(n: int) -> list[list[str]]:
    """``n`` distributed runs: ``async`` at three positions in every five, the others between."""
    asyncs, others = itertools.cycle(ASYNC), itertools.cycle(OTHERS)
    return [next(asyncs) if k % 5 in (0, 1, 3) else next(others) for k in range(n)]


@dataclass
class Outcome:
    """One run: its options, exit code, seconds, and what it showed."""

    options: list[str]
    code: int
    seconds: float
    native: bool = False
    wrong: bool = False
    stalled: bool = False
    detail: str = ""

    @property
    def failed(self) -> bool:
        return self.code != 0 and not self.native


def vastray(*args: str, cwd: Path, timeout: float) -> subprocess.CompletedProcess:
    """``vastray ARGS`` in ``cwd``, as a user runs it (fault handler on, to name a crash)."""
    env = checked_env(dict(os.environ, PYTHONFAULTHANDLER="1"))  # a fresh cache if checked
    return subprocess.run([sys.executable, "-m", "vastray.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def frame_files(stem: str, options: list[str]) -> list[str]:
    """The image files a run writes: one, or one per frame of an animation."""
    if "--frames" in options:
        return [f"{stem}_{f:04d}.exr" for f in range(FRAMES)]
    return [f"{stem}.exr"]


def run_one(k: int, options: list[str], work: Path, timeout: float) -> Outcome:
    """Render with ``options`` and judge the run against the reference images."""
    stem = f"run{k}"
    scene = ["--scene", "orbit.toml"] if "--frames" in options else []
    start = time.perf_counter()
    try:
        proc = vastray("render", "s.store", "-o", f"{stem}.exr", *SIZE, *scene, *options,
                       cwd=work, timeout=timeout)
        code, text = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        code, text = 124, f"timed out after {timeout:.0f} s: {exc.stderr or ''}"
    outcome = Outcome(options, code, time.perf_counter() - start)
    outcome.native = code < 0 or code in (128 + 6, 128 + 11) or bool(NATIVE.search(text))
    outcome.stalled = "stalled" in text
    if code == 0:
        reference = ("ref_anim" if "--frames" in options
                     else "ref_fast" if "fast" in options else "ref")
        for got, expect in zip(frame_files(stem, options), frame_files(reference, options),
                               strict=True):
            diff = np.abs(read_image(work / got) - read_image(work / expect))
            if diff.max() > 0:
                outcome.wrong = True
                outcome.detail += (f"{got}: {np.count_nonzero(diff.max(axis=2))} pixels differ, "
                                   f"max {diff.max():.3g}; ")
            (work / got).unlink()
    if code != 0 or outcome.native or outcome.stalled:
        outcome.detail += " | ".join(line for line in text.strip().splitlines()[-6:])
    return outcome


def prepare(work: Path, timeout: float) -> None:
    """A small store (18 domains) and the reference images, rendered without the hog (one with
    Embree's fast BVH, ``--bvh fast``, for the runs that build it)."""
    (work / "orbit.toml").write_text(ORBIT)
    steps = [["generate", "rm", "-o", "s.store", "--resolution", "40", "--grid", "3x3x2",
              "--quiet"],
             ["render", "s.store", "-o", "ref.exr", *SIZE, "--threads", "1", "--quiet"],
             ["render", "s.store", "-o", "ref_anim.exr", *SIZE, "--threads", "1", "--scene",
              "orbit.toml", "--frames", str(FRAMES), "--quiet"],
             ["render", "s.store", "-o", "ref_fast.exr", *SIZE, "--threads", "1", "--bvh",
              "fast", "--quiet"]]
    for step in steps:
        proc = vastray(*step, cwd=work, timeout=timeout)
        if proc.returncode != 0:
            sys.exit(f"stress: set-up failed: vastray {' '.join(step)}\n{proc.stderr}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--local", type=int, default=50, help="single-process renders")
    parser.add_argument("--distributed", type=int, default=50, help="renders on 2-3 nodes")
    parser.add_argument("--hog", type=int, default=4, help="busy processes per core")
    parser.add_argument("--jobs", type=int, default=3, help="renders run at once")
    parser.add_argument("--timeout", type=float, default=300, help="seconds per render")
    parser.add_argument("--quick", action="store_true", help="8 + 8 renders")
    args = parser.parse_args(argv)
    if args.quick:
        args.local, args.distributed = min(args.local, 8), min(args.distributed, 8)
    plan = ([opts for opts, _ in zip(itertools.cycle(LOCAL), range(args.local))]
            + distributed_plan(args.distributed))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="vastray-stress-") as tmp:
        work = Path(tmp)
        prepare(work, args.timeout)
        outcomes: list[Outcome] = []
        with cpu_hog(args.hog) as hogs, ThreadPoolExecutor(args.jobs) as pool:
            print(f"stress: {len(plan)} renders, {args.jobs} at a time, under {hogs} busy "
                  f"processes", flush=True)
            futures = [pool.submit(run_one, k, opts, work, args.timeout)
                       for k, opts in enumerate(plan)]
            for k, future in enumerate(futures):
                o = future.result()
                outcomes.append(o)
                verdict = ("NATIVE CRASH" if o.native else "WRONG IMAGE" if o.wrong
                           else f"FAILED ({o.code})" if o.code else "stalled, recovered"
                           if o.stalled else "ok")
                print(f"[{k + 1}/{len(plan)}] {' '.join(o.options)}: {verdict} in "
                      f"{o.seconds:.1f} s{'  ' + o.detail if o.detail else ''}", flush=True)
    from vastray.scene.embree.library import binding as embree_binding

    binding = "compiled" if embree_binding() is not None else "embreex-fallback"
    crashes = sum(o.native for o in outcomes)
    wrong = sum(o.wrong for o in outcomes)
    stalls = sum(o.stalled and not o.native for o in outcomes)
    failures = sum(o.failed for o in outcomes)
    async_runs = sum("async" in o.options for o in outcomes)
    print(f"native_crashes={crashes} wrong_images={wrong} stalls={stalls} failures={failures} "
          f"runs={len(outcomes)} async_runs={async_runs} hog={args.hog}/core binding={binding} "
          f"seconds={time.perf_counter() - start:.0f}")
    return 0 if crashes == wrong == failures == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
