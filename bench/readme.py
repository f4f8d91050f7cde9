"""Every code block of the README run as written, top to bottom, in one fresh folder.

A user copies the README's blocks into a shell; this does the same: each ```` ```bash ````
block is one ``bash -euo pipefail`` script, run in order in a fresh folder (later blocks use
what earlier ones made), with the ``vastray`` on ``PATH``, without internet. An HTML comment
right above a block says what the run changes, and nothing else is changed:

``<!-- readme-test`` ... ``-->``, one directive a line:

- ``skip: WHY`` -- the block is not run (the install-and-test block, which CI runs verbatim);
- ``shrink: OLD => NEW`` -- only with ``--small``: a smaller scene (the README says which);
- ``here: OLD => NEW`` -- always: what differs on this machine (``/shared/`` is a local
  folder, ``HEAD`` is loopback);
- ``not-here: REGEX => WHY`` -- lines that need what a test machine lacks (SSH hosts, Slurm,
  MPI, docker) are left out, each printed with its reason;
- ``mirror: OLD => NEW`` -- where the sample meshes can be copied from a local mirror
  (``$SAMPLES_MIRROR``, ``--mirror``), the fetch line uses it; without one, the lines that
  match ``needs-samples: REGEX`` are left out.

Background jobs a block starts (``&``) are waited for, and any that failed fails the block.
A run counts as a native crash when a process died of a signal or printed glibc's or Python's
fatal errors (as in ``bench/stress.py``).

Usage::

    python bench/readme.py --small               # once, shrunk as the README says (CI, a slow test)
    python bench/readme.py --repeat 10 --hog 4   # ten full runs under 4 busy processes per core
    python bench/readme.py --small --block 2     # only the second block (and what it needs)

Prints one line per block and run, then
``readme_blocks=N runs=R failures=F native_crashes=C hog=H seconds=S``; exits 1 on any failure.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hogs import cpu_hog  # noqa: E402
from stress import NATIVE  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MIRROR = ROOT.parent / "shared" / "data" / "meshes"
#: Waits for every background job of a block; a failed one fails the block.
WAIT_ALL = '\nfor job in $(jobs -p); do wait "$job" || { echo "background job failed"; exit 1; }; done\n'


@dataclass
class Block:
    """One ```` ```bash ```` block and the directives of the comment above it."""

    line: int  # 1-based line of the opening fence
    text: str
    directives: dict[str, list[str]] = field(default_factory=dict)

    def get(self, key: str) -> list[str]:
        return self.directives.get(key, [])

    @staticmethod
    def pairs(values: list[str]) -> list[tuple[str, str]]:
        out = []
        for value in values:
            old, sep, new = value.partition(" => ")
            if not sep:
                raise ValueError(f"README directive {value!r} needs 'OLD => NEW'")
            out.append((old.strip(), new.strip()))
        return out


def parse_blocks(readme: str) -> list[Block]:
    """The README's bash blocks, each with the ``readme-test`` directives just above it."""
    lines = readme.splitlines()
    blocks, k = [], 0
    while k < len(lines):
        if lines[k].strip() != "```bash":
            k += 1
            continue
        start = k
        k += 1
        body = []
        while k < len(lines) and lines[k].strip() != "```":
            body.append(lines[k])
            k += 1
        directives: dict[str, list[str]] = {}
        above = start - 1
        while above >= 0 and not lines[above].strip():
            above -= 1
        if above >= 0 and lines[above].strip() == "-->":
            top = above
            while top >= 0 and not lines[top].startswith("<!-- readme-test"):
                top -= 1
            for entry in lines[top + 1:above]:
                key, _, value = entry.strip().partition(":")
                directives.setdefault(key.strip(), []).append(value.strip())
        blocks.append(Block(start + 1, "\n".join(body) + "\n", directives))
        k += 1
    return blocks


def script_for(block: Block, small: bool, mirror: Path | None) -> tuple[str, list[str]]:
    """The block as it runs here, and the lines left out (each with its reason)."""
    text = block.text.replace("\\\n", " ")  # one line per command
    substitutions = Block.pairs(block.get("here"))
    if small:
        substitutions += Block.pairs(block.get("shrink"))
    if mirror is not None:
        substitutions += [(old, new.replace("$SAMPLES_MIRROR", str(mirror)))
                          for old, new in Block.pairs(block.get("mirror"))]
    for old, new in substitutions:
        if old not in text:
            raise ValueError(f"README block at line {block.line}: {old!r} is not in the block")
        text = text.replace(old, new)
    left_out = [(re.compile(p), why) for p, why in Block.pairs(block.get("not-here"))]
    if mirror is None:
        left_out += [(re.compile(p), "needs the sample meshes: no internet here and no mirror")
                     for p in block.get("needs-samples")]
    kept, skipped = [], []
    for line in text.splitlines():
        reason = next((why for pattern, why in left_out if pattern.search(line)), None)
        if reason and not line.lstrip().startswith("#"):
            skipped.append(f"{line.strip()}  [{reason}]")
        else:
            kept.append(line)
    return "\n".join(kept) + WAIT_ALL, skipped


@dataclass
class Result:
    block: Block
    code: int
    seconds: float
    native: bool
    tail: str


def run_block(block: Block, work: Path, small: bool, mirror: Path | None,
              timeout: float) -> tuple[Result, list[str]]:
    script, skipped = script_for(block, small, mirror)
    env = dict(os.environ, PYTHONFAULTHANDLER="1")
    start = time.perf_counter()
    # Its own process group, so that a block over time goes with everything it started.
    proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", script], cwd=work, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        text, _ = proc.communicate(timeout=timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        code, text = 124, f"timed out after {timeout:.0f} s\n{out}"
    native = code < 0 or code in (128 + 6, 128 + 11) or bool(NATIVE.search(text))
    tail = "\n".join(text.strip().splitlines()[-12:])
    return Result(block, code, time.perf_counter() - start, native, tail), skipped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--readme", type=Path, default=ROOT / "README.md")
    parser.add_argument("--small", action="store_true",
                        help="apply the README's shrink directives (a smaller scene)")
    parser.add_argument("--repeat", type=int, default=1, help="runs of every block")
    parser.add_argument("--hog", type=int, default=0, help="busy processes per core meanwhile")
    parser.add_argument("--block", type=int, action="append",
                        help="run only these blocks (1-based, in README order), and every "
                             "earlier runnable block they build on")
    parser.add_argument("--mirror", type=Path,
                        default=Path(os.environ.get("SAMPLES_MIRROR", DEFAULT_MIRROR)),
                        help="folder holding the sample meshes (default: %(default)s)")
    parser.add_argument("--timeout", type=float, default=None,
                        help="seconds per block (default: 900 with --small, else 3600)")
    parser.add_argument("--keep", action="store_true", help="keep the work folders")
    args = parser.parse_args(argv)
    timeout = args.timeout or (900.0 if args.small else 3600.0)
    mirror = args.mirror if args.mirror.is_dir() else None
    blocks = parse_blocks(args.readme.read_text())
    chosen = [b for b in blocks if not b.get("skip")]
    if args.block:
        last = max(args.block)
        chosen = [b for b in chosen if blocks.index(b) + 1 <= last]
    print(f"readme: {len(chosen)} of {len(blocks)} blocks, {args.repeat} run(s)"
          f"{', shrunk' if args.small else ''}, mirror {mirror or 'none'}", flush=True)
    for b in blocks:
        if b.get("skip"):
            print(f"  block at line {b.line}: not run ({b.get('skip')[0]})")
    failures = crashes = runs = 0
    start = time.perf_counter()
    with cpu_hog(args.hog) if args.hog else contextlib.nullcontext(0) as hogs:
        if args.hog:
            print(f"under {hogs} busy processes", flush=True)
        for rep in range(args.repeat):
            work = Path(tempfile.mkdtemp(prefix="vastray-readme-"))
            try:
                for block in chosen:
                    result, skipped = run_block(block, work, args.small, mirror, timeout)
                    runs += 1
                    for line in skipped if rep == 0 else []:
                        print(f"  left out: {line}")
                    state = "ok" if result.code == 0 else f"FAILED (exit {result.code})"
                    if result.native:
                        state += " NATIVE CRASH"
                    print(f"run {rep + 1} block at line {result.block.line}: {state} in "
                          f"{result.seconds:.1f} s", flush=True)
                    if result.code != 0 or result.native:
                        failures += result.code != 0
                        crashes += result.native
                        print("    " + result.tail.replace("\n", "\n    "), flush=True)
                        break  # later blocks build on this one
            finally:
                if args.keep:
                    print(f"  kept {work}")
                else:
                    shutil.rmtree(work, ignore_errors=True)
    print(f"readme_blocks={len(chosen)} runs={runs} failures={failures} native_crashes={crashes} "
          f"hog={args.hog}/core seconds={time.perf_counter() - start:.0f}")
    return 0 if failures == 0 and crashes == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
