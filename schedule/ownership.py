"""Which node owns which domain, and which node starts which paths or tiles: fixed
assignments made once per job (the temporal scheduler's per-frame
assignment is ``schedule.temporal``'s)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np


def round_robin_owners(n_domains: int, size: int) -> np.ndarray:
    """(D,) owning rank of each domain: domain d goes to node d mod P (Navrátil's static
    domain schedule, and the Galaxy-style ``async`` baseline)."""
    return np.arange(n_domains) % size


def zorder_owners(lo: np.ndarray, hi: np.ndarray, size: int,
                  weights: np.ndarray | None = None) -> np.ndarray:
    """(D,) owner of each domain: domains sorted along the Morton curve of their box centres
    ((D, 3) ``lo``, ``hi``), cut into ``size`` contiguous runs (spatially compact groups per
    node, as SpRay's in-situ schedule assigns them): of equal counts, or, with ``weights``
    ((D,) non-negative integers), of equal summed weight as whole domains allow (a domain
    goes to the node whose share holds the middle of its weight; one heavier than a node's
    share can leave a node none). Integers, so every node computes the same runs."""
    center = (lo + hi) / 2.0
    span = np.maximum(center.max(axis=0) - center.min(axis=0), 1e-300)
    grid = np.clip(((center - center.min(axis=0)) / span * 1023).astype(np.uint64), 0, 1023)
    code = np.zeros(len(lo), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((grid[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    order = np.argsort(code, kind="stable")
    owner = np.empty(len(lo), np.int64)
    if weights is None:
        owner[order] = np.arange(len(lo)) * size // max(len(lo), 1)
        return owner
    weight = np.asarray(weights, np.int64)[order]
    if len(weight) and weight.min() < 0:
        raise ValueError("zorder_owners: weights must be non-negative")
    total = max(int(weight.sum()), 1)
    middle = 2 * (np.cumsum(weight) - weight) + weight  # twice each domain's middle
    owner[order] = np.minimum(middle * size // (2 * total), size - 1)
    return owner


#: Weight of a domain in ``insitu_owners`` beside its triangles: an empty domain's runs of
#: the curve still go somewhere, and a store of empty domains is cut by count.
INSITU_DOMAIN_WEIGHT = 1


def insitu_owners(lo: np.ndarray, hi: np.ndarray, triangles, size: int) -> np.ndarray:
    """(D,) owner of each domain for ``spec-insitu``: z-order runs of equal triangles
    (``zorder_owners``' weights: each domain's (D,) ``triangles`` + ``INSITU_DOMAIN_WEIGHT``).

    Runs of equal counts (until session 51) gave the node holding the dense part of the data
    the most rays to trace as well as the most bytes to hold: replayed on the 1,439-domain
    cosmology store at 4,096 paths a node, the frame took 0.300 / 0.627 / 1.437 s on 64 /
    256 / 1,024 nodes by count, 0.260 / 0.544 / 1.185 s by triangles (the camera rays'
    crossings as the weight: 0.257 / 0.533 / 1.210 s, and it would move the data with the
    camera). Rays end on surfaces, so triangles follow the work without the camera, and a
    node's bytes are balanced too (what ``--memory-limit`` checks)."""
    weights = np.asarray(triangles, np.int64) + INSITU_DOMAIN_WEIGHT
    return zorder_owners(lo, hi, size, weights)


@dataclass(frozen=True)
class Holders:
    """The nodes holding each domain in situ: its owner first, then, for the domains crossed
    most, extra holders (``insitu_holders``). Domain d's holders are
    ``nodes[first[d]:first[d + 1]]``.

    Parameters
    ----------
    first : (D + 1,) int64 offsets into ``nodes``.
    nodes : (H,) int64 ranks, H >= D.
    """

    first: np.ndarray
    nodes: np.ndarray

    @classmethod
    def owned(cls, owner: np.ndarray) -> Holders:
        """Each domain held by its owner alone ((D,) ``owner``)."""
        owner = np.asarray(owner, np.int64)
        return cls(np.arange(len(owner) + 1, dtype=np.int64), owner.copy())

    @property
    def owner(self) -> np.ndarray:
        """(D,) each domain's owner."""
        return self.nodes[self.first[:-1]]

    @property
    def count(self) -> np.ndarray:
        """(D,) how many nodes hold each domain."""
        return np.diff(self.first)

    def destination(self, domain: np.ndarray, path: np.ndarray) -> np.ndarray:
        """(n,) the node that traces path ``path``'s copy in ``domain`` ((n,) each): holder
        ``path mod k`` of the domain's k, so each (path, domain) is traced by one node and a
        replicated domain's paths are dealt evenly among its holders."""
        domain = np.asarray(domain, np.int64)
        return self.nodes[self.first[domain] + np.asarray(path, np.int64) % self.count[domain]]

    def held_by(self, rank: int) -> np.ndarray:
        """Sorted ids of the domains ``rank`` holds."""
        domain = np.repeat(np.arange(len(self.first) - 1), self.count)
        return np.unique(domain[self.nodes == rank])


def insitu_holders(owner: np.ndarray, weights: np.ndarray, size: int,
                   footprints: np.ndarray) -> Holders:
    """``spec-insitu``'s holders: each domain's owner, and for a domain whose ``weights``
    ((D,) non-negative integers, the crossings expected there) reach k >= 2 node shares
    (k = floor(w_d P / W)), k - 1 more, each the node then least loaded by weight (ties to
    the lower rank) among those it leaves holding no more bytes (``footprints``: (D,)
    integers) than the node that owns the most, the domain's weight split evenly among its
    holders. Domains are taken heaviest first (ties to the lower id). Integer weights and
    float64 sums in a fixed order, so every node computes the same holders
    (``actors/insitu.py``, over ``spec_insitu.camera_crossings``).

    Why: with one holder a domain, the node owning the domain most lines cross traces its
    copies and holds the rays its hits spawn, work that grows with P while a node's share
    does not (issue 38: at 1,024 nodes 0.72 % of all copies, 7.4 node shares, and 10.6× the
    mean node's copies to send). Its data is then on more than one node, which SpRay's in
    situ never does (each domain stays where it was made), so it costs memory; bounded by
    the most any node owns, it costs no node more than ``--memory-limit``'s check of the
    owners (``preflight.check_owned_fit``) allowed for.
    """
    owner = np.asarray(owner, np.int64)
    weight = np.asarray(weights, np.int64)
    total = int(weight.sum())
    if size < 2 or total <= 0:
        return Holders.owned(owner)
    k = np.clip(weight * size // total, 1, size)
    replicated = [int(d) for d in np.argsort(-weight, kind="stable") if k[d] > 1]
    if not replicated:
        return Holders.owned(owner)
    # float64 sums in a fixed order: the same bits on every node
    load = np.bincount(owner, weights=weight.astype(np.float64), minlength=size)
    footprint = np.asarray(footprints, np.int64)
    held = np.bincount(owner, weights=footprint, minlength=size).astype(np.int64)
    cap = held.max()
    ranks = np.arange(size)
    extra: dict[int, np.ndarray] = {}
    for d in replicated:  # once a frame, over the few domains heavier than two shares
        order = np.lexsort((ranks, load))
        room = held[order] + footprint[d] <= cap
        chosen = order[room & (order != owner[d])][: k[d] - 1]
        if not len(chosen):
            continue
        held[chosen] += footprint[d]
        k[d] = len(chosen) + 1
        share = float(weight[d]) / float(k[d])
        load[owner[d]] -= float(weight[d]) - share
        load[chosen] += share
        extra[d] = chosen
    count = np.ones(len(owner), np.int64)
    for d, chosen in extra.items():
        count[d] += len(chosen)
    first = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
    nodes = np.empty(first[-1], np.int64)
    nodes[first[:-1]] = owner
    for d, chosen in extra.items():
        nodes[first[d] + 1:first[d + 1]] = chosen
    return Holders(first, nodes)


#: Image-plane blocks a sort-first node is dealt where the frame has paths enough
#: (``sort_first_block``): 1, a band of the image a node. More blocks spread a node's share
#: over the image, so the shares cost alike, but each node then meets most of the domains:
#: measured on real nodes (session 42, 4 blocks against 1, medians of 3), the turbine scan
#: on 8 processes 0.483 against 0.316 s (61 against 33 loads), rm 128³ out of core 5.2
#: against 2.7 s (852 against 491 loads); only the replay's core-per-node cluster at 4,096
#: paths a node gains (weak efficiency 0.90-1.01 against 0.60-0.76 on 4 to 256 nodes for
#: bands of equal paths, ``bench/replay_variants.py`` section 4; ``image``'s bands cut by
#: cost since session 49 reach 0.97, each still one run of the image, the loads over all
#: nodes 1.4 times equal bands'). A knob for that comparison, 1 in the product.
BLOCKS_PER_NODE = 1
#: Fewest paths in a block where a node is dealt several.
MIN_BLOCK_PATHS = 1024


def sort_first_block(total: int, tile: int, size: int) -> int:
    """Paths in each image-plane block of a sort-first frame of ``total`` paths over ``size``
    nodes, ``tile`` at most in flight on a node: on one node, the tile; on several, the
    frame cut into ``k`` blocks a node, ``k`` as many as keep ``MIN_BLOCK_PATHS`` a block, 1
    to ``BLOCKS_PER_NODE`` (so every node gets blocks, and as many), none over the tile.
    With ``BLOCKS_PER_NODE`` 1: a band a node, or tiles round robin where the frame holds
    more than a tile a node (until session 42 always tiles, which left every node but one
    idle on a frame of fewer paths than the tile)."""
    total, tile = max(int(total), 1), max(int(tile), 1)
    if size <= 1:
        return min(tile, total)
    k = min(max(total // (size * MIN_BLOCK_PATHS), 1), BLOCKS_PER_NODE)
    return max(1, min(tile, -(-total // (size * k))))


def sort_first_tile_paths(total: int, tile: int, rank: int, size: int,
                          weight_before: Callable[[np.ndarray], np.ndarray] | None = None
                          ) -> Iterator[np.ndarray]:
    """The tiles node ``rank`` of ``size`` renders under the static image-plane schedule
    (Navrátil et al. 2012, Fig. 3), each (n,) int64 path ids ascending: the frame of
    ``total`` paths is cut into blocks of ``sort_first_block`` paths dealt round robin
    (blocks rank, rank + P, rank + 2P, ...), and the node's blocks are grouped in order into
    tiles of at most ``tile`` paths (at least one block each), made one at a time. On one
    node: the tiles of ``tile`` paths, in order. Over the ranks every path is in exactly one
    tile.

    Where a node's share is one band of the frame (``sort_first_block``) and
    ``weight_before`` is given, the bands are cut at equal estimated cost rather than equal
    paths (``weighted_band_cuts``), each cut into tiles of at most ``tile`` paths: equal
    bands left the nodes whose band is mostly background idle while the ones on the data
    worked (replayed weak efficiency 0.58-0.73 on 4 to 1,024 nodes, bench/README).
    """
    block = sort_first_block(total, tile, size)
    if weight_before is not None and size > 1 and block == -(-max(total, 1) // size):
        cuts = weighted_band_cuts(weight_before, total, size)
        first, stop = int(cuts[rank]), int(cuts[rank + 1])
        for start in range(first, stop, max(int(tile), 1)):
            yield np.arange(start, min(stop, start + int(tile)), dtype=np.int64)
        return
    firsts = np.arange(rank * block, total, size * block, dtype=np.int64)
    together = max(1, tile // block)
    for group in range(0, len(firsts), together):
        starts = firsts[group:group + together]
        ids = (starts[:, None] + np.arange(block, dtype=np.int64)[None, :]).ravel()
        yield ids[ids < total]


def sort_first_sweep_paths(passes, tile: int, rank: int, size: int,
                           weight_before_pass: Callable[[int], Callable | None] | None = None
                           ) -> Iterator[np.ndarray]:
    """The tiles node ``rank`` of ``size`` renders of a sweep of several passes, each (n,)
    int64 path ids ascending, the sweep's paths numbered pass after pass (``passes``: (K,)
    paths of each): the node's share of each pass, as ``sort_first_tile_paths`` cuts that
    pass alone (with ``weight_before_pass(k)`` its ``weight_before``), run on from one pass
    into the next in tiles of at most ``tile`` paths, so a tile's domain loads serve several
    passes. Over the ranks every path is in exactly one tile; on one node the tiles are
    ``sort_first_tile_paths``' of the whole sweep.

    Cut as one frame, a sweep gave a node a band of the sweep's path ids, not of the image:
    on 2 nodes one traced the first passes' whole images and the other the last pass's,
    each crossing every domain the image shows, where a pass alone gives each its half of
    the image (1.46-1.51x the loads of one pass at a quarter cached, ``bench/ooc.py
    --quick``'s ``passes_kept_loads_ratio_nodes``). Here a node's share of every pass is
    the same part of the image.
    """
    tile = max(int(tile), 1)
    held: list[np.ndarray] = []
    count = 0
    offset = 0
    for k, paths in enumerate(passes):
        before = None if weight_before_pass is None else weight_before_pass(k)
        for ids in sort_first_tile_paths(int(paths), tile, rank, size, before):
            ids = ids + offset
            while len(ids):
                take = ids[:tile - count]
                held.append(take)
                count += len(take)
                ids = ids[len(take):]
                if count == tile:
                    yield np.concatenate(held)
                    held, count = [], 0
        offset += int(paths)
    if count:
        yield np.concatenate(held)


def weighted_band_cuts(weight_before: Callable[[np.ndarray], np.ndarray], total: int,
                       size: int) -> np.ndarray:
    """(size + 1,) int64: where each node's band of a frame of ``total`` paths starts (and,
    last, ``total``), so that the bands' estimated costs are as equal as whole paths allow.

    ``weight_before(ids)`` gives, for (n,) int64 path ids in 0 .. ``total``, (n,) int64 the
    summed integer weight of the paths before each (non-decreasing, 0 at 0). Node k's band
    starts at the first path whose weight before reaches k / ``size`` of the frame's: found
    by bisection over every cut at once (log2 ``total`` calls). Integer weights make every
    node compute the same cuts, so every path is in exactly one band.
    """
    total, size = max(int(total), 0), max(int(size), 1)
    whole = int(weight_before(np.array([total], np.int64))[0])
    target = whole * np.arange(1, size, dtype=np.int64) // size
    lo = np.zeros(size - 1, np.int64)
    hi = np.full(size - 1, total, np.int64)
    while (lo < hi).any():
        mid = (lo + hi) // 2
        reached = weight_before(mid) >= target
        hi = np.where(reached, mid, hi)
        lo = np.where(reached, lo, mid + 1)
    return np.concatenate([[0], lo, [total]]).astype(np.int64)


def interleaved_paths(n_paths: int, rank: int, size: int) -> np.ndarray:
    """(n,) bool: the paths of a tile whose camera rays node ``rank`` makes, every P-th one
    (each node starts an equal, image-wide share)."""
    return np.arange(n_paths) % size == rank
