"""Which node owns which domain, and which node starts which paths or tiles: fixed
assignments made once per job (the temporal scheduler's per-frame
assignment is ``schedule.temporal``'s)."""

from __future__ import annotations

import numpy as np


def round_robin_owners(n_domains: int, size: int) -> np.ndarray:
    """(D,) owning rank of each domain: domain d goes to node d mod P (Navrátil's static
    domain schedule, and the Galaxy-style ``async`` baseline)."""
    return np.arange(n_domains) % size


def zorder_owners(lo: np.ndarray, hi: np.ndarray, size: int) -> np.ndarray:
    """(D,) owner of each domain: domains sorted along the Morton curve of their box centres
    ((D, 3) ``lo``, ``hi``), cut into ``size`` contiguous runs (spatially compact groups per
    node, as SpRay's in-situ schedule assigns them)."""
    center = (lo + hi) / 2.0
    span = np.maximum(center.max(axis=0) - center.min(axis=0), 1e-300)
    grid = np.clip(((center - center.min(axis=0)) / span * 1023).astype(np.uint64), 0, 1023)
    code = np.zeros(len(lo), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((grid[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    order = np.argsort(code, kind="stable")
    owner = np.empty(len(lo), np.int64)
    owner[order] = np.arange(len(lo)) * size // max(len(lo), 1)
    return owner


def sort_first_tiles(total: int, tile: int, rank: int, size: int) -> range:
    """First path ids of the tiles node ``rank`` of ``size`` renders under the static
    image-plane schedule (Navrátil et al. 2012, Fig. 3): of the tiles of ``tile`` paths that
    cover ``total`` paths, tiles rank, rank + P, rank + 2P, ..."""
    return range(rank * tile, total, size * tile)


def interleaved_paths(n_paths: int, rank: int, size: int) -> np.ndarray:
    """(n,) bool: the paths of a tile whose camera rays node ``rank`` makes, every P-th one
    (each node starts an equal, image-wide share)."""
    return np.arange(n_paths) % size == rank
