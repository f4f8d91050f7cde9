"""The per-domain loops that ``DomainGeometry``'s box-tree walks replaced: every domain box
tested against every ray, O(domains x rays). The reference the walks must equal bit for bit
(``tests/test_many_domains.py``) and the baseline of ``bench/domains.py``; not production code."""

from __future__ import annotations

import numpy as np

from vastray.schedule.geometry import DomainGeometry, order_crossings


def _loop_entries(geometry: DomainGeometry, origins, directions):
    """Yield (domain, entry (n,) float32 with inf where the ray misses the box)."""
    slabs = geometry.slabs(origins, directions)
    for d in geometry.ids:
        t0, t1 = slabs.intervals(geometry.lo[d], geometry.hi[d])
        entry = np.maximum(t0, np.float32(0))
        entry[(t0 > t1) | (t1 < 0)] = np.inf
        yield int(d), entry


def next_domain_by_loop(geometry: DomainGeometry, origins, directions, after_t, after_d, limit):
    """``DomainGeometry.next_domain`` by testing every domain box in turn (the former code)."""
    n = len(origins)
    best_d = np.full(n, -1, np.int32)
    best_e = np.full(n, np.inf, np.float32)
    for d, entry in _loop_entries(geometry, origins, directions):
        later = (entry > after_t) | ((entry == after_t) & (d > after_d))
        take = later & (entry < limit) & (entry < best_e)  # ids ascend: ties keep the lower
        best_d[take] = d
        best_e[take] = entry[take]
    return best_d, best_e


def crossings_by_loop(geometry: DomainGeometry, origins, directions, limit):
    """``DomainGeometry.crossings`` by testing every domain box in turn (the former code)."""
    rays, domains, entries = [], [], []
    for d, entry in _loop_entries(geometry, origins, directions):
        rows = np.nonzero(entry < limit)[0]
        rays.append(rows)
        domains.append(np.full(len(rows), d, np.int32))
        entries.append(entry[rows])
    if not rays:
        empty = np.zeros(0, np.int64)
        return empty, empty.astype(np.int32), empty.astype(np.float32), empty.astype(np.int32)
    return order_crossings(np.concatenate(rays), np.concatenate(domains), np.concatenate(entries))
