"""Try to reproduce session 4's heap corruption with 16-ray packets (issue 39, part 1).

Session 4 (bench/README.md, ``throughput.py``) saw ``malloc(): unaligned tcache chunk
detected`` within 12 renders when 16-ray occlusion packets through the in-core top-level scene
of instances ran from two threads at once, and 9dd359d dropped the packets on that record. The
experiment's code was never committed; this script rebuilds it on the commit it ran on and
renders under a CPU hog, or runs the committed packet path just before its removal:

* ``--code session4`` (default): commit 809b966 with serial twins of its 16-ray packet kernels
  (``rtcIntersect16``, ``rtcOccluded16``) run by the in-core render workers side by side without
  the launch lock, on raw scene handles (no leases: they came later), the top-level scene
  rebuilt by whichever worker sees the resident set change;
* ``--code packets``: 9dd359d^, the packet occlusion path as committed (with the leases).

Each render is its own ``vastray render`` process of that code (a git worktree and a virtual
environment over this one's packages, made under ``--work`` once) with ``--threads 2``
(three render workers), beside ``--hog`` busy processes, bounds-checked by numba unless
``--no-boundscheck``; each is compared bit for bit with the same code's ``--threads 1`` render.
Prints one line a render and ``native_crashes=N wrong_images=N runs=N``.

    python bench/old_crash.py --renders 20 --size 320x240x8 --resolution 256 --grid 2x2x2 \\
        --extra "--shadow-samples 16"
    python bench/old_crash.py --code packets --renders 20 --size 320x240x8 --resolution 256 \\
        --grid 2x2x2 --extra "--shadow-samples 16"
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from hogs import busy_processes
from numba_env import checked_env

from vastray.render.imageio import read_image

REPO = Path(__file__).resolve().parents[1]
COMMITS = {"session4": "809b966", "packets": "9dd359d^"}
#: What glibc, the kernel and CPython print when native code corrupts memory or crashes.
NATIVE = re.compile(r"Fatal Python error|Segmentation fault|double free|corrupted|"
                    r"malloc\(\)|free\(\): |munmap_chunk|core dumped")


def serial_twins(source: str) -> str:
    """809b966's ``scene/embree.py`` with serial twins of the packet kernels as the queries,
    launched without the lock (session 4's experiment as its note describes it)."""
    for name in ("_intersect16", "_occluded16"):
        start = source.index(f"@njit(parallel=True, nogil=True, cache=True)\ndef {name}(")
        end = source.index("\n\n\n", start)
        twin = (source[start:end]
                .replace("@njit(parallel=True, nogil=True, cache=True)",
                         "@njit(nogil=True, cache=True)")
                .replace(f"def {name}(", f"def {name}_serial(").replace("prange(", "range("))
        source = source[:end] + "\n\n\n" + twin + source[end:]
    source = source.replace('_QUERY = {"intersect": _intersect16, "occluded": _occluded16}',
                            '_QUERY = {"intersect": _intersect16_serial, '
                            '"occluded": _occluded16_serial}')
    locked = "    with _serial_lock:\n"
    assert source.count(locked) == 1
    return source.replace(locked, "    if kernel in (_intersect16_serial, _occluded16_serial):\n"
                                  "        kernel(*args)  # side by side, no lock\n"
                                  "        return\n" + locked)


def prepare(code: str, work: Path) -> Path:
    """The Python of a virtual environment running ``code`` (made once under ``work``)."""
    tree, venv = work / f"tree-{code}", work / f"venv-{code}"
    if not tree.exists():
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-f", str(tree),
                        COMMITS[code]], check=True, capture_output=True)
        if code == "session4":
            path = tree / "scene" / "embree.py"
            path.write_text(serial_twins(path.read_text()))
    python = venv / "bin" / "python"
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)],
                       check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", "-e",
                        str(tree)], check=True)
    return python


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", choices=sorted(COMMITS), default="session4")
    parser.add_argument("--work", type=Path, default=Path("/tmp/vastray-old-crash"))
    parser.add_argument("--renders", type=int, default=20)
    parser.add_argument("--hog", type=int, default=4, help="busy processes (default 4)")
    parser.add_argument("--size", default="64x48x4", help="WIDTHxHEIGHTxSPP")
    parser.add_argument("--resolution", type=int, default=96, help="rm store resolution")
    parser.add_argument("--grid", default="3x3x2", help="domain grid")
    parser.add_argument("--extra", default="", help="more render options")
    parser.add_argument("--no-boundscheck", action="store_true")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    python = prepare(args.code, args.work)
    run_dir = args.work / f"run-{args.code}-{args.resolution}-{args.grid}"
    run_dir.mkdir(exist_ok=True)
    env = checked_env(dict(os.environ, NUMBA_BOUNDSCHECK="0" if args.no_boundscheck else "1",
                           PYTHONFAULTHANDLER="1"))  # checked kernels: a fresh numba cache

    def cli(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(python), "-m", "vastray.cli", *argv], cwd=run_dir, env=env,
                              capture_output=True, text=True, timeout=900)

    store = run_dir / "s.store"
    if not store.exists():
        made = cli("generate", "rm", "-o", str(store), "--resolution", str(args.resolution),
                   "--grid", args.grid, "--quiet")
        if made.returncode:
            sys.exit(f"old_crash: generate failed: {made.stderr[-500:]}")
    width, height, spp = args.size.split("x")
    size = ["--width", width, "--height", height, "--spp", spp, "--integrator", "pt",
            *args.extra.split()]
    reference = run_dir / "reference.exr"
    made = cli("render", str(store), "-o", str(reference), *size, "--threads", "1", "--quiet")
    if made.returncode:
        sys.exit(f"old_crash: the reference render failed: {made.stderr[-500:]}")
    expected = read_image(reference)
    crashes = wrong = 0
    start = time.perf_counter()
    with busy_processes(args.hog):
        for i in range(args.renders):
            out = run_dir / f"render-{i}.exr"
            done = cli("render", str(store), "-o", str(out), *size, "--threads", "2", "--quiet")
            native = done.returncode < 0 or bool(NATIVE.search(done.stderr))
            bad = done.returncode == 0 and not np.array_equal(read_image(out), expected)
            crashes += native
            wrong += bad
            last = done.stderr.strip().splitlines()[-1][:160] if done.stderr.strip() else ""
            print(f"render {i}: exit {done.returncode} native_crash={native} wrong={bad} "
                  f"{last if native or done.returncode else ''}", flush=True)
            out.unlink(missing_ok=True)
    print(f"native_crashes={crashes} wrong_images={wrong} runs={args.renders} "
          f"(code {args.code} = {COMMITS[args.code]}, {time.perf_counter() - start:.0f} s)")
    return 1 if crashes or wrong else 0


if __name__ == "__main__":
    sys.exit(main())
