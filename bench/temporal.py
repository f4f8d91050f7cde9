"""The temporal-coherence paper's experiments on our data (Xu et al., TVCG 2022: Fig. 5,
Fig. 7, Tables 2-4), with N local node processes and emulated network storage, against two
baselines: the paper's and the strongest we have.

A generated scene in a grid of 64 domains, larger than the nodes' caches (each node may hold
25 % of its group: 4 of 16 domains at N = 4), a camera orbiting 1 degree per frame, and every
node's loads throttled to an emulated storage bandwidth: the fastest node loads a domain of
mean size in ``--load-ms`` milliseconds (default 30), the others at .75, .5 and .25 of its
speed by rank, as the paper's nodes load at different speeds. Loads must dominate for the
method to matter, so the script prints the share of node time spent waiting for loads.

Headline rows (each run ``--repeats`` times, default 3, interleaved, reported by the median
time per frame; every run renders the same frames with the same seeds):

- ``baseline (paper's)``: "async (spatial assignment, queue priority)" on the same runtime
  as ``temporal``: contiguous z-order groups, screen tiles, fullest queue first, the same
  preloader (the next fullest queue).
- ``baseline, cache-aware``: the same with cached domains traced first (``--priority
  queue+resident``), the cache awareness the temporal priorities have through T_LOAD: the
  strongest baseline (the project rule: a baseline gets every improvement our method gets).
- ``temporal``: Algorithm 1 with cache affinity (``--assignment affinity``: a domain a node
  holds stays unless moving it saves more than its load) and Eq. 1-4 as a ratio
  (``cost-rate``); lossless, so its frames equal the baseline's bit for bit.
- ``baseline, cache-aware --simplified`` and ``temporal --simplified``: the portal policy
  (depth-1 rays predicted at most 0.5 and every deeper ray on the simplified model, 1 % of
  the triangles), with portals of ``--portal-resolution`` (default 4) accumulated over the
  frames (``--portal-memory``, default 10: every frame records the depth-1 rays it traces
  fine). One recording frame of 128x72x8 paths leaves 72 % of the crossings of the next
  frame in cells of an 8x8 portal it never saw, 46 % at 4x4; accumulation fills them frame
  by frame.

Ablations, one run each: assignment ``paper`` (Algorithm 1 as written) / ``affinity`` x
priority (``cost-rate``, ``queue+resident``; without ``--quick`` also ``cost-benefit``, Eq. 1
as written, and ``queue``), and without ``--quick`` vastray's ``async`` as shipped.

Printed: time per frame over frames 1.. (frame 0 bootstraps the statistics), loads, MB
loaded, rays sent between nodes; ``temporal_speedup_strongest=`` (cache-aware / temporal;
floor 1.25) and ``temporal_speedup=`` (paper's baseline / temporal);
``simplified_speedup_strongest=`` (cache-aware --simplified / temporal --simplified; floor
1.5), the same against the lossless cache-aware baseline, and ``simplified_speedup=``
(paper's baseline / temporal --simplified). The error of ``--simplified`` against a
converged reference (``REFERENCE_FACTOR`` x the samples, another seed; the last two timed
frames with ``--quick``, else the last three): ``simplified_rel_mse_global=`` is the
energy-normalised relative MSE it adds (``rel_mse_global`` = MSE / mean(r**2), as in the
render reports; not the per-pixel ``rel_mse``) (its rel_mse_global minus the lossless
cache-aware run's, same seeds; bound 1e-3), split into bias^2 and variance (each film's own
variance estimate, per channel, over the same mean square), with the lossless run's split as
the control.
Then ``acc=`` and ``unrecorded_share=`` (the paper's ACC, Table 4) from an instrumented run
of the same frames that follows the timed run's portals, overall and per frame.

``--tables`` adds Tables 2, 3 and 4 (assignment x priority without and with preloading,
simplification policies, portal resolution 8-64); ``--table4`` runs only the baseline and
Table 4; ``--fig7`` only Fig. 7 (both baselines and temporal with each assignment at caches
of 1, 2, 4, 8 and all of a node's group).

    python bench/temporal.py --quick      # N = 4, 4 frames 128x72, about 6 minutes on 2 cores
    python bench/temporal.py              # N = 4, 10 frames 192x108, under 30 minutes
    python bench/temporal.py --quick --fig7     # cache sizes only
    python bench/temporal.py --quick --table4   # portal resolution only
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from bench_scenes import CACHE

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import parse_scene_config
from vastray.scene.generate import generate
from vastray.scene.simplify import build_simplified
from vastray.scene.store import Store

SPEED_BY_RANK = (1.0, 1.0, 0.75, 0.75, 0.5, 0.5, 0.25, 0.25)
ORBIT = """
[camera.orbit]
degrees_per_frame = 1
"""


def scene(resolution: int) -> Store:
    """The ``cosmo`` scene (the paper's Cosmic Web analogue) in 4x4x4 domains, with a
    simplified model of 1 % of its triangles, made on first use."""
    path = CACHE / f"cosmo-{resolution}-4x4x4.store"
    if not (path / "manifest.json").is_file():
        generate("cosmo", path, resolution, grid=(4, 4, 4), seed=0, overwrite=True,
                 progress=True)
    store = Store(path)
    if store.simplified is None:
        build_simplified(store, 0.01, min_faces=200, progress=True)
        store = Store(path)
    return store


#: Samples of the converged reference per sample of a run (its own noise is 1/FACTOR of a
#: run's variance, taken out of the bias below), and its seed (not the runs' 0).
REFERENCE_FACTOR = 8
REFERENCE_SEED = 7919


def run(store: Store, settings: RenderSettings, nodes: int, frames: list[int], cache: int,
        bandwidth: float | None, scheduler: str, **options) -> dict:
    """One animation; per-frame seconds, images, the films' variance estimates and summed
    counters (``bandwidth``: MB/s of the fastest node's emulated storage, None: no
    emulation)."""
    images, variances, seconds, counters = {}, {}, {}, []

    def on_frame(frame, result):
        images[frame] = result.film.image()
        variances[frame] = result.film.variance_of_mean()
        seconds[frame] = result.seconds["total"]
        counters.append([n["counters"] for n in result.counters["per_node"]])

    options = {"load_bandwidth": None if bandwidth is None
               else [bandwidth * s for s in SPEED_BY_RANK[:nodes]], "preload": True, **options}
    config = parse_scene_config(ORBIT, "orbit")
    start = time.perf_counter()
    render_distributed(store.path, None, settings, nodes,
                       options=JobOptions(scheduler=scheduler, cache=cache,
                                          max_samples_in_flight=1 << 20, **options), timeout=600,
                       config=config, frames=frames, on_frame=on_frame)
    wall = time.perf_counter() - start
    later = [f for f in frames if f != frames[0]]

    def total(key, rows=counters[1:]):
        return sum(c.get(key, 0) for frame in rows for c in frame)

    # a node's time: tracing, waiting for loads, for messages, and sending (trace_s is the
    # trace alone: the domain loop counts load waits apart, as load_wait_s)
    busy = sum(c.get("trace_s", 0) + c.get("load_wait_s", 0) + c.get("wait_s", 0)
               + c.get("send_s", 0) for frame in counters[1:] for c in frame)
    # Simple/total over the frames that predict (recording frames predict nothing)
    predicting = [frame for frame in counters[1:]
                  if not any(c.get("portal_recording") for c in frame)]
    crossings = total("portal_crossings", predicting)
    acc_crossings = total("acc_crossings")

    def per_frame(key):
        out = []
        for frame in counters[1:]:
            n = sum(c.get("acc_crossings", 0) for c in frame)
            out.append(sum(c.get(key, 0) for c in frame) / n if n else None)
        return out

    return {"images": images, "variances": variances, "seconds": seconds, "wall": wall,
            "simplified_share": (total("predicted_low", predicting) / crossings if crossings
                                 else None),
            "acc": total("acc_agree") / acc_crossings if acc_crossings else None,
            "acc_unrecorded_share": (total("acc_unrecorded") / acc_crossings
                                     if acc_crossings else None),
            "acc_per_frame": per_frame("acc_agree"),
            "unrecorded_per_frame": per_frame("acc_unrecorded"),
            "mean_s": float(np.mean([seconds[f] for f in later])),
            "loads": total("loads") / len(later), "mb": total("bytes_loaded") / 1e6 / len(later),
            "rays_sent": total("rays_sent") / len(later),
            "preloads": total("preloads") / len(later),
            "simplified": total("simplified_rays") / len(later),
            "load_wait_share": total("load_wait_s") / max(busy, 1e-9)}


def errors(images: dict, lossless: dict) -> tuple[float, float]:
    """Mean MSE and energy-normalised relative MSE (``rel_mse_global``: MSE / mean square of
    the lossless frame) over frames."""
    mse = [float(np.mean((images[f] - lossless[f]) ** 2)) for f in images]
    rel = [m / max(float(np.mean(lossless[f] ** 2)), 1e-30) for m, f in zip(mse, images,
                                                                            strict=True)]
    return float(np.mean(mse)), float(np.mean(rel))


def converged_split(r: dict, reference: dict) -> dict:
    """A run's error against the converged reference over the reference's frames, as
    energy-normalised relative MSE (``rel_mse_global``: MSE / mean square of the reference,
    as the render reports name it; not the per-pixel ``rel_mse``) split into bias^2 and
    variance.

    ``variance`` is the film's own estimate of its noise (``Film.variance_of_mean``, per
    pixel and channel, over the same mean square); ``bias2 = rel_mse_global - variance - the
    reference's own variance`` (it comes out slightly negative where the bias is below the
    noise of the estimates).
    """
    rel, var, ref_var = [], [], []
    for f, (image, ref_variance) in reference.items():
        energy = max(float(np.mean(image.astype(np.float64) ** 2)), 1e-30)
        rel.append(float(np.mean((r["images"][f].astype(np.float64) - image) ** 2)) / energy)
        var.append(float(np.nanmean(r["variances"][f])) / energy)
        ref_var.append(float(np.nanmean(ref_variance)) / energy)
    rel_mse, variance, noise = (float(np.mean(x)) for x in (rel, var, ref_var))
    return {"rel_mse_global": rel_mse, "variance": variance, "bias2": rel_mse - variance - noise,
            "reference_variance": noise}


def converged_reference(store: Store, settings: RenderSettings, frames: list[int],
                        nodes: int) -> dict:
    """(image, variance) per frame at REFERENCE_FACTOR times the samples and another seed,
    rendered with every domain cached and no storage emulation (lossless, so any schedule
    gives the same image for a seed)."""
    dense = replace(settings, spp=settings.spp * REFERENCE_FACTOR, seed=REFERENCE_SEED)
    r = run(store, dense, nodes, frames, len(store.domains), None, "temporal",
            assignment="spatial", priority="queue+resident")
    return {f: (r["images"][f].astype(np.float64), r["variances"][f]) for f in frames}


def row(name: str, r: dict, lossless: dict | None, base_s: float, aware_s: float,
        runs: int = 1) -> str:
    mse, rel = errors(r["images"], lossless) if lossless is not None else (0.0, 0.0)
    spread = (f"{min(r['all_s']):.2f}-{max(r['all_s']):.2f}" if runs > 1 else "one run")
    return (f"| {name} | {r['mean_s']:.2f} ({spread}) | {base_s / r['mean_s']:.2f} | "
            f"{aware_s / r['mean_s']:.2f} | {r['loads']:.0f} | "
            f"{r['preloads']:.0f} | {r['mb']:.1f} | {r['rays_sent']:,.0f} | "
            f"{r['simplified']:,.0f} | {mse:.3g} | {rel:.3g} |")


def share(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


HEADER = ("| run | s per frame (median; range) | vs paper's baseline | vs cache-aware baseline "
          "| loads per frame | of them preloads | MB loaded per frame | rays sent per frame "
          "| simplified rays per frame | MSE vs lossless | MSE/mean(r²) vs lossless |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")

#: The two baselines and the method, lossless and with the simplified model: each run
#: ``--repeats`` times, interleaved, and reported by the median time per frame.
PAPER_BASELINE = "baseline (paper's: spatial groups, screen tiles, queue priority)"
AWARE_BASELINE = "baseline, cache-aware (spatial groups, queue+resident: cached domains first)"
TEMPORAL = "temporal (affinity assignment, cost-rate)"
AWARE_SIMPLIFIED = "baseline, cache-aware --simplified"
TEMPORAL_SIMPLIFIED = "temporal --simplified (affinity, cost-rate)"
HEADLINE = {
    PAPER_BASELINE: dict(assignment="spatial", priority="queue"),
    AWARE_BASELINE: dict(assignment="spatial", priority="queue+resident"),
    TEMPORAL: dict(assignment="affinity", priority="cost-rate"),
    AWARE_SIMPLIFIED: dict(assignment="spatial", priority="queue+resident", simplified=True),
    TEMPORAL_SIMPLIFIED: dict(assignment="affinity", priority="cost-rate", simplified=True),
}


def ablations(full: bool) -> dict[str, dict]:
    """Assignment (paper's Algorithm 1 / with affinity) x priority, one run each: the
    combinations the headline rows leave out."""
    priorities = (("cost-rate", "queue+resident", "cost-benefit", "queue") if full
                  else ("cost-rate", "queue+resident"))
    out = {}
    for assignment in ("paper", "affinity"):
        for priority in priorities:
            if (assignment, priority) != ("affinity", "cost-rate"):
                out[f"assignment {assignment}, priority {priority}"] = dict(
                    assignment=assignment, priority=priority)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="4 frames 128x72, the headline runs 3 times (about 6 minutes)")
    parser.add_argument("--tables", action="store_true",
                        help="also the paper's Tables 2, 3 and 4 (one run each)")
    parser.add_argument("--table4", action="store_true",
                        help="only the baseline and Table 4 (portal resolution 8-64)")
    parser.add_argument("--fig7", action="store_true",
                        help="only Fig. 7: both baselines and temporal at caches of 1, 2, 4, 8 "
                             "and all of a node's group")
    parser.add_argument("--nodes", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3,
                        help="runs of each headline row (medians; default 3)")
    parser.add_argument("--spp", type=int,
                        help="samples per pixel (default 8 with --quick, else 16; the paper "
                             "renders 32-128)")
    parser.add_argument("--load-ms", type=float, default=30.0,
                        help="milliseconds the fastest node takes to load a domain of mean "
                             "size (the emulated storage bandwidth; default 30)")
    parser.add_argument("--portal-resolution", type=int, default=4,
                        help="portal cells per edge of the --simplified runs (default 4: at "
                             "these image sizes finer portals stay mostly unrecorded; Table 4 "
                             "sweeps 8-64)")
    parser.add_argument("--portal-memory", type=int, default=10,
                        help="frames a portal cell is kept without a new record (default 10; "
                             "0: the paper's, only recording frames record)")
    args = parser.parse_args()
    store = scene(160 if args.quick else 224)
    frames = list(range(4 if args.quick else 10))
    width, height = (128, 72) if args.quick else (192, 108)
    spp = args.spp or (8 if args.quick else 16)
    settings = RenderSettings(width=width, height=height, spp=spp,
                              integrator="pt", bounces=3, shadow_samples=2)
    group = -(-len(store.domains) // args.nodes)
    cache = max(2, -(-group // 4))  # 25 % of a node's group
    sizes = [d.nbytes for d in store.domains if d.n_triangles]
    args.bandwidth = float(np.mean(sizes)) / 1e6 / (args.load_ms / 1000)
    print("Baselines: every ratio named *_strongest is against the cache-aware baseline "
          "(spatial groups, cached domains first, the same preloader); the others against "
          "the paper's baseline (spatial groups, queue priority). Lossless runs' images are "
          "checked bit for bit against the paper's baseline.", flush=True)
    print(f"scene: {store.n_triangles:,} triangles in {len(store.domains)} domains "
          f"({np.mean(sizes) / 1e6:.2f} MB mean), simplified model "
          f"{store.simplified.n_triangles:,} triangles ({store.simplified.rate:.2%}); "
          f"{args.nodes} nodes, cache {cache} of a {group}-domain group; "
          f"{len(frames)} frames {width}x{height} {settings.spp} spp pt bounces 3; storage "
          f"{args.bandwidth:.3g} MB/s x {SPEED_BY_RANK[:args.nodes]} by rank (emulated: "
          f"{args.load_ms:g} ms per mean domain on the fastest node); --simplified: portal "
          f"{args.portal_resolution}x{args.portal_resolution}, --portal-memory "
          f"{args.portal_memory}\n", flush=True)
    common = dict(store=store, settings=settings, nodes=args.nodes, frames=frames,
                  cache=cache, bandwidth=args.bandwidth)
    simplified = dict(simplified="portal", portal_resolution=args.portal_resolution,
                      portal_memory=args.portal_memory)
    if args.fig7:
        fig7(common, group)
        return
    if args.table4:
        baseline = run(scheduler="temporal", assignment="spatial", priority="queue", **common)
        table4(common, baseline["images"], baseline["mean_s"], args.portal_memory)
        return

    def options(config: dict) -> dict:
        config = dict(config)
        return {**config, **(simplified if config.pop("simplified", False) else {})}

    timed: dict[str, list[dict]] = {name: [] for name in HEADLINE}
    names = list(HEADLINE)
    for repeat in range(args.repeats):  # interleaved, each repeat starting one further on
        for name in names[repeat % len(names):] + names[:repeat % len(names)]:
            timed[name].append(run(scheduler="temporal", **options(HEADLINE[name]), **common))
            print(f"  {name}: {timed[name][-1]['mean_s']:.2f} s per frame", flush=True)
    runs = {}
    for name, results in timed.items():
        times = [r["mean_s"] for r in results]
        median = results[int(np.argsort(times)[len(times) // 2])]
        runs[name] = {**median, "mean_s": float(np.median(times)), "all_s": times}
    lossless = runs[PAPER_BASELINE]["images"]
    extra = {name: run(scheduler="temporal", **config, **common)
             for name, config in ablations(not args.quick).items()}
    if not args.quick:
        extra["async (as shipped: round robin, path-split camera rays)"] = run(
            scheduler="async", **common)
    base_s, aware_s = runs[PAPER_BASELINE]["mean_s"], runs[AWARE_BASELINE]["mean_s"]
    print(f"\nFig. 5 (means over frames 1.., frame 0 bootstraps the statistics; headline rows: "
          f"median of {args.repeats} runs)\n")
    print(HEADER)
    for name, r in runs.items():
        print(row(name, r, lossless, base_s, aware_s, len(r["all_s"])), flush=True)
    for name, r in extra.items():
        print(row(name, r, lossless, base_s, aware_s), flush=True)
    temporal, both = runs[TEMPORAL], runs[TEMPORAL_SIMPLIFIED]
    exact = max(float(np.abs(r["images"][f] - lossless[f]).max())
                for r in [runs[AWARE_BASELINE], *timed[TEMPORAL]] for f in frames)
    _, rel = errors(both["images"], lossless)
    print(f"\nbaseline_load_wait_share={runs[PAPER_BASELINE]['load_wait_share']:.2f} "
          f"aware_load_wait_share={runs[AWARE_BASELINE]['load_wait_share']:.2f} (share of node "
          "time spent waiting for loads; the method matters only where loads dominate)")
    print(f"temporal_max_abs_diff={exact:.3g} (lossless: 0 expected, every temporal run against "
          "the paper's baseline)")
    print(f"temporal_speedup_strongest={aware_s / temporal['mean_s']:.3f} (cache-aware baseline "
          f"/ temporal; floor 1.25; below 1: the baseline wins) temporal_speedup="
          f"{base_s / temporal['mean_s']:.3f} (paper's baseline / temporal; paper +26 %)")
    # the converged reference: the last timed frames (its samples cost REFERENCE_FACTOR runs)
    checked = frames[1:][-2:] if args.quick else frames[1:][-3:]
    reference = converged_reference(store, settings, checked, args.nodes)
    split = converged_split(both, reference)
    control = converged_split(runs[AWARE_BASELINE], reference)
    added = split["rel_mse_global"] - control["rel_mse_global"]
    print(f"simplified_speedup_strongest={runs[AWARE_SIMPLIFIED]['mean_s'] / both['mean_s']:.3f} "
          f"(cache-aware baseline --simplified / temporal --simplified; floor 1.5) "
          f"simplified_speedup_vs_lossless_strongest={aware_s / both['mean_s']:.3f} (cache-aware "
          f"baseline, lossless / temporal --simplified) simplified_speedup="
          f"{base_s / both['mean_s']:.3f} (paper's baseline / temporal --simplified; paper +56 %)")
    print(f"simplified_rel_mse_global={added:.3g} (bound 1e-3: the energy-normalised relative "
          f"MSE, MSE / mean(r^2), --simplified adds "
          f"against a converged reference of {REFERENCE_FACTOR}x the samples, frames "
          f"{checked}: {split['rel_mse_global']:.3g} for temporal --simplified, minus "
          f"{control['rel_mse_global']:.3g} for the lossless cache-aware baseline, same seeds)")
    print(f"simplified_bias2={split['bias2']:.3g} simplified_variance={split['variance']:.3g} "
          f"lossless_bias2={control['bias2']:.3g} lossless_variance={control['variance']:.3g} "
          f"reference_variance={split['reference_variance']:.3g} (rel_mse_global = bias^2 + "
          f"variance "
          f"+ the reference's variance; variance from each film's own estimate; the lossless "
          f"run's bias^2, truly 0, shows the noise of this split) "
          f"simplified_rel_mse_global_vs_lossless={rel:.3g} (same seed)", flush=True)
    measured = run(scheduler="temporal", portal_accuracy=True,
                   **options(HEADLINE[TEMPORAL_SIMPLIFIED]), **common)
    print(f"acc={share(measured['acc'])} simplified_share={share(both['simplified_share'])} "
          f"unrecorded_share={share(measured['acc_unrecorded_share'])} (temporal "
          "--simplified, predicting frames: ACC from an instrumented run; target ACC >= 0.5; "
          "paper T4/T5 at 32x32: Courtyard 84.3 %/85.7 %, Agent327 98.3 %/16.5 %)")
    print("per frame: " + " ".join(
        f"f{f}: acc={share(a)} unrecorded={share(u)}"
        for f, a, u in zip(frames[1:], measured["acc_per_frame"],
                           measured["unrecorded_per_frame"], strict=True)), flush=True)
    if args.tables:
        tables(common, lossless, base_s, aware_s, args.portal_memory)


def tables(common: dict, lossless: dict, base_s: float, aware_s: float, memory: int) -> None:
    """The paper's Tables 2, 3 and 4 on this scene, one run each."""
    print("\nTable 2: assignment (no preloading, queue priority), then priority (affinity "
          "assignment, preloading)\n")
    print(HEADER)
    for assignment in ("sequential", "spatial", "paper", "affinity"):
        r = run(scheduler="temporal", assignment=assignment, priority="queue", preload=False,
                **common)
        print(row(f"assignment {assignment}", r, lossless, base_s, aware_s), flush=True)
    for priority in ("queue", "spray", "queue+act", "cost-benefit", "cost-rate",
                     "queue+resident"):
        r = run(scheduler="temporal", priority=priority, **common)
        print(row(f"priority {priority}", r, lossless, base_s, aware_s), flush=True)
    print("\nTable 3: which rays go to the simplified model (temporal scheduling)\n")
    print(HEADER)
    for policy, threshold in (("depth>2", 0.5), ("depth>1", 0.5), ("portal", 0.3),
                              ("portal", 0.5), ("depth>0", 0.5)):
        r = run(scheduler="temporal", simplified=policy, portal_threshold=threshold, **common)
        label = f"{policy} (threshold {threshold})" if policy == "portal" else policy
        print(row(label, r, lossless, base_s, aware_s), flush=True)
    table4(common, lossless, base_s, memory)


def fig7(common: dict, group: int) -> None:
    """The paper's Fig. 7: time per frame against the cache size per node, for the paper's
    baseline, the cache-aware one and temporal with the paper's Algorithm 1 and with cache
    affinity (all lossless, cost-rate), with loads and the paper's baseline's load-wait
    share."""
    print("Fig. 7: cache size per node (baseline: spatial groups, queue priority; cache-aware: "
          "the same, cached domains first; temporal: cost-rate with Algorithm 1 as the paper "
          "has it, and with cache affinity)\n")
    print("| cache (domains) | baseline s per frame | cache-aware s per frame | temporal paper "
          "s per frame | temporal affinity s per frame | temporal_speedup_strongest (paper / "
          "affinity) | baseline loads | cache-aware loads | temporal paper loads | temporal "
          "affinity loads | baseline load-wait share |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for cache in sorted({1, 2, 4, 8, group}):
        options = dict(common, cache=cache)
        base = run(scheduler="temporal", assignment="spatial", priority="queue", **options)
        aware = run(scheduler="temporal", assignment="spatial", priority="queue+resident",
                    **options)
        paper = run(scheduler="temporal", assignment="paper", **options)
        affinity = run(scheduler="temporal", assignment="affinity", **options)
        print(f"| {cache}{' (all)' if cache == group else ''} | {base['mean_s']:.2f} | "
              f"{aware['mean_s']:.2f} | {paper['mean_s']:.2f} | {affinity['mean_s']:.2f} | "
              f"{aware['mean_s'] / paper['mean_s']:.2f} / "
              f"{aware['mean_s'] / affinity['mean_s']:.2f} | {base['loads']:.0f} | "
              f"{aware['loads']:.0f} | {paper['loads']:.0f} | {affinity['loads']:.0f} | "
              f"{base['load_wait_share']:.2f} |", flush=True)


def table4(common: dict, lossless: dict, base_s: float, memory: int) -> None:
    """The paper's Table 4: temporal --simplified (portal policy) at portal resolutions 8-64
    (the paper: 8-128; 128 holds 64 x 6 x 128^2 x 8 cells per node, 240 MiB here), each
    timed, then measured in an instrumented run for ACC; ``memory``: --portal-memory."""
    print(f"\nTable 4: portal resolution (temporal --simplified, threshold 0.5, --portal-memory "
          f"{memory})\n")
    print("| resolution | s per frame | speedup vs baseline | MSE | MSE/mean(r²) | ACC | "
          "Simple/total | unrecorded share | simplified rays per frame |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for resolution in (8, 16, 32, 64):
        timed = run(scheduler="temporal", simplified="portal", portal_resolution=resolution,
                    portal_memory=memory, **common)
        measured = run(scheduler="temporal", simplified="portal", portal_accuracy=True,
                       portal_resolution=resolution, portal_memory=memory, **common)
        mse, rel = errors(timed["images"], lossless)
        print(f"| {resolution}x{resolution} | {timed['mean_s']:.2f} | "
              f"{base_s / timed['mean_s']:.2f} | {mse:.3g} | {rel:.3g} | "
              f"{share(measured['acc'])} | {share(timed['simplified_share'])} | "
              f"{share(measured['acc_unrecorded_share'])} | {timed['simplified']:,.0f} |",
              flush=True)


if __name__ == "__main__":
    main()
