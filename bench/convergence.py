"""Convergence of every scheduler on one scene: time to an error, efficiency, and the lossy
mode's error split into bias and variance (issue 22).

One generated ``rm`` store, one converged reference (a single-process render at 16x the runs'
samples per pixel, with another seed so that its samples are not the runs' own), then every
run as a separate ``vastray render ... --reference ref.exr --report run.json`` process, as a
user runs it:

- single process: ``reference`` (in core) and ``spec-ooc --cache 50%`` (out of core);
- with ``--nodes 1, 2, 4``: ``image``, ``spec-ooc``, ``domain``, ``async``, ``dynamic``,
  ``spec-insitu`` and ``temporal`` (``--quick``: the decomposition schedulers on 2 nodes
  only, ``async`` on 1, 2 and 4);
- lossy: ``temporal --simplified portal`` on 2 nodes (after ``vastray simplify --ratio
  0.01``).

Every run renders the same image at the same spp and seed with the default threads (the
machine's cores shared out over the nodes), and stops at ``--spp``. From each report's
``passes``: seconds to relMSE <= 1e-2 and <= 1e-3 (log-log interpolation,
``vastray.convergence.time_to_error``), efficiency 1/(relMSE*t) at the last pass, final relMSE
and ``stopped_by``. A pass's time counts from the start of the first pass, as the report
does: starting the node processes and opening the store come before it and are not counted
(the table's ``process s`` is the whole command's wall time); loading domains (out of core) and
compiling kernels on a cold numba cache fall in the first pass.

The lossy run's error is split: variance = the film's own estimate (``estimated_rel_mse`` of
its last pass) and bias^2 = its relMSE against the converged reference minus that variance;
and, paired, bias^2 = its relMSE minus the relMSE of the lossless ``temporal`` run of the same
nodes and seed (the same paths wherever the model was not swapped). Both are estimates: the
reference has its own noise (1/16 of a run's variance, counted in every relMSE), and the film's
variance estimate is itself noisy, so a bias below the noise can come out negative. The same
split of the lossless ``temporal`` run (whose true bias is 0) is printed beside it as a control:
what "no bias" looks like at this spp.

Invariance: every lossless run's final image must equal the single-process ``reference``
run's bit for bit (``mismatches=0``).

Prints a Markdown table (a row per run), the bias/variance split and a summary line
``key=value ...``; writes every report, the table and ``vastray plot``'s relMSE-against-time
PNG to ``--out`` (default: a new temporary folder) and prints its path.

    python bench/convergence.py --quick   # 64x48, 64 spp, 12 runs: under a minute on 2 cores
    python bench/convergence.py           # 128x96, 128 spp, 24 runs: about 8 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vastray.convergence import efficiency, time_to_error
from vastray.render.imageio import read_image

THRESHOLDS = (1e-2, 1e-3)
DECOMPOSITION = ("image", "spec-ooc", "domain", "dynamic", "spec-insitu", "temporal")
REFERENCE_FACTOR = 16
REFERENCE_SEED = "7919"  # not the runs' seed 0: the reference must not share their samples


@dataclass
class Run:
    """One render of the plan: its scheduler, node count (None: single process) and the
    extra options."""

    scheduler: str
    nodes: int | None = None
    options: list[str] = field(default_factory=list)
    lossy: bool = False

    @property
    def name(self) -> str:
        nodes = f"n{self.nodes}" if self.nodes else "local"
        return f"{self.scheduler}-{nodes}{'-simplified' if self.lossy else ''}"

    def args(self) -> list[str]:
        nodes = ["--nodes", str(self.nodes)] if self.nodes else []
        return ["--scheduler", self.scheduler, *nodes, *self.options]


def plan(quick: bool) -> list[Run]:
    """The runs, the single-process ``reference`` first (the invariance's yardstick)."""
    runs = [Run("reference"), Run("spec-ooc", options=["--cache", "50%"])]
    for scheduler in DECOMPOSITION[:3] + ("async",) + DECOMPOSITION[3:]:
        counts = (1, 2, 4) if not quick or scheduler == "async" else (2,)
        runs += [Run(scheduler, n) for n in counts]
    runs.append(Run("temporal", 2, ["--simplified", "portal"], lossy=True))
    return runs


@dataclass
class Summary:
    """What the table shows of one run's report."""

    scheduler: str
    nodes: int | None
    spp: int
    to_threshold: list[float | None]
    efficiency: float
    final_rel_mse: float
    stopped_by: str
    first_pass_s: float
    lossy: bool = False
    process_s: float | None = None


def summarize(report: dict, lossy: bool = False) -> Summary:
    """The table's row for a single render's ``report`` (its ``passes`` against a
    reference; passes at 0 s or without an error are skipped)."""
    passes = [p for p in report["passes"]
              if p.get("rel_mse") is not None and (p.get("seconds") or 0) > 0]
    if not passes:
        raise ValueError("the report has no pass with a relMSE and a time: render it with "
                         "--reference")
    seconds = [p["seconds"] for p in passes]
    errors = [p["rel_mse"] for p in passes]
    last = passes[-1]
    return Summary(scheduler=report["scheduler"], nodes=(report.get("options") or {}).get("nodes"),
                   spp=last["spp"], to_threshold=[time_to_error(seconds, errors, h)
                                                  for h in THRESHOLDS],
                   efficiency=efficiency(last["seconds"], last["rel_mse"]),
                   final_rel_mse=last["rel_mse"], stopped_by=report.get("stopped_by", "?"),
                   first_pass_s=seconds[0], lossy=lossy)


def bias_variance(report: dict, lossless: dict | None = None) -> dict:
    """The final image's error split: ``variance`` (the film's own relMSE estimate at the
    last pass), ``bias2`` (relMSE against the converged reference minus that variance) and,
    given the ``lossless`` run of the same options and seed, ``bias2_paired`` (the relMSE
    minus the lossless run's). Each bias may come out negative when it is below the noise."""
    last = [p for p in report["passes"] if p.get("rel_mse") is not None][-1]
    variance = last.get("estimated_rel_mse")
    if variance is None:
        raise ValueError("the last pass has no estimated_rel_mse (a 1-spp render)")
    split = {"rel_mse": last["rel_mse"], "variance": variance,
             "bias2": last["rel_mse"] - variance}
    if lossless is not None:
        split["bias2_paired"] = last["rel_mse"] - lossless["passes"][-1]["rel_mse"]
    return split


def cell(value: float | None) -> str:
    return "—" if value is None else f"{value:.3g}"


HEADER = ("| scheduler | nodes | spp | s to ≤1e-2 | s to ≤1e-3 | 1/(relMSE·t) (1/s) | "
          "final relMSE | first pass s | process s | stopped by |\n"
          "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")


def markdown_table(rows: list[Summary]) -> str:
    """The rows as a Markdown table; the lossy run labelled as such."""
    lines = [HEADER]
    for r in rows:
        name = r.scheduler + (" --simplified portal (lossy)" if r.lossy else "")
        eff = "∞" if math.isinf(r.efficiency) else f"{r.efficiency:.3g}"
        lines.append(f"| {name} | {r.nodes if r.nodes else '1 (single process)'} | "
                     f"{r.spp} | {cell(r.to_threshold[0])} | {cell(r.to_threshold[1])} | "
                     f"{eff} | {r.final_rel_mse:.3g} | {r.first_pass_s:.2f} | "
                     f"{cell(r.process_s)} | {r.stopped_by} |")
    return "\n".join(lines)


def vastray(*args: str, cwd: Path, timeout: float) -> None:
    """``vastray ARGS`` in ``cwd``; exits naming the command when it fails."""
    proc = subprocess.run([sys.executable, "-m", "vastray", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        sys.exit(f"convergence: vastray {' '.join(args)} failed ({proc.returncode}):\n"
                 f"{proc.stderr.strip()[-2000:]}")
    return proc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="64x48, 64 spp, 12 runs (under a minute on an idle 2-core machine)")
    parser.add_argument("--out", type=Path,
                        help="folder for the reports, table and plot (default: a new "
                             "temporary folder)")
    parser.add_argument("--timeout", type=float, default=900, help="seconds per render")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    if args.quick:
        resolution, grid, width, height, spp = "48", "2x2x2", "64", "48", 64
    else:
        resolution, grid, width, height, spp = "96", "3x3x3", "128", "96", 128
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out}: is a file, not a folder")
    out = args.out or Path(tempfile.mkdtemp(prefix="vastray-convergence-"))
    out.mkdir(parents=True, exist_ok=True)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    runs = plan(args.quick)
    print(f"convergence: rm --resolution {resolution} --grid {grid}, {width}x{height}, "
          f"{spp} spp pt, seed 0; reference {REFERENCE_FACTOR * spp} spp (seed "
          f"{REFERENCE_SEED}); {len(runs)} runs on a {cores}-core machine (every node process "
          f"of a run shares those {cores} cores: 4 nodes get a half core each on 2 cores)",
          flush=True)
    size = ["--width", width, "--height", height, "--quiet"]
    with tempfile.TemporaryDirectory(prefix="vastray-convergence-work-") as tmp:
        work = Path(tmp)
        vastray("generate", "rm", "-o", "rm.store", "--resolution", resolution, "--grid", grid,
                "--quiet", cwd=work, timeout=args.timeout)
        vastray("simplify", "rm.store", "--ratio", "0.01", cwd=work, timeout=args.timeout)
        t0 = time.perf_counter()
        vastray("render", "rm.store", "-o", "ref.exr", *size, "--spp",
                str(REFERENCE_FACTOR * spp), "--seed", REFERENCE_SEED, "--scheduler",
                "reference", cwd=work, timeout=args.timeout)
        print(f"reference: {REFERENCE_FACTOR * spp} spp in {time.perf_counter() - t0:.1f} s",
              flush=True)
        reports, rows, mismatches = {}, [], []
        for run in runs:
            t0 = time.perf_counter()
            vastray("render", "rm.store", "-o", f"{run.name}.exr", *size, "--spp", str(spp),
                    *run.args(), "--reference", "ref.exr", "--report", f"{run.name}.json",
                    cwd=work, timeout=args.timeout)
            report = json.loads((work / f"{run.name}.json").read_text())
            reports[run.name] = report
            rows.append(summarize(report, run.lossy))
            rows[-1].process_s = time.perf_counter() - t0
            shutil.copy(work / f"{run.name}.json", out / f"{run.name}.json")
            if not run.lossy and run.name != runs[0].name:
                same = np.array_equal(read_image(work / f"{run.name}.exr"),
                                      read_image(work / f"{runs[0].name}.exr"))
                if not same:
                    mismatches.append(run.name)
            print(f"  {run.name}: {rows[-1].process_s:.1f} s, final relMSE "
                  f"{rows[-1].final_rel_mse:.3g}", flush=True)
    print(f"\nTime to error (seconds from the first pass's start, as the reports count; "
          f"process s: the whole command), {width}x{height} at {spp} spp:\n")
    table = markdown_table(rows)
    print(table)
    print("\nFairness: every run renders the same image at the same spp and seed with the "
          "same threads per machine (the default: its cores, shared out over the nodes); the "
          "lossy run is labelled as such and compared with the same converged reference.")
    lossy = next(r for r in runs if r.lossy)
    twin = reports.get(f"temporal-n{lossy.nodes}")
    split = bias_variance(reports[lossy.name], twin)
    control = bias_variance(twin)
    print(f"\nLossy {lossy.name}: relMSE {split['rel_mse']:.3g} = bias^2 {split['bias2']:.3g} "
          f"+ variance {split['variance']:.3g} (the film's own estimate); paired with the "
          f"lossless temporal run of the same seed: bias^2 {split['bias2_paired']:.3g}. "
          f"Caveat: the reference has its own noise (about 1/{REFERENCE_FACTOR} of a run's "
          f"variance, {split['variance'] / REFERENCE_FACTOR:.2g} here) inside every relMSE, "
          "and the film's estimate is noisy too, so a bias below the noise can come out "
          "negative.")
    print(f"Control, lossless temporal-n{lossy.nodes} (true bias 0): relMSE "
          f"{control['rel_mse']:.3g} = bias^2 {control['bias2']:.3g} + variance "
          f"{control['variance']:.3g}: a bias^2 of this size is noise.")
    (out / "table.md").write_text(table + "\n")
    plot = subprocess.run([sys.executable, "-m", "vastray", "plot",
                           *[str(out / f"{r.name}.json") for r in runs], "-o",
                           str(out / "convergence.png"), "--title",
                           f"rm {width}x{height}, {spp} spp, {cores} cores"],
                          capture_output=True, text=True, timeout=args.timeout)
    if plot.returncode != 0:
        print(f"plot failed: {plot.stderr.strip()}")
    lossless = [r for r in rows if not r.lossy]
    best = max(lossless, key=lambda r: r.efficiency)
    print(f"\nplot: {out / 'convergence.png'}\nreports: {out}")
    print(f"runs={len(rows)} mismatches={len(mismatches)} spp={spp} "
          f"best_efficiency={best.scheduler}@{best.nodes or 1}:{best.efficiency:.3g} "
          f"lossy_rel_mse={split['rel_mse']:.3g} lossy_bias2={split['bias2']:.3g} "
          f"lossy_bias2_paired={split['bias2_paired']:.3g} "
          f"lossy_variance={split['variance']:.3g} control_bias2={control['bias2']:.3g} "
          f"cores={cores} "
          f"seconds={time.perf_counter() - start:.0f}"
          + (f" mismatched={','.join(mismatches)}" if mismatches else ""))
    return 0 if not mismatches else 1


if __name__ == "__main__":
    sys.exit(main())
