"""Occupancy masks (issue 40): domain loads and (ray, domain) pairs queued with and without them.

A domain's box is often much larger than its triangles; a ray that crosses only its empty part
is queued there (and may cost a load) without masks. This renders the same image with the
masks on and off (``VASTRAY_OCCUPANCY``), for the baseline (``image``) and ``spec-ooc`` at a
25 % cache, and prints per schedule: loads, (ray, domain) pairs queued (every row pushed into
a domain's queue: the baseline's one-domain-at-a-time forwards, spec-ooc's speculative
copies), rays traced per domain (Embree queries), render seconds, and whether the two images
are the same bit for bit (they must be). Scenes:

* ``rm 320^3`` in 5x5x4 domains, ``bench/ooc.py --quick``'s first scene (1.2 M triangles, 58
  domains; generated into .bench_cache/ once, reused while its format is current);
* a real scan from ``../shared/data`` (the turbine blade CT isosurface, 199 k triangles) split
  into 64 k-d domains; skipped, with the reason, where the file is absent.

Each render is PT at 32x24, 8 spp, 4 shadow rays, 3 bounces (``--quick``'s), with
preloading off and resident-first on, so the loads are deterministic (preload guesses race
the render thread).

    python bench/masks.py            # both scenes, a few minutes on 2 cores
    python bench/masks.py --spp 2    # quicker
    python bench/masks.py --resolution 32 --resolution 64 --bound   # what finer culling could do

``--resolution R`` (repeatable) adds a row per schedule with every domain's mask computed
again at ``R`` cells along its longest axis (in memory, ignoring the stores' 1 % cap: what a
finer grid would remove). ``--bound`` adds the ceiling of any conservative culling (finer
masks, boxes of triangle runs, ...): a pair is kept only where its ray hits a triangle of the
domain before its limit, found by querying a side Embree scene of every domain outside the
cache (``ExactCulling``; an oracle for the measurement, not something a render could do
without loading the domain). Its loads are the fewest that dropping rays which find nothing
in a domain can give; the rest are loads for rays that do hit there.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.integrators import RenderSettings
from vastray.render.scene_config import SceneConfig
from vastray.scene import occupancy
from vastray.scene.embree.scenes import Scene
from vastray.scene.generate import generate
from vastray.scene.manifest import VERSION
from vastray.scene.occupancy import Occupancy
from vastray.scene.partition import partition_kd
from vastray.scene.readers import read_mesh
from vastray.scene.store import Store, StoreWriter, is_store
from vastray.schedule.soa import DomainQueues

ROOT = Path(__file__).resolve().parent.parent
CACHE = ROOT / ".bench_cache"
SCAN = ROOT.parent / "shared" / "data" / "meshes" / "turbine_blade_199k.ply"
SCHEDULERS = ("image", "spec-ooc")


def current(path: Path) -> Store | None:
    """The store at ``path`` if it is written in the current format (with masks)."""
    if not is_store(path):
        return None
    store = Store(path)
    return store if store.manifest["version"] == VERSION else None


def generated(resolution: int, grid: tuple[int, int, int]) -> Store:
    path = CACHE / f"rm-{resolution}-{'x'.join(map(str, grid))}.store"
    store = current(path)
    if store is None:
        print(f"generating {path.name} ...", file=sys.stderr, flush=True)
        generate("rm", path, resolution, grid=grid, seed=0, overwrite=True, progress=True)
        store = Store(path)
    return store


def scan(domains: int) -> Store | str:
    """The scan in ``domains`` k-d domains, or why not."""
    if not SCAN.is_file():
        return f"{SCAN} is absent (see ../shared/data/README.md)"
    path = CACHE / f"{SCAN.stem}-kd{domains}.store"
    store = current(path)
    if store is None:
        print(f"partitioning {SCAN.name} ...", file=sys.stderr, flush=True)
        with StoreWriter(path, objects=[{"name": SCAN.stem}]) as writer:
            for dom in partition_kd(read_mesh(SCAN), domains).domains:
                writer.add_domain(dom)
        store = Store(path)
    return store


class Counting:
    """Counts the rows pushed into every ``DomainQueues`` while active."""

    def __init__(self):
        self.pairs = 0
        self._push = DomainQueues.push

    def __enter__(self):
        counter = self

        def push(queues, domain, rays):
            counter.pairs += len(rays)
            return counter._push(queues, domain, rays)

        DomainQueues.push = push
        return self

    def __exit__(self, *exc):
        DomainQueues.push = self._push


class ExactCulling(Occupancy):
    """The store's masks, then an oracle: of the pairs they keep, only those whose ray hits a
    triangle of the domain within its limit (grown by 1e-4 relative, so a hit at the limit
    is kept). Each domain's side scene is built once, outside every cache and count."""

    def __init__(self, store: Store):
        super().__init__(*store.domain_boxes(), [d.occupancy for d in store.domains])
        self.store, self.scenes = store, {}

    @property
    def any_useful(self) -> bool:
        return True

    def crosses(self, origins, directions, ray, domain, limit, pad):
        keep = super().crosses(origins, directions, ray, domain, limit, pad)
        ends = np.broadcast_to(np.asarray(limit, np.float32), (len(origins),))
        for d in np.unique(domain[keep]):
            rows = np.nonzero(keep & (domain == d))[0]
            scene = self._scene(int(d))
            if scene is None:
                keep[rows] = False
                continue
            r = ray[rows]
            hit = scene.occluded(np.ascontiguousarray(origins[r], np.float32),
                                 np.ascontiguousarray(directions[r], np.float32),
                                 np.ascontiguousarray(ends[r] * np.float32(1.0001)), 1)
            keep[rows[~hit]] = False
        return keep

    def _scene(self, domain: int) -> Scene | None:
        if domain not in self.scenes:
            arrays = self.store.load_domain(domain)
            self.scenes[domain] = (Scene(np.asarray(arrays.vertices), np.asarray(arrays.indices))
                                   if len(arrays.indices) else None)
        return self.scenes[domain]

    def close(self) -> None:
        for scene in self.scenes.values():
            if scene is not None:
                scene.close()


def finer(store: Store, resolution: int) -> Occupancy:
    """Every domain's mask at ``resolution`` cells along its longest axis (no size cap)."""
    lo, hi = store.domain_boxes()
    masks = []
    for d in range(len(store.domains)):
        arrays = store.load_domain(d)
        dims = occupancy.grid_dims(lo[d], hi[d], math.inf, resolution)
        masks.append(occupancy.compute(np.asarray(arrays.vertices), np.asarray(arrays.indices),
                                       lo[d], hi[d], dims))
    return Occupancy(lo, hi, masks)


def run(store: Store, settings: RenderSettings, scheduler: str, cache: int, masks: bool,
        culling: Occupancy | None = None) -> dict:
    """One render at ``cache`` domains; ``culling`` replaces the store's masks (None: the
    store's own, or none without ``masks``)."""
    os.environ[occupancy.ENV] = "1" if masks else "0"
    store._occupancy = culling  # (None: the store's masks, built again when asked)
    start = time.perf_counter()
    with Counting() as counting:
        result = render_out_of_core(store, SceneConfig(), settings,
                                    options=JobOptions(scheduler=scheduler, cache=cache,
                                                       preload=False, resident_first=True),
                                    progress=False)
    c = result.counters
    return {"loads": c["loads"], "pairs": counting.pairs,
            "traced": c["radiance_tests"] + c["shadow_tests"], "floor": c["domains_traced"],
            "seconds": time.perf_counter() - start, "image": result.film.image()}


def scene_report(name: str, store: Store, settings: RenderSettings,
                 resolutions: tuple[int, ...] = (), bound: bool = False) -> None:
    n = len(store.domains)
    cache = max(1, math.ceil(0.25 * n))
    masks = [d.occupancy for d in store.domains if d.occupancy is not None]
    empty = np.mean([1 - m.mean() for m in masks]) if masks else float("nan")
    mask_bytes = sum((m.size + 7) // 8 for m in masks)
    print(f"\n## {name}: {store.n_triangles:,} triangles in {n} domains, cache {cache} (25 %); "
          f"masks {mask_bytes:,} bytes ({mask_bytes / sum(d.nbytes for d in store.domains):.4%} "
          f"of the domains'), {empty:.0%} of cells empty on average\n", flush=True)
    print("| scheduler | masks | loads | floor | pairs queued | rays traced | render s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    summary = []
    variants = [(f"{r} cells", lambda r=r: finer(store, r)) for r in resolutions]
    if bound:
        variants.append(("bound (oracle)", lambda: ExactCulling(store)))
    for scheduler in SCHEDULERS:
        got = {}
        for on in (False, True):
            r = got[on] = run(store, settings, scheduler, cache, on)
            print(f"| {scheduler} | {'on' if on else 'off'} | {r['loads']} | {r['floor']} | "
                  f"{r['pairs']:,} | {r['traced']:,} | {r['seconds']:.1f} |", flush=True)
        same = np.array_equal(got[True]["image"], got[False]["image"])
        summary.append(f"{scheduler}: loads {got[False]['loads']} -> {got[True]['loads']} "
                       f"({got[True]['loads'] / got[False]['loads']:.3f}), pairs "
                       f"{got[False]['pairs']:,} -> {got[True]['pairs']:,} "
                       f"({got[True]['pairs'] / got[False]['pairs']:.3f}), "
                       f"image {'identical' if same else 'DIFFERS'}")
        for label, make in variants:
            culling = make()
            try:
                r = run(store, settings, scheduler, cache, True, culling)
            finally:
                if isinstance(culling, ExactCulling):
                    culling.close()
                store._occupancy = None
            same = np.array_equal(r["image"], got[False]["image"])
            print(f"| {scheduler} | {label} | {r['loads']} | {r['floor']} | {r['pairs']:,} | "
                  f"{r['traced']:,} | {r['seconds']:.1f} |", flush=True)
            summary.append(f"{scheduler}, {label}: loads {r['loads']} "
                           f"({r['loads'] / got[True]['loads']:.3f} of the store's masks'), "
                           f"pairs {r['pairs']:,}, image {'identical' if same else 'DIFFERS'}")
    print()
    for line in summary:
        print(f"masks_{name.split()[0]}: {line}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--skip-generated", action="store_true")
    parser.add_argument("--resolution", type=int, action="append", default=[], metavar="R",
                        help="also masks of R cells along each domain's longest axis "
                             f"(1..{occupancy.MAX_CELLS}; repeatable)")
    parser.add_argument("--bound", action="store_true",
                        help="also the ceiling of any culling: pairs kept only where the ray "
                             "hits the domain (an oracle)")
    args = parser.parse_args()
    if any(not 1 <= r <= occupancy.MAX_CELLS for r in args.resolution):
        parser.error(f"--resolution must be 1..{occupancy.MAX_CELLS}")
    extra = {"resolutions": tuple(args.resolution), "bound": args.bound}
    settings = RenderSettings(width=32, height=24, spp=args.spp, integrator="pt", bounces=3,
                              shadow_samples=4, seed=7)
    started = time.perf_counter()
    if not args.skip_generated:
        scene_report("rm 320^3 5x5x4", generated(320, (5, 5, 4)), settings, **extra)
    got = scan(64)
    if isinstance(got, str):
        print(f"\n## scan: skipped: {got}")
    else:
        scene_report(f"{SCAN.stem} kd64", got, settings, **extra)
    print(f"\nbench/masks.py: {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
