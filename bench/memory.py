"""The preflight's memory estimate against the measured peak RSS of real renders (issue 23).

Each case is a ``vastray render`` run as a separate process (``python -c`` calling
``vastray.cli.main``, which also prints the process's own peak, ``VmHWM``, when it exits) on a
generated ``rm`` store (``vastray generate rm --resolution 64 --grid 2x2x2``, and one at 160^3
for the domains' share) or the built-in scene. The estimate is the one ``vastray render``
itself checks: ``plan_render(...).memory`` for the same arguments, computed in this process.

Rows compare one process each: a single-process render (estimate ``process``, measured: the
process's peak), each ``--nodes`` node (``process`` against the largest ``peak_rss_bytes`` the
nodes report) and the coordinator (``coordinator`` against the render process's own peak). It
prints a markdown table ``case | role | estimate | measured peak RSS | ratio`` and a last line
``cases=N min_ratio=... max_ratio=...``; the model is calibrated to keep every ratio within
0.8-1.5 (``--check`` exits 1 otherwise).

The limit sweep (issue 37) renders spec-ooc on a fine store (``rm --resolution 256 --grid
8x8x4``, 136 domains; ``--quick``: at 128) at 256x256 x 4 spp with ``--cold-reads`` under
several ``--memory-limit`` values: 700M, the smallest the preflight accepts (the one its
refusal of 64M names), 1G and 2G. Each is refused up front or its peak RSS stays under it: a
table ``store | limit | cache | measured peak RSS | peak / limit`` and a last line
``limit_cases=N accepted=M max_peak_over_limit=...`` (``--check`` exits 1 if one exceeds).

    python bench/memory.py            # both sweeps (a few minutes on 2 cores)
    python bench/memory.py --quick    # the estimate's quick cases, about a minute
    python bench/memory.py --limits --quick   # the limit sweep on the smaller fine store
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

#: Estimate / measured peak RSS the model must stay within.
RATIO_RANGE = (0.8, 1.5)

#: The render process: the CLI's main, then its own peak RSS on stderr as it exits.
#: (``VmHWM``, not ``ru_maxrss``, which on Linux keeps the peak of the bench process it was
#: started from: a CI run measured every case 55-80 MB high that way.)
WRAPPER = ("import atexit, sys\n"
           "from vastray.processes import peak_rss_bytes\n"
           "atexit.register(lambda: print('PEAK_RSS_KB', peak_rss_bytes() // 1024, "
           "file=sys.stderr))\n"
           "from vastray.cli import main\n"
           "sys.exit(main(sys.argv[1:]))\n")

RM = ["{rm}"]
RM160 = ["{rm160}"]
DEFAULT = []  # the built-in scene


def size(n: int) -> list[str]:
    return ["--width", str(n), "--height", str(n)]


def cases(quick: bool) -> list[tuple[str, list[str]]]:
    """(label, render arguments) of the sweep; ``--quick`` keeps one of each kind."""
    quick_cases = [
        ("rm 64² 1 spp t1 (base)", RM + size(64) + ["--spp", "1", "--threads", "1"]),
        ("rm 256² 4 spp t1", RM + size(256) + ["--spp", "4", "--threads", "1"]),
        ("rm 256² 16 spp t2", RM + size(256) + ["--spp", "16", "--threads", "2"]),
        ("rm 1024² 1 spp t1", RM + size(1024) + ["--spp", "1", "--threads", "1"]),
        ("rm 256² 4 spp spec-ooc", RM + size(256) + ["--spp", "4", "--threads", "1",
                                                     "--scheduler", "spec-ooc"]),
        ("rm 256² 4 spp --nodes 2", RM + size(256) + ["--spp", "4", "--nodes", "2"]),
        ("default 256² 4 spp ss16", DEFAULT + size(256) + ["--spp", "4",
                                                           "--shadow-samples", "16"]),
    ]
    if quick:
        return quick_cases
    full = [
        ("rm 128² 1 spp t1", RM + size(128) + ["--spp", "1", "--threads", "1"]),
        ("rm 512² 1 spp t1", RM + size(512) + ["--spp", "1", "--threads", "1"]),
        ("rm 2048² 1 spp t1", RM + size(2048) + ["--spp", "1", "--threads", "1"]),
        ("rm 256² 1 spp t1", RM + size(256) + ["--spp", "1", "--threads", "1"]),
        ("rm 256² 16 spp t1", RM + size(256) + ["--spp", "16", "--threads", "1"]),
        ("rm 256² 1 spp t2", RM + size(256) + ["--spp", "1", "--threads", "2"]),
        ("rm 256² 4 spp t2", RM + size(256) + ["--spp", "4", "--threads", "2"]),
        ("rm 512² 4 spp t2", RM + size(512) + ["--spp", "4", "--threads", "2"]),
        ("rm 256² 4 spp ss1 spec-ooc", RM + size(256) + ["--spp", "4", "--threads", "1",
                                                         "--scheduler", "spec-ooc",
                                                         "--shadow-samples", "1"]),
        ("rm 256² 4 spp ao spec-ooc", RM + size(256) + ["--spp", "4", "--threads", "1",
                                                        "--scheduler", "spec-ooc",
                                                        "--integrator", "ao"]),
        ("rm 256² 4 spp --cache 2", RM + size(256) + ["--spp", "4", "--threads", "1",
                                                      "--cache", "2"]),
        ("rm160 64² 1 spp t1 (domains)", RM160 + size(64) + ["--spp", "1", "--threads", "1"]),
        ("rm 1024² 1 spp --nodes 2", RM + size(1024) + ["--spp", "1", "--nodes", "2"]),
        ("rm 256² 4 spp --nodes 2 async", RM + size(256) + ["--spp", "4", "--nodes", "2",
                                                            "--scheduler", "async"]),
        ("rm 1024² 1 spp --reference", RM + size(1024) + ["--spp", "1", "--threads", "1",
                                                          "--reference", "{ref1024}"]),
        ("default 512² 8 spp", DEFAULT + size(512) + ["--spp", "8"]),
    ]
    return quick_cases + full


#: The limit sweep's render (``{fine}``: the fine store) and its limits ("smallest": the one
#: the preflight names when it refuses ``PROBE_LIMIT``).
LIMIT_RENDER = ["{fine}", "--width", "256", "--height", "256", "--spp", "4",
                "--scheduler", "spec-ooc", "--cold-reads"]
LIMITS = ["700M", "smallest", "1G", "2G"]
PROBE_LIMIT = "64M"


@dataclass
class LimitRow:
    """One render of the limit sweep: its limit (bytes), the cache it got and its measured
    peak, or the preflight's refusal."""

    limit: int
    peak: int | None = None
    cache: int | None = None
    refusal: str | None = None

    @property
    def ratio(self) -> float | None:
        return None if self.peak is None else self.peak / self.limit


def smallest_limit(refusal: str) -> str | None:
    """The ``--memory-limit`` a refusal names as the smallest that fits (``"906M"``)."""
    found = re.search(r"smallest that fits is --memory-limit (\d+M)", refusal)
    return found.group(1) if found else None


def limit_sweep(store: str, workdir: Path, limits: list[str]) -> list[LimitRow]:
    """Render ``LIMIT_RENDER`` on ``store`` under each of ``limits``: refused up front
    (``plan_render``'s InputError, the line the CLI prints) or run, its peak measured."""
    from vastray.preflight import parse_size
    from vastray.scene.errors import InputError

    argv = [a.format(fine=store) for a in LIMIT_RENDER] + ["-o", str(workdir / "out.exr")]
    rows = []
    for limit in limits:
        if limit == "smallest":
            try:
                estimate([*argv, "--memory-limit", PROBE_LIMIT])
            except InputError as refused:
                limit = smallest_limit(str(refused))
            if limit is None:
                raise SystemExit(f"--memory-limit {PROBE_LIMIT} was not refused naming a limit")
        limited = [*argv, "--memory-limit", limit]
        try:
            estimate(limited)
        except InputError as refused:
            rows.append(LimitRow(parse_size(limit), refusal=str(refused)))
            continue
        peak, report = measure(limited, workdir)
        rows.append(LimitRow(parse_size(limit), peak, report["counters"]["cache_capacity"]))
        print(f"  --memory-limit {limit}: done", file=sys.stderr, flush=True)
    return rows


def limit_table(name: str, rows: list[LimitRow]) -> str:
    lines = ["| store | limit | cache | measured peak RSS | peak / limit |",
             "|---|---:|---:|---:|---:|"]
    for r in rows:
        if r.peak is None:
            smallest = smallest_limit(r.refusal or "")
            said = f"refused (smallest: {smallest})" if smallest else "refused"
            lines.append(f"| {name} | {r.limit / 2**20:.0f} MiB | - | {said} | - |")
        else:
            lines.append(f"| {name} | {r.limit / 2**20:.0f} MiB | {r.cache} | "
                         f"{r.peak / 1e6:.0f} MB | {r.ratio:.2f} |")
    return "\n".join(lines)


@dataclass
class Row:
    case: str
    role: str
    estimate: int
    measured: int

    @property
    def ratio(self) -> float:
        return self.estimate / self.measured


def estimate(argv: list[str]):
    """``plan_render``'s ``RenderMemory`` for ``vastray render ARGV`` (what the CLI checks)."""
    from vastray.cli import build_parser
    from vastray.planning import plan_render
    from vastray.request import RenderRequest

    args = build_parser().parse_args(["render", *argv])
    return plan_render(RenderRequest.from_namespace(args)).memory


def measure(argv: list[str], workdir: Path) -> tuple[int, dict]:
    """Run ``vastray render ARGV --report`` as a process: its own peak RSS and its report."""
    report = workdir / "report.json"
    out = subprocess.run([sys.executable, "-c", WRAPPER, "render", *argv, "--quiet",
                          "--report", str(report)], capture_output=True, text=True,
                         timeout=600)
    if out.returncode != 0:
        raise SystemExit(f"vastray render {' '.join(argv)} failed: {out.stderr.strip()}")
    peaks = [int(line.split()[1]) * 1024 for line in out.stderr.splitlines()
             if line.startswith("PEAK_RSS_KB")]
    return peaks[-1], json.loads(report.read_text())


def run_case(label: str, argv: list[str], workdir: Path) -> list[Row]:
    argv = [*argv, "-o", str(workdir / "out.exr")]
    memory = estimate(argv)
    peak, report = measure(argv, workdir)
    nodes = report["counters"].get("per_node")
    if not nodes:
        return [Row(label, "process", memory.process.total, peak)]
    node_peak = max(n["counters"]["peak_rss_bytes"] for n in nodes)
    return [Row(label, "node", memory.process.total, node_peak),
            Row(label, "coordinator", memory.coordinator.total, peak)]


def prepare_fine(workdir: Path, quick: bool) -> str:
    """The limit sweep's fine store: ``rm`` on an 8x8x4 grid (136 domains at 256^3)."""
    path = workdir / "fine.store"
    subprocess.run([sys.executable, "-m", "vastray.cli", "generate", "rm", "-o", str(path),
                    "--resolution", "128" if quick else "256", "--grid", "8x8x4", "--quiet"],
                   check=True, capture_output=True, cwd=workdir)
    return str(path)


def prepare(workdir: Path, quick: bool) -> dict[str, str]:
    """The stores (and the reference image) the cases name."""
    def vastray(*args):
        subprocess.run([sys.executable, "-m", "vastray.cli", *args], check=True,
                       capture_output=True, cwd=workdir)

    places = {"rm": str(workdir / "rm.store"), "rm160": str(workdir / "rm160.store"),
              "ref1024": str(workdir / "ref1024.exr")}
    vastray("generate", "rm", "-o", places["rm"], "--resolution", "64", "--grid", "2x2x2")
    if not quick:
        vastray("generate", "rm", "-o", places["rm160"], "--resolution", "160", "--grid",
                "2x2x2")
        vastray("render", places["rm"], "-o", places["ref1024"], *size(1024), "--spp", "1",
                "--quiet")
    return places


def table(rows: list[Row]) -> str:
    lines = ["| case | role | estimate | measured peak RSS | ratio |",
             "|---|---|---:|---:|---:|"]
    lines += [f"| {r.case} | {r.role} | {r.estimate / 1e6:.0f} MB | {r.measured / 1e6:.0f} MB "
              f"| {r.ratio:.2f} |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="the estimate's quick cases; with --limits, the smaller fine store")
    parser.add_argument("--limits", action="store_true",
                        help="only the limit sweep: spec-ooc on a fine store under several "
                             "--memory-limit values")
    parser.add_argument("--check", action="store_true",
                        help=f"exit 1 if a ratio falls outside {RATIO_RANGE} or a peak "
                             "exceeds its limit")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    rows: list[Row] = []
    limit_rows: list[LimitRow] = []
    with tempfile.TemporaryDirectory(prefix="vastray-memory-") as tmp:
        workdir = Path(tmp)
        if not args.limits:
            places = prepare(workdir, args.quick)
            for label, case in cases(args.quick):
                rows += run_case(label, [a.format(**places) for a in case], workdir)
                print(f"  {label}: done", file=sys.stderr, flush=True)
        if args.limits or not args.quick:
            fine = prepare_fine(workdir, args.limits and args.quick)
            limit_rows = limit_sweep(fine, workdir, LIMITS)
    inside = True
    if rows:
        print(table(rows))
        ratios = [r.ratio for r in rows]
        print(f"cases={len(rows)} min_ratio={min(ratios):.2f} max_ratio={max(ratios):.2f} "
              f"seconds={time.perf_counter() - start:.0f}")
        inside = all(RATIO_RANGE[0] <= r <= RATIO_RANGE[1] for r in ratios)
    if limit_rows:
        name = "rm 128³ 8x8x4" if args.limits and args.quick else "rm 256³ 8x8x4"
        print(limit_table(name, limit_rows))
        accepted = [r.ratio for r in limit_rows if r.ratio is not None]
        print(f"limit_cases={len(limit_rows)} accepted={len(accepted)} "
              f"max_peak_over_limit={max(accepted, default=0):.2f} "
              f"seconds={time.perf_counter() - start:.0f}")
        inside = inside and all(r <= 1 for r in accepted)
    return 0 if inside or not args.check else 1


if __name__ == "__main__":
    sys.exit(main())
