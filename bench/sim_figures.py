"""The papers' scaling figures in the simulator (``bench/simulate.py`` runs them in full mode):

- Navrátil et al. 2012, Fig. 12: strong scaling of the ``image``, ``domain`` and ``dynamic``
  schedules, 1 to 1,024 nodes;
- Park et al. 2018 (SpRay), Fig. 7: in situ rendering of DNS-like stores of 723 and 1,439
  domains (the paper's DNS1 and DNS2 have 720 and 1,427) on 8 and 16 nodes, ``spec-insitu``
  against the non-speculative baselines, AO and PT;
- Xu et al. 2022, Fig. 5: an animation on 4, 8 and 16 nodes, ``temporal`` against Galaxy's
  asynchronous decomposition (``async``, the paper's Abram et al.) and Navrátil's ``domain``
  and ``dynamic`` rounds, each node caching 4 domains behind emulated storage.

Every run: warm nodes (no first-use cost: the papers time rendering, not start-up), a core
per node, this machine's calibrated costs. Each figure is a PNG in ``docs/`` and a table here.
"""

from __future__ import annotations

from pathlib import Path

from bench_scenes import cached_cosmo

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


def paper_figures(costs: CostModel, times: dict, n_domains: int) -> dict:
    """Every figure; ``times``: the scaling runs on a store of ``n_domains`` domains
    (Navrátil's from them)."""
    warm = costs.warm().with_cores(None)
    return {"navratil_fig12": navratil(times, n_domains), "spray_fig7": spray_insitu(warm),
            "xu_fig5": xu_fig5(warm)}
