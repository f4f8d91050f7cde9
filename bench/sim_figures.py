"""The papers' scaling figures in the simulator (``bench/simulate.py`` runs them in full mode):

- Navrátil et al. 2012, Fig. 12: strong scaling of the ``image``, ``domain`` and ``dynamic``
  schedules, 1 to 1,024 nodes;
- Park et al. 2018 (SpRay), Fig. 7: in situ rendering of DNS-like stores of 723 and 1,439
  domains (the paper's DNS1 and DNS2 have 720 and 1,427) on 8 and 16 nodes, ``spec-insitu``
  against the non-speculative baselines, AO and PT;
- Xu et al. 2022, Fig. 5: an animation on 4, 8 and 16 nodes, ``temporal`` against Galaxy's
  asynchronous decomposition (``async``, the paper's Abram et al.) and Navrátil's ``domain``
  and ``dynamic`` rounds, each node caching 4 domains behind emulated storage;
- Xu et al. at 8 to 64 nodes (``python bench/sim_figures.py --temporal-scale``, run alone:
  about 20 minutes, which the full bench's 30 have no room for): ``temporal``
  with Algorithm 1 (``paper``), with cache affinity (``affinity``, the default) and with the
  static groups while they fit the caches (``fit``), against Galaxy's ``async`` and the
  cache-aware baseline (``temporal`` on the static groups, cached domains first), with a
  quarter of the domains cached a node (the paper's ratio) and with a quarter of a node's
  group (where the groups do not fit).

Every run: warm nodes (no first-use cost: the papers time rendering, not start-up), a core
per node, this machine's calibrated costs. Each figure is a PNG in ``docs/`` and a table here.
"""

from __future__ import annotations

from pathlib import Path

from bench_scenes import CACHE, cached_cosmo

from vastray.actors.job_options import JobOptions
from vastray.render.driver import shading_inputs
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig, parse_scene_config
from vastray.scene.store import Store
from vastray.sim.cache import Domains
from vastray.sim.costs import CostModel
from vastray.sim.simulate import simulate

DOCS = Path(__file__).resolve().parent.parent / "docs"
NAVRATIL = ("image", "domain", "dynamic")
#: Xu's Fig. 5: 4 frames of an orbit, each node caching 4 domains, storage at this many
#: MB/s per node (the same for every scheduler)
XU_FRAMES, XU_CACHE, XU_BANDWIDTH_MB_S = 4, 4, 100.0
XU_SCHEDULERS = ("temporal", "async", "domain", "dynamic")
ORBIT = parse_scene_config("[camera.orbit]\ndegrees_per_frame = 2\n", "orbit")


def _run(store, scheduler: str, nodes: int, costs: CostModel, settings: RenderSettings,
         domains: Domains, config: SceneConfig | None = None, **options) -> float:
    frames = options.pop("frames", None)
    result = simulate(store, JobOptions(scheduler=scheduler, **options), nodes, costs, settings,
                      config, frames=frames, max_pass_spp=None, domains=domains)
    return result.seconds


def _plot(path: Path, draw) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = draw(plt)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    print(f"  wrote {path.relative_to(DOCS.parent)}")


def navratil(times: dict, n_domains: int) -> dict:
    """Fig. 12 from the scaling runs ``times`` ({scheduler: {P: seconds}}) on a store of
    ``n_domains`` domains."""
    rows = {s: times[s] for s in NAVRATIL if s in times}
    print("\nNavrátil Fig. 12 (strong scaling speed-up, T(1)/T(P)):")
    counts = sorted(next(iter(rows.values())))
    print("| P | " + " | ".join(rows) + " |")
    print("| --- |" + " --- |" * len(rows))
    for p in counts:
        print(f"| {p} | " + " | ".join(f"{by[1] / by[p]:.1f}" for by in rows.values()) + " |")

    def draw(plt):
        figure, axes = plt.subplots(figsize=(5.5, 4))
        axes.loglog(counts, counts, "k:", label="ideal")
        for scheduler, by in rows.items():
            axes.loglog(counts, [by[1] / by[p] for p in counts], "o-", label=scheduler)
        axes.set_xlabel("nodes")
        axes.set_ylabel("speed-up over 1 node")
        axes.set_title(f"Navrátil Fig. 12 in the simulator ({n_domains:,} domains)")
        axes.legend()
        return figure, axes

    _plot(DOCS / "sim_navratil.png", draw)
    return {s: {str(p): by[p] for p in counts} for s, by in rows.items()}


def dns_like(grid: tuple[int, int, int]) -> Store:
    """The ``cosmo`` scene at 160^3 in ``grid`` cells (a DNS-like domain count: 10x10x8 gives
    723 domains, 16x16x8 1,439; DNS1 and DNS2 have 720 and 1,427)."""
    return cached_cosmo(160, grid)


def spray_insitu(costs: CostModel) -> dict:
    """SpRay Fig. 7: spec-insitu against domain and async, AO and PT, 8 and 16 nodes."""
    out: dict = {}
    settings = {"ao": RenderSettings(width=64, height=64, spp=2, integrator="ao",
                                     shadow_samples=4),
                "pt": RenderSettings(width=64, height=64, spp=2, integrator="pt", bounces=1,
                                     shadow_samples=2)}
    print("\nSpRay Fig. 7 (in situ, simulated seconds; ratio = baseline / spec-insitu):")
    print("| store | domains | integrator | nodes | spec-insitu | domain | async | "
          "domain / spec-insitu | async / spec-insitu |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, grid in (("DNS1-like", (10, 10, 8)), ("DNS2-like", (16, 16, 8))):
        store = dns_like(grid)
        for integrator, st in settings.items():
            domains = Domains(store, shading_inputs(store, SceneConfig(), integrator)[1])
            for nodes in (8, 16):
                t = {s: _run(store, s, nodes, costs, st, domains)
                     for s in ("spec-insitu", "domain", "async")}
                out[f"{name} {integrator} {nodes}"] = t
                print(f"| {name} | {len(store.domains)} | {integrator} | {nodes} | "
                      f"{t['spec-insitu']:.3f} | {t['domain']:.3f} | {t['async']:.3f} | "
                      f"{t['domain'] / t['spec-insitu']:.2f} | "
                      f"{t['async'] / t['spec-insitu']:.2f} |", flush=True)
            domains.close()

    def draw(plt):
        figure, axes = plt.subplots(figsize=(7, 4))
        labels = list(out)
        for k, scheduler in enumerate(("spec-insitu", "domain", "async")):
            axes.bar([i + 0.27 * (k - 1) for i in range(len(labels))],
                     [out[label][scheduler] for label in labels], width=0.27, label=scheduler)
        axes.set_xticks(range(len(labels)), [label.replace(" ", "\n", 1) for label in labels],
                        fontsize=7)
        axes.set_ylabel("simulated seconds")
        axes.set_title("SpRay Fig. 7 (in situ) in the simulator")
        axes.legend()
        return figure, axes

    _plot(DOCS / "sim_spray_insitu.png", draw)
    return out


def xu_store() -> Store:
    """The ``cosmo`` scene at 160^3 in 4x4x4 domains (the temporal bench's)."""
    return cached_cosmo(160, (4, 4, 4))


def xu_fig5(costs: CostModel) -> dict:
    """Xu Fig. 5: seconds per frame (frames after the first) on 4, 8 and 16 nodes."""
    store = xu_store()
    settings = RenderSettings(width=96, height=96, spp=2, integrator="pt", bounces=1,
                              shadow_samples=2)
    domains = Domains(store, shading_inputs(store, ORBIT, settings.integrator)[1])
    out: dict = {}
    print(f"\nXu Fig. 5 ({XU_FRAMES}-frame orbit of {store.path.name}, cache {XU_CACHE} "
          f"domains per node, storage {XU_BANDWIDTH_MB_S:g} MB/s per node; simulated seconds "
          "for the animation):")
    print("| nodes | " + " | ".join(XU_SCHEDULERS) + " | async / temporal |")
    print("| --- |" + " --- |" * (len(XU_SCHEDULERS) + 1))
    for nodes in (4, 8, 16):
        t = {s: _run(store, s, nodes, costs, settings, domains, ORBIT, frames=XU_FRAMES,
                     cache=XU_CACHE, load_bandwidth=(XU_BANDWIDTH_MB_S,))
             for s in XU_SCHEDULERS}
        out[nodes] = t
        print(f"| {nodes} | " + " | ".join(f"{t[s]:.3f}" for s in XU_SCHEDULERS)
              + f" | {t['async'] / t['temporal']:.2f} |", flush=True)
    domains.close()

    def draw(plt):
        figure, axes = plt.subplots(figsize=(5.5, 4))
        counts = sorted(out)
        for scheduler in XU_SCHEDULERS:
            axes.plot(counts, [out[p][scheduler] for p in counts], "o-", label=scheduler)
        axes.set_xscale("log", base=2)
        axes.set_xticks(counts, [str(p) for p in counts])
        axes.set_xlabel("nodes")
        axes.set_ylabel(f"simulated seconds ({XU_FRAMES} frames)")
        axes.set_title("Xu et al. Fig. 5 in the simulator")
        axes.legend()
        return figure, axes

    _plot(DOCS / "sim_xu_fig5.png", draw)
    return out


#: Temporal coherence at the paper's scale: the runs compared (label, scheduler, options)
TEMPORAL_RUNS = (
    ("async (Galaxy)", "async", {}),
    ("cache-aware baseline", "temporal", {"assignment": "spatial", "priority": "queue+resident"}),
    ("temporal paper", "temporal", {"assignment": "paper"}),
    ("temporal affinity", "temporal", {"assignment": "affinity"}),
    ("temporal fit", "temporal", {"assignment": "fit"}),
)
TEMPORAL_NODES = (8, 16, 32, 64)
#: the store: cosmo 160^3 in 8x8x4 cells (256 domains where every cell is non-empty): a
#: group of 4 domains a node at 64 nodes
TEMPORAL_GRID = (8, 8, 4)


def temporal_at_scale(costs: CostModel, node_counts=TEMPORAL_NODES) -> dict:
    """Xu et al.'s schedules at 8 to 64 nodes (``TEMPORAL_RUNS``), Fig. 5's orbit and storage,
    each node caching a quarter of the domains (the paper's ratio: every static group fits
    from 4 nodes on) or a quarter of a node's static group (none fits): simulated seconds for
    the animation, and the strongest baseline's over the best ``temporal``'s."""
    store = cached_cosmo(160, TEMPORAL_GRID)
    settings = RenderSettings(width=96, height=96, spp=2, integrator="pt", bounces=1,
                              shadow_samples=2)
    domains = Domains(store, shading_inputs(store, ORBIT, settings.integrator)[1])
    n_domains = sum(1 for d in store.domains if d.n_triangles > 0)
    labels = [label for label, _, _ in TEMPORAL_RUNS]
    out: dict = {}
    caches = {"a quarter of the domains": lambda p: max(2, n_domains // 4),
              "a quarter of a node's group": lambda p: max(2, -(-n_domains // p) // 4)}
    for name, cache_of in caches.items():
        print(f"\ntemporal at scale: {XU_FRAMES}-frame orbit of {store.path.name} "
              f"({n_domains} domains), 96x96 x 2 spp, each node caching {name}, storage "
              f"{XU_BANDWIDTH_MB_S:g} MB/s a node; simulated seconds for the animation:")
        print("| nodes | cache | " + " | ".join(labels)
              + " | strongest baseline / best temporal |")
        print("| --- | --- |" + " --- |" * (len(labels) + 1))
        rows = out[name] = {}
        for nodes in node_counts:
            cache = cache_of(nodes)
            t = {label: _run(store, scheduler, nodes, costs, settings, domains, ORBIT,
                             frames=XU_FRAMES, cache=cache,
                             load_bandwidth=(XU_BANDWIDTH_MB_S,), **extra)
                 for label, scheduler, extra in TEMPORAL_RUNS}
            baseline = min(t[labels[0]], t[labels[1]])
            best = min(t[label] for label in labels[2:])
            rows[nodes] = {**t, "cache": cache, "ratio": baseline / best}
            print(f"| {nodes} | {cache} | " + " | ".join(f"{t[label]:.3f}" for label in labels)
                  + f" | {baseline / best:.2f} |", flush=True)
    domains.close()
    return out


def paper_figures(costs: CostModel, times: dict, n_domains: int) -> dict:
    """Every figure; ``times``: the scaling runs on a store of ``n_domains`` domains
    (Navrátil's from them)."""
    warm = costs.warm().with_cores(None)
    return {"navratil_fig12": navratil(times, n_domains), "spray_fig7": spray_insitu(warm),
            "xu_fig5": xu_fig5(warm)}


def main() -> None:
    import argparse
    import json

    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--temporal-scale", action="store_true",
                        help="Xu et al.'s schedules at 8 to 64 nodes (the figure run alone; "
                             "the others run in bench/simulate.py's full mode)")
    parser.add_argument("--costs", default=str(CACHE / "costs.json"),
                        help="a calibration file (default: the last bench/simulate.py's)")
    parser.add_argument("--nodes", default=",".join(map(str, TEMPORAL_NODES)),
                        help="node counts, comma-separated (default: %(default)s)")
    parser.add_argument("--json", help="write the table's numbers here")
    args = parser.parse_args()
    if not args.temporal_scale:
        parser.error("name the figure to run: --temporal-scale (the papers' others run in "
                     "`python bench/simulate.py`'s full mode)")
    costs = CostModel.load(args.costs).warm().with_cores(None)
    out = temporal_at_scale(costs, tuple(int(n) for n in args.nodes.split(",")))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
