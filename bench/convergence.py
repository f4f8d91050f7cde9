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

Every error here is the per-pixel relMSE ``rel_mse`` = mean over pixels and channels of
``(x - r)**2 / (r**2 + ε)``, ε = 0.01 (``imageio.REL_MSE_EPSILON``); the film's
``estimated_rel_mse`` estimates that same quantity (per channel, same ε), so the two subtract.
The lossy run's error is split: variance = the film's own estimate (``estimated_rel_mse`` of
its last pass), the reference's variance = the reference render's own ``estimated_rel_mse``
(its noise, 1/16 of a run's, is inside every relMSE against it) and bias^2 = its relMSE
against the converged reference minus both; and, paired, bias^2 = its relMSE minus the relMSE
of the lossless ``temporal`` run of the same nodes and seed (the same paths wherever the model
was not swapped; the reference's noise cancels). Both are estimates: the film's variance
estimate is itself noisy, so a bias below the noise can come out negative. The same split of
the lossless ``temporal`` run (whose true bias is 0) is printed beside it as a control: what
"no bias" looks like at this spp.

Invariance: every lossless run's final image must equal the single-process ``reference``
run's bit for bit (``mismatches=0``).

Calibration of the error estimates without a reference (issue 41; ``calibrate``): on seven
scenes (``calibration_scenes``: generated ``rm`` (PT and AO) and ``cosmo`` (PT, on ``--nodes
2``, ``async``) at ``--resolution 32`` (full: 64), the built-in scene (PT), the heavy-tailed
hidden lamp (``bench_scenes.hidden_lamp_scene``: a point light in a cup under the ceiling,
every visible pixel lit through a bounce off a small bright spot; PT; the full run adds it on
2 nodes), and two real scans from ``../shared/data/meshes`` partitioned with ``vastray
partition``: the bunny (PT, one process) and the turbine blade (a CT isosurface; AO on 2
nodes), skipped with a printed reason when absent; the full run adds the built-in scene with
AO), 48x36 (full: 64x48), each against a reference of 16x64 spp with seed 7919 in one process.
Per scene, 6 seeds (full: 10) render ``--spp 64 --max-pass-spp 8 --reference ref.exr``
(passes at 1, 2, 4, 8, 16, 24, ..., 64 spp) and the same seeds ``--target-error E`` without a
reference. Every error is the per-pixel relMSE the reports call ``rel_mse``: the mean over
pixels and channels of ``(x - r)**2 / (r**2 + ε)``, ε = 0.01; the film's
``estimated_rel_mse`` estimates the same (per channel, same ε). True relMSE = the relMSE
against the reference minus the reference's own estimated relMSE (its variance, about 1/16 of
a run's at equal spp). Printed: ``ci_coverage`` (share of the passes at >= 4 spp whose true
relMSE lies inside ``estimated_rel_mse_ci95``), ``target_met_share`` (share of the target runs
whose true relMSE at the stop, from their image, is <= E; E per scene = the median true relMSE
at 16 spp over the seeds) and ``spp_over_oracle`` (median and max over the target runs of the
stop's spp over the oracle's: the first pass of the same seed's run whose true relMSE is <=
E), with a row per scene, and as a diagnostic the same at the stop for the grey
(channel-mean) image, the metric the film estimated before it kept its batches per channel.
``--only TEXT`` calibrates the scenes whose "name integrator" holds TEXT.

Prints a Markdown table (a row per run), the bias/variance split and a summary line
``key=value ...``; writes every report, the table and ``vastray plot``'s relMSE-against-time
PNG to ``--out`` (default: a new temporary folder) and prints its path.

    python bench/convergence.py --quick   # 64x48, 64 spp, 12 runs, then 7 scenes x 6 seeds x 2
                                          # calibration runs at 48x36: 5 minutes on 2 cores
                                          # (2026-11-29, load average 3.4-5.5 meanwhile)
    python bench/convergence.py           # 128x96, 128 spp, 24 runs: about 8 minutes on 2 cores,
                                          # then 9 scenes x 10 seeds x 2 at 64x48 (not yet timed)
    python bench/convergence.py --part calibration   # the calibration alone
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
from vastray.render.imageio import REL_MSE_EPSILON, read_image, relative_mse

THRESHOLDS = (1e-2, 1e-3)
DECOMPOSITION = ("image", "spec-ooc", "domain", "dynamic", "spec-insitu", "temporal")
REFERENCE_FACTOR = 16
REFERENCE_SEED = "7919"  # not the runs' seed 0: the reference must not share their samples
MESHES = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "meshes"


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


def bias_variance(report: dict, lossless: dict | None = None,
                  reference_noise: float = 0.0) -> dict:
    """The final image's error split, every term a per-pixel relMSE over pixels and channels
    (``(x - r)**2 / (r**2 + ε)``, ε = ``REL_MSE_EPSILON``): ``variance`` (the film's own
    estimate at the last pass, ``estimated_rel_mse``: the same metric, with the film's
    independent halves' product estimating r**2 in the denominator), ``reference_variance``
    (``reference_noise``: the converged reference's own estimated relMSE, which every relMSE
    against it contains) and ``bias2`` = relMSE against the reference - variance - the
    reference's variance; given the ``lossless`` run of the same options and seed,
    ``bias2_paired`` (the relMSE minus the lossless run's: the same reference noise in
    both). Each bias may come out negative when it is below the noise."""
    last = [p for p in report["passes"] if p.get("rel_mse") is not None][-1]
    variance = last.get("estimated_rel_mse")
    if variance is None:
        raise ValueError("the last pass has no estimated_rel_mse (a 1-spp render)")
    split = {"rel_mse": last["rel_mse"], "variance": variance,
             "reference_variance": reference_noise,
             "bias2": last["rel_mse"] - variance - reference_noise}
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


# --- Calibration of the error estimates without a reference (issue 41 part 5) -------------

CAL_SPP = 64  # each run's cap; the reference has REFERENCE_FACTOR x as many samples
CAL_MAX_PASS_SPP = 8  # passes 1, 2, 4, 8, 16, 24, ..., 64: the stop can fall every 8 spp
COVERAGE_MIN_SPP = 4  # the CI's coverage counts the passes at this spp or more
TARGET_AT_SPP = 16  # E per scene: the median true relMSE of the seeds' passes at this spp
CAL_SEED_BASE = 100  # the runs' seeds: 100, 101, ... (never the reference's 7919)


@dataclass
class CalScene:
    """One calibration scene: a store (None: the built-in scene), its integrator, the node
    count (None: one process) and the extra render options."""

    name: str
    store: Path | None
    integrator: str
    nodes: int | None = None
    options: list[str] = field(default_factory=list)

    def args(self, width: int, height: int) -> list[str]:
        store = [str(self.store)] if self.store is not None else []
        nodes = ["--nodes", str(self.nodes), "--scheduler", "async"] if self.nodes else []
        return [*store, "--integrator", self.integrator, "--width", str(width),
                "--height", str(height), *nodes, *self.options]


def true_rel_mse(rel_mse: float, reference_noise: float) -> float:
    """The relMSE against the true image: the relMSE against a noisy reference counts the
    reference's own variance too (E (x - y)**2 = (x - r)**2 + var y), so its estimated relMSE
    is subtracted."""
    return rel_mse - reference_noise


def reference_noise(report: dict) -> float:
    """The reference's own relMSE: its film's estimate at its last pass (at 16x the runs'
    spp, so about 1/16 of a run's variance at equal spp)."""
    last = [p for p in report["passes"] if p.get("estimated_rel_mse") is not None][-1]
    return float(last["estimated_rel_mse"])


def coverage(reports: list[dict], noise: float, min_spp: int = COVERAGE_MIN_SPP) -> dict:
    """Over the passes at ``min_spp`` spp or more of ``reports`` (rendered with
    ``--reference``): how many have their true relMSE inside ``estimated_rel_mse_ci95``
    (``inside``), below it (``below``: the estimate pessimistic) or above it (``above``:
    optimistic), of ``passes``."""
    counts = {"passes": 0, "inside": 0, "below": 0, "above": 0}
    for report in reports:
        for p in report["passes"]:
            ci = p.get("estimated_rel_mse_ci95")
            if p.get("spp", 0) < min_spp or ci is None or p.get("rel_mse") is None:
                continue
            true = true_rel_mse(p["rel_mse"], noise)
            counts["passes"] += 1
            key = "below" if true < ci[0] else "above" if true > ci[1] else "inside"
            counts[key] += 1
    return counts


def grey_rel_mse(image: np.ndarray, reference: np.ndarray) -> float:
    """The per-pixel relMSE of the grey (channel-mean) image, ε as ``rel_mse``: the metric
    the film's batches estimate (``rel_mse`` is over the three channels)."""
    x, r = image.astype(np.float64).mean(axis=-1), reference.astype(np.float64).mean(axis=-1)
    return float(np.mean((x - r) ** 2 / (r ** 2 + REL_MSE_EPSILON)))


def inside(value: float, ci: list[float] | None) -> bool:
    return ci is not None and ci[0] <= value <= ci[1]


def true_series(report: dict, noise: float) -> list[tuple[int, float]]:
    """(spp, true relMSE) of every pass of ``report`` with a relMSE."""
    return [(p["spp"], true_rel_mse(p["rel_mse"], noise)) for p in report["passes"]
            if p.get("rel_mse") is not None and p.get("spp", 0) > 0]


def choose_target(reports: list[dict], noise: float, at_spp: int = TARGET_AT_SPP) -> float:
    """The scene's target E: the median over ``reports`` of the true relMSE at ``at_spp``
    (so the oracle stops there or one pass later, and the rule's stop falls at a moderate
    spp)."""
    values = [e for r in reports for spp, e in true_series(r, noise) if spp == at_spp]
    if not values:
        raise ValueError(f"no pass at {at_spp} spp")
    return float(np.median(values))


def oracle_spp(report: dict, noise: float, target: float) -> int | None:
    """The oracle's minimum spp: the first pass of ``report`` (same seed, with
    ``--reference``) whose true relMSE is <= ``target`` (None: none)."""
    return next((spp for spp, e in true_series(report, noise) if e <= target), None)


@dataclass
class TargetRun:
    """One ``--target-error`` run without a reference: where it stopped, its true error
    there and the oracle's minimum spp for the same seed."""

    seed: int
    stop_spp: int
    stopped_by: str
    stop_bound: float | None
    true_error: float
    target: float
    oracle: int | None
    grey_error: float | None = None  # the grey image's true relMSE at the stop
    ci95: list[float] | None = None  # the stop pass's estimated_rel_mse_ci95

    @property
    def met(self) -> bool:
        return self.true_error <= self.target

    @property
    def over_oracle(self) -> float | None:
        return None if self.oracle is None else self.stop_spp / self.oracle


def calibration_figures(cov: list[dict], runs: list[TargetRun]) -> dict:
    """The three figures over every scene: ``ci_coverage`` (share of passes with the true
    relMSE inside the 95 % CI), ``target_met_share`` (share of target runs whose true relMSE
    at the stop is <= E), ``spp_over_oracle`` median and max (runs whose oracle exists)."""
    passes = sum(c["passes"] for c in cov)
    ratios = [r.over_oracle for r in runs if r.over_oracle is not None]
    grey = [r for r in runs if r.grey_error is not None]
    return {"target_met_share_grey": (sum(r.grey_error <= r.target for r in grey) / len(grey)
                                      if grey else None),
            "ci_coverage_grey_at_stop": (sum(inside(r.grey_error, r.ci95) for r in grey)
                                         / len(grey) if grey else None),
            "ci_coverage": sum(c["inside"] for c in cov) / passes if passes else None,
            "passes": passes, "runs": len(runs),
            "target_met_share": sum(r.met for r in runs) / len(runs) if runs else None,
            "spp_over_oracle": float(np.median(ratios)) if ratios else None,
            "spp_over_oracle_max": max(ratios) if ratios else None}


CAL_HEADER = ("| scene | integrator | nodes | passes ≥{m} spp | in CI | below / above | coverage | "
              "ref noise | E | runs | met | stop spp | oracle spp | spp/oracle median (max) |\n"
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|")


def calibration_table(rows: list[tuple[CalScene, dict, float, float, list[TargetRun]]]) -> str:
    """A row per scene: (scene, coverage counts, reference noise, E, target runs)."""
    lines = [CAL_HEADER.format(m=COVERAGE_MIN_SPP)]
    for scene, cov, noise, target, runs in rows:
        ratios = [r.over_oracle for r in runs if r.over_oracle is not None]
        ratio = (f"{np.median(ratios):.2f} ({max(ratios):.2f})" if ratios else "—")
        lines.append(
            f"| {scene.name} | {scene.integrator} | {scene.nodes or '1 (single process)'} | "
            f"{cov['passes']} | {cov['inside']} | {cov['below']} / {cov['above']} | "
            f"{cov['inside'] / max(cov['passes'], 1):.2f} | {noise:.2g} | {target:.3g} | "
            f"{len(runs)} | {sum(r.met for r in runs)} | "
            f"{','.join(str(r.stop_spp) for r in runs)} | "
            f"{','.join(str(r.oracle) if r.oracle else '—' for r in runs)} | {ratio} |")
    return "\n".join(lines)


def calibration_scenes(quick: bool, work: Path, meshes: Path, timeout: float,
                       only: str | None = None) -> tuple[list[CalScene], list[str]]:
    """Build the stores and list the scenes (``only``: those whose "name integrator" holds
    that text); the second list says what was skipped and why.

    Both runs: generated ``rm`` (PT, AO) and ``cosmo`` (PT on 2 nodes), the built-in scene
    (PT), the heavy-tailed hidden lamp (``bench_scenes.hidden_lamp_scene``: a point light in
    a cup under the ceiling, every visible pixel lit through a bounce off a small bright spot;
    PT, one process; the full run adds it on 2 nodes) and the real scans of ``meshes``: the
    bunny (PT, one process) and the turbine blade (a CT isosurface; AO on 2 nodes). The full
    run adds the built-in scene with AO."""
    from bench_scenes import hidden_lamp_scene

    res, grid = ("32", "2x2x2") if quick else ("64", "2x2x2")
    skipped: list[str] = []

    def wanted(name: str, *integrators: str) -> bool:
        return not only or any(only in f"{name} {i}" for i in integrators)

    scenes = []
    for kind in ("rm", "cosmo"):
        if wanted(kind, "pt", "ao"):
            vastray("generate", kind, "-o", str(work / f"{kind}.store"), "--resolution", res,
                    "--grid", grid, "--force", "--quiet", cwd=work, timeout=timeout)
    scenes += [CalScene("rm", work / "rm.store", "pt"),
               CalScene("rm", work / "rm.store", "ao"),
               CalScene("cosmo", work / "cosmo.store", "pt", nodes=2),
               CalScene("built-in", None, "pt")]
    if wanted("hidden lamp", "pt"):
        ply, toml = hidden_lamp_scene(work / "lamp")
        vastray("partition", str(ply), "-o", str(work / "lamp.store"), "--grid", "2x2x2",
                "--force", "--quiet", cwd=work, timeout=timeout)
        lamp = ["--scene", str(toml)]
        scenes.append(CalScene("hidden lamp", work / "lamp.store", "pt", options=lamp))
        if not quick:
            scenes.append(CalScene("hidden lamp", work / "lamp.store", "pt", nodes=2,
                                   options=lamp))
    scans = [("bunny", "stanford_bunny.ply", "pt", None),
             ("turbine blade", "turbine_blade_199k.ply", "ao", 2)]
    if not meshes.is_dir():
        skipped.append(f"real scans: {meshes} does not exist")
    else:
        for name, file, integrator, nodes in scans:
            if not wanted(name, integrator):
                continue
            if not (meshes / file).is_file():
                skipped.append(f"{name}: {meshes / file} not found")
                continue
            store = work / f"{file.split('.')[0]}.store"
            vastray("partition", str(meshes / file), "-o", str(store), "--grid", "2x2x2",
                    "--force", "--quiet", cwd=work, timeout=timeout)
            scenes.append(CalScene(name, store, integrator, nodes=nodes))
    if not quick:
        scenes.append(CalScene("built-in", None, "ao"))
    return [c for c in scenes if wanted(c.name, c.integrator)], skipped


def calibrate(quick: bool, out: Path, meshes: Path, timeout: float,
              only: str | None = None) -> dict:
    """Issue 41's calibration on real renders; prints the per-scene table and returns the
    figures (``calibration_figures``); ``only``: the scenes whose "name integrator" holds
    that text."""
    start = time.perf_counter()
    width, height = (48, 36) if quick else (64, 48)
    seeds = range(CAL_SEED_BASE, CAL_SEED_BASE + (6 if quick else 10))
    ref_spp = REFERENCE_FACTOR * CAL_SPP
    work = out / "calibration"
    work.mkdir(parents=True, exist_ok=True)
    scenes, skipped = calibration_scenes(quick, work, meshes, timeout, only)
    print(f"\nCalibration of the error estimates without a reference (issue 41): "
          f"{len(scenes)} scenes, {width}x{height}, runs of {CAL_SPP} spp at most "
          f"(--max-pass-spp {CAL_MAX_PASS_SPP}), seeds {seeds[0]}-{seeds[-1]}; each scene's "
          f"reference {ref_spp} spp, seed {REFERENCE_SEED}, in one process", flush=True)
    for reason in skipped:
        print(f"  skipped: {reason}")
    rows, all_cov, all_runs = [], [], []
    common = ["--spp", str(CAL_SPP), "--max-pass-spp", str(CAL_MAX_PASS_SPP), "--quiet"]
    for k, scene in enumerate(scenes):
        tag = f"{k}-{scene.name.replace(' ', '_')}-{scene.integrator}"
        ref = work / f"{tag}-ref.exr"
        base = scene.args(width, height)
        if scene.nodes:  # the reference in one process: the image is the same on any nodes
            base_ref = CalScene(scene.name, scene.store, scene.integrator,
                                options=scene.options).args(width, height)
        else:
            base_ref = base
        vastray("render", *base_ref, "--spp", str(ref_spp), "--seed", REFERENCE_SEED,
                "-o", str(ref), "--report", str(work / f"{tag}-ref.json"), "--quiet",
                cwd=work, timeout=timeout)
        noise = reference_noise(json.loads((work / f"{tag}-ref.json").read_text()))
        reference = read_image(ref)
        cov_reports = {}
        for seed in seeds:
            path = work / f"{tag}-cov{seed}.json"
            vastray("render", *base, *common, "--seed", str(seed), "--reference", str(ref),
                    "-o", str(work / f"{tag}-cov{seed}.exr"), "--report", str(path),
                    cwd=work, timeout=timeout)
            cov_reports[seed] = json.loads(path.read_text())
        cov = coverage(list(cov_reports.values()), noise)
        target = choose_target(list(cov_reports.values()), noise)
        runs = []
        for seed in seeds:
            image, path = work / f"{tag}-target{seed}.exr", work / f"{tag}-target{seed}.json"
            vastray("render", *base, *common, "--seed", str(seed), "--target-error",
                    f"{target:.6g}", "-o", str(image), "--report", str(path),
                    cwd=work, timeout=timeout)
            report = json.loads(path.read_text())
            last = [p for p in report["passes"] if p.get("spp", 0) > 0][-1]
            pixels = read_image(image)
            runs.append(TargetRun(
                seed=seed, stop_spp=last["spp"], stopped_by=report.get("stopped_by", "?"),
                stop_bound=report.get("stop_bound"), target=float(f"{target:.6g}"),
                true_error=true_rel_mse(relative_mse(pixels, reference), noise),
                oracle=oracle_spp(cov_reports[seed], noise, float(f"{target:.6g}")),
                grey_error=true_rel_mse(grey_rel_mse(pixels, reference), noise),
                ci95=last.get("estimated_rel_mse_ci95")))
        rows.append((scene, cov, noise, target, runs))
        all_cov.append(cov)
        all_runs += runs
        print(f"  {scene.name} {scene.integrator}{f' on {scene.nodes} nodes' if scene.nodes else ''}: "
              f"coverage {cov['inside']}/{cov['passes']}, E {target:.3g}, met "
              f"{sum(r.met for r in runs)}/{len(runs)}, stops at "
              f"{[r.stop_spp for r in runs]} spp (oracle {[r.oracle for r in runs]}), "
              f"{time.perf_counter() - start:.0f} s", flush=True)
    table = calibration_table(rows)
    print(f"\nPer scene (true relMSE = relMSE against the reference minus the reference's own "
          f"estimated relMSE; coverage over the passes at >= {COVERAGE_MIN_SPP} spp; E = the "
          f"median true relMSE at {TARGET_AT_SPP} spp; stop spp and oracle spp per seed):\n")
    print(table)
    (out / "calibration.md").write_text(table + "\n")
    figures = calibration_figures(all_cov, all_runs)
    print(f"\nDiagnostic: the film's batches estimate the per-channel relMSE (the reports' "
          f"rel_mse; before, the grey image's); at the {len(all_runs)} target runs' stops, the "
          f"grey (channel-mean) image's true relMSE is <= E in "
          f"{figures['target_met_share_grey']:.3f} and inside the stop pass's 95 % CI in "
          f"{figures['ci_coverage_grey_at_stop']:.3f} of them (ci_coverage above: the "
          f"channels' relMSE, the one users compare with).")
    figures["scenes"] = len(scenes)
    figures["seconds"] = time.perf_counter() - start
    return figures


def calibration_line(f: dict) -> str:
    def num(v, fmt=".3f"):
        return "none" if v is None else format(v, fmt)
    return (f"ci_coverage={num(f['ci_coverage'])} (passes at >= {COVERAGE_MIN_SPP} spp: "
            f"{f['passes']}) target_met_share={num(f['target_met_share'])} (runs: {f['runs']}) "
            f"spp_over_oracle={num(f['spp_over_oracle'], '.2f')} "
            f"(max {num(f['spp_over_oracle_max'], '.2f')}) scenes={f['scenes']} "
            f"calibration_seconds={f['seconds']:.0f} "
            f"target_met_share_grey={num(f['target_met_share_grey'])} "
            f"ci_coverage_grey_at_stop={num(f['ci_coverage_grey_at_stop'])}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="64x48, 64 spp, 12 runs (under a minute on an idle 2-core machine)")
    parser.add_argument("--out", type=Path,
                        help="folder for the reports, table and plot (default: a new "
                             "temporary folder)")
    parser.add_argument("--timeout", type=float, default=900, help="seconds per render")
    parser.add_argument("--part", choices=("all", "schedulers", "calibration"), default="all",
                        help="the schedulers' table, the error estimates' calibration (issue "
                             "41), or both (default)")
    parser.add_argument("--meshes", type=Path, default=MESHES,
                        help=f"folder of real scans for the calibration (default: {MESHES}; "
                             "skipped with a printed reason when absent)")
    parser.add_argument("--only", metavar="TEXT",
                        help="calibrate only the scenes whose 'name integrator' holds TEXT "
                             "(e.g. 'lamp', 'blade ao'); the figures are then of those alone")
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
    status = 0
    if args.part != "calibration":
        status = schedulers(args, out, cores, start, resolution, grid, width, height, spp)
    if args.part != "schedulers":
        figures = calibrate(args.quick, out, args.meshes, args.timeout, args.only)
        print("\n" + calibration_line(figures) + f" cores={cores} "
              f"seconds={time.perf_counter() - start:.0f}")
    return status


def schedulers(args, out: Path, cores: int, start: float, resolution: str, grid: str,
               width: str, height: str, spp: int) -> int:
    """The schedulers' time-to-error table and the lossy split (issue 22); 1 on a mismatch."""
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
                "reference", "--report", "ref.json", cwd=work, timeout=args.timeout)
        noise = reference_noise(json.loads((work / "ref.json").read_text()))
        print(f"reference: {REFERENCE_FACTOR * spp} spp in {time.perf_counter() - t0:.1f} s, "
              f"its own estimated relMSE {noise:.3g}", flush=True)
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
    split = bias_variance(reports[lossy.name], twin, noise)
    control = bias_variance(twin, reference_noise=noise)
    print(f"\nLossy {lossy.name} (per-pixel relMSE over pixels and channels, ε = "
          f"{REL_MSE_EPSILON:g}, every term): relMSE {split['rel_mse']:.3g} = bias^2 "
          f"{split['bias2']:.3g} + variance {split['variance']:.3g} (the film's own estimate) "
          f"+ the reference's variance {noise:.3g} (its film's own estimate, at "
          f"{REFERENCE_FACTOR}x the spp); paired with the lossless temporal run of the same "
          f"seed: bias^2 {split['bias2_paired']:.3g}. Caveat: the estimates are noisy, so a "
          "bias below the noise can come out negative.")
    print(f"Control, lossless temporal-n{lossy.nodes} (true bias 0): relMSE "
          f"{control['rel_mse']:.3g} = bias^2 {control['bias2']:.3g} + variance "
          f"{control['variance']:.3g} + the reference's {noise:.3g}: a bias^2 of this size "
          "is noise.")
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
          f"lossy_variance={split['variance']:.3g} reference_variance={noise:.3g} "
          f"control_bias2={control['bias2']:.3g} "
          f"cores={cores} "
          f"seconds={time.perf_counter() - start:.0f}"
          + (f" mismatched={','.join(mismatches)}" if mismatches else ""))
    return 0 if not mismatches else 1


if __name__ == "__main__":
    sys.exit(main())
