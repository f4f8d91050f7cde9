"""Ray-domain enumeration at thousands of domains: the tree over domain boxes, walked in
compiled code, against the numpy walks and the former per-domain loop (issue "Honest
comparisons and a runtime that scales", section 3; issue 9's compiled enumeration).

The same rays meet 8, 64, 512 and 4,096 box domains: uniform grids of 2^3 .. 16^3 cells over
the unit cube (neighbouring boxes share faces, so rays run along faces and edges and ties are
frequent). Half the rays are camera rays from outside the cube, half start inside it in random
directions (as bounce rays do). For each domain count it times, as the schedulers call them:

- ``crossings``: every domain each ray crosses, in order (``DomainGeometry.crossings``;
  spec-ooc and spec-insitu queue rays this way; the reference renderer's ``DomainTracer``
  runs the same tree walk);
- ``walk``: ``DomainGeometry.next_domain`` again and again until no domain is left, each call
  for the rays still moving (the image schedule's front-to-back walk), per call and ray;
- ``loop``: the former per-domain slab loop's ``crossings`` (O(domains x rays)), on a subset
  of the rays, against ``crossings`` on the same subset (the two results are checked equal).

Queries walk the tree each ray in compiled code (``render.boxwalk``, the default); the
``numpy`` columns time the same queries through the numpy walks they replaced (breadth first
over the tree, a flat pass up to 64 boxes), with the same rays, boxes and answers (checked
equal), one thread each.

Each figure is the best of a few runs (the machine is shared). A ray crosses more domains in a
finer grid, so the per-ray cost of any exact enumeration grows with them; the cost that should
not grow with the domain count is the cost per ray *per domain crossed*. The last line,
``domain_scaling=``, is that cost at 4,096 domains divided by the cost at 8 (goal: <= 3); the
lines before it give the plain per-ray ratio and the walk's per-call ratio next to it.

    python bench/domains.py            # 2^18 rays (a few minutes on 2 cores)
    python bench/domains.py --quick    # 2^15 rays (well under a minute)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from vastray.render.boxtree import FLAT_BOXES
from vastray.schedule.geometry import DomainGeometry

# The per-domain loop the box-tree walk replaced, the baseline here, is test code.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from domain_loops import crossings_by_loop  # noqa: E402

SIDES = (2, 4, 8, 16)  # 8, 64, 512, 4096 domains
FULL = {"rays": 1 << 18, "loop_rays": 1 << 14, "repeat": 5}
QUICK = {"rays": 1 << 15, "loop_rays": 1 << 12, "repeat": 3}


def grid_boxes(side: int) -> tuple[np.ndarray, np.ndarray]:
    """(side^3, 3) lo, hi: the cells of a uniform grid over the unit cube."""
    edges = np.linspace(0.0, 1.0, side + 1)
    ix, iy, iz = (a.ravel() for a in np.meshgrid(*[np.arange(side)] * 3, indexing="ij"))
    lo = np.stack([edges[ix], edges[iy], edges[iz]], axis=1)
    hi = np.stack([edges[ix + 1], edges[iy + 1], edges[iz + 1]], axis=1)
    return lo, hi


def rays(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) float32 origins and unit directions: camera rays, then rays from inside."""
    rng = np.random.default_rng(seed)
    half = n // 2
    eye = np.array([2.2, 1.7, 2.9])
    forward = np.array([0.5, 0.5, 0.5]) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    u, v = rng.uniform(-0.3, 0.3, (2, half))  # a 33-degree field of view: the cube fills it
    camera = forward + u[:, None] * right + v[:, None] * up
    inside = rng.normal(size=(n - half, 3))
    origins = np.concatenate([np.tile(eye, (half, 1)), rng.uniform(0, 1, (n - half, 3))])
    directions = np.concatenate([camera, inside])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return origins.astype(np.float32), directions.astype(np.float32)


def best_of(repeat: int, fn) -> tuple[float, object]:
    """Least wall time of ``repeat`` calls of ``fn`` (seconds), and its last result."""
    best, out = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def walk(geometry: DomainGeometry, origins, directions, limit) -> tuple[int, int]:
    """Front-to-back walk with ``next_domain``; returns (calls, ray-calls)."""
    n = len(origins)
    moving = np.arange(n)
    at_t = np.full(n, -np.inf, np.float32)
    at_d = np.full(n, -1, np.int32)
    calls = ray_calls = 0
    while len(moving):
        domain, entry = geometry.next_domain(origins[moving], directions[moving], at_t[moving],
                                             at_d[moving], limit[moving])
        calls += 1
        ray_calls += len(moving)
        found = domain >= 0
        moving = moving[found]
        at_t[moving], at_d[moving] = entry[found], domain[found]
    return calls, ray_calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer rays (under a minute)")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    origins, directions = rays(plan["rays"])
    limit = np.full(len(origins), np.inf, np.float32)
    m = plan["loop_rays"]
    print(f"{len(origins):,} rays (half camera rays, half from inside the cube); best of "
          f"{plan['repeat']} runs; loop on {m:,} of them (half of each kind); the compiled "
          f"walk always walks the tree; numpy tests every box in one flat pass up to "
          f"{FLAT_BOXES} domains and walks the tree above that\n")
    print("| domains | tree levels | domains crossed per ray | crossings us/ray "
          "| us per domain crossed | walk us per call and ray | walk us/ray | loop us/ray "
          "| loop / crossings, same rays | numpy crossings us/ray | numpy walk us per call "
          "and ray |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    rows = {}
    subset = np.r_[0:m // 2, len(origins) // 2:len(origins) // 2 + m // 2]
    sub = origins[subset], directions[subset], limit[subset]
    for side in SIDES:
        lo, hi = grid_boxes(side)
        geometry = DomainGeometry(lo, hi, np.ones(len(lo), bool), origin_bound=3.0)
        t_cross, found = best_of(plan["repeat"],
                                 lambda g=geometry: g.crossings(origins, directions, limit))
        crossed = len(found[0]) / len(origins)
        t_walk, (calls, ray_calls) = best_of(
            plan["repeat"], lambda g=geometry: walk(g, origins, directions, limit))
        t_loop, old = best_of(max(1, plan["repeat"] - 2),
                              lambda g=geometry: crossings_by_loop(g, *sub))
        t_sub, new = best_of(plan["repeat"], lambda g=geometry: g.crossings(*sub))
        assert all(np.array_equal(a, b) for a, b in zip(new, old, strict=True)), "not exact"
        geometry.tree.compiled = False  # the numpy walks, on the same rays
        t_np_cross, np_found = best_of(plan["repeat"],
                                       lambda g=geometry: g.crossings(origins, directions, limit))
        t_np_walk, (_, np_ray_calls) = best_of(
            plan["repeat"], lambda g=geometry: walk(g, origins, directions, limit))
        geometry.tree.compiled = True
        assert all(np.array_equal(a, b) for a, b in zip(found, np_found, strict=True))
        assert np_ray_calls == ray_calls
        r = {"domains": len(lo), "levels": geometry.tree.height,
             "crossed": crossed, "cross_ray": t_cross / len(origins) * 1e6,
             "walk_call": t_walk / ray_calls * 1e6, "walk_ray": t_walk / len(origins) * 1e6,
             "loop_ray": t_loop / len(subset) * 1e6, "sub_ray": t_sub / len(subset) * 1e6,
             "np_cross_ray": t_np_cross / len(origins) * 1e6,
             "np_walk_call": t_np_walk / ray_calls * 1e6}
        r["per_crossed"] = r["cross_ray"] / crossed
        rows[len(lo)] = r
        print(f"| {r['domains']:,} | {r['levels']} | {crossed:.2f} | {r['cross_ray']:.2f} "
              f"| {r['per_crossed']:.3f} | {r['walk_call']:.2f} | {r['walk_ray']:.2f} "
              f"| {r['loop_ray']:.2f} | {r['loop_ray'] / r['sub_ray']:.1f} "
              f"| {r['np_cross_ray']:.2f} | {r['np_walk_call']:.2f} |", flush=True)
    first, last = rows[SIDES[0] ** 3], rows[SIDES[-1] ** 3]
    print(f"\ncrossed_ratio={last['crossed'] / first['crossed']:.2f} "
          f"(domains crossed per ray, {last['domains']:,} vs {first['domains']})")
    print(f"per_ray_scaling={last['cross_ray'] / first['cross_ray']:.2f} "
          f"(crossings us/ray; the loop's: {last['loop_ray'] / first['loop_ray']:.1f})")
    print(f"walk_call_scaling={last['walk_call'] / first['walk_call']:.2f} "
          f"(next_domain us per call and ray)")
    speedups = " / ".join(f"{rows[s ** 3]['np_cross_ray'] / rows[s ** 3]['cross_ray']:.2f}"
                          for s in SIDES)
    walk_speedups = " / ".join(f"{rows[s ** 3]['np_walk_call'] / rows[s ** 3]['walk_call']:.2f}"
                               for s in SIDES)
    print(f"compiled_speedup_crossings={speedups} (numpy walk / compiled walk, "
          f"{' / '.join(f'{s ** 3:,}' for s in SIDES)} domains)")
    print(f"compiled_speedup_walk={walk_speedups}")
    print(f"domain_scaling={last['per_crossed'] / first['per_crossed']:.2f}")


if __name__ == "__main__":
    main()
