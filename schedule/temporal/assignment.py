"""Domain assignment of the temporal-coherence scheduler (Xu et al., TVCG 2022, §5.1): which
node owns which domain and renders which screen tile. ``assign_temporal`` is Algorithm 1;
``sequential_owners`` and ``spatial_owners`` are the comparators of the paper's Table 2;
``eye_domain`` is the box every node may load (it is replicated)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from vastray.schedule.registry import ASSIGNMENTS
from vastray.schedule.temporal.screen import projected_rects, screen_tiles
from vastray.schedule.temporal.stats import FrameStats

if TYPE_CHECKING:
    from vastray.render.camera import Camera

__all__ = ["ASSIGNMENTS", "Assignment", "assign_affinity", "assign_frame", "assign_temporal",
           "eye_domain", "groups_fit", "sequential_owners", "spatial_owners"]

# Domain assignments (``ASSIGNMENTS``, named in ``schedule.registry``): Table 2's three
# (``paper`` is Algorithm 1), Algorithm 1 with cache affinity, and the choice between the
# static groups and that by whether they fit the caches.


def eye_domain(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray, nonempty: np.ndarray) -> int | None:
    """The non-empty box that contains the eye (boundaries included), lowest id; None if none.

    Parameters
    ----------
    eye : (3,) camera position.
    lo, hi : (D, 3) domain boxes.
    nonempty : (D,) bool.
    """
    eye = np.asarray(eye, dtype=np.float64)
    inside = np.asarray(nonempty, dtype=bool) & np.all((lo <= eye) & (eye <= hi), axis=1)
    hits = np.flatnonzero(inside)
    return int(hits[0]) if len(hits) else None

@dataclass
class Assignment:
    """Which node owns which domain and renders which screen tile.

    Attributes
    ----------
    owner : (D,) int64 node of each domain, -1 for empty domains. The replicated domain has an
        owner too (a routing default; ``assign_temporal`` gives it to the fastest-loading node).
    tiles : (P, 4) int64 screen tile ``(x0, y0, x1, y1)`` of each node (its camera rays).
    replicated : the domain containing the eye, which every node may load, or None.
    """

    owner: np.ndarray
    tiles: np.ndarray
    replicated: int | None = None

    def owns(self, rank: int) -> np.ndarray:
        """(D,) bool, the local domains of node ``rank`` (the replicated domain included)."""
        local = np.asarray(self.owner) == rank
        if self.replicated is not None:
            local = local.copy()
            local[self.replicated] = True
        return local

    def routes_from(self, rank: int) -> np.ndarray:
        """(D,) the node node ``rank`` sends each domain's rays to: the owner, except that it
        keeps the rays of the replicated domain and of empty domains (no owner)."""
        owner = np.where(np.asarray(self.owner) >= 0, self.owner, rank)
        if self.replicated is not None:  # the eye's domain: every node may load it
            owner[self.replicated] = rank
        return owner


def _overlap(tiles: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """(n, D) float64 area of the intersection of tile i with rectangle d."""
    t = np.asarray(tiles, dtype=np.float64)[:, None, :]
    r = np.asarray(rects, dtype=np.float64)[None, :, :]
    w = np.minimum(t[..., 2], r[..., 2]) - np.maximum(t[..., 0], r[..., 0])
    h = np.minimum(t[..., 3], r[..., 3]) - np.maximum(t[..., 1], r[..., 1])
    return np.maximum(w, 0.0) * np.maximum(h, 0.0)


def _seeds(overlap: np.ndarray, sent_out: np.ndarray, eye: int | None) -> list[list[int]]:
    """Step 1: the initial domains of each unit (indices into the candidate domains).

    overlap : (n, m) tile/domain overlap areas; sent_out : (m,) s(A) of the candidates;
    eye : index of the eye domain among the candidates, or None.
    """
    n, m = overlap.shape
    if eye is not None:
        # The eye domain seeds every unit; the n other domains with the most rays sent seed
        # units 0..n-1 in turn.
        others = np.delete(np.arange(m, dtype=np.int64), eye)
        ranked = others[np.argsort(-sent_out[others], kind="stable")][:n]
        return [[eye] + ([int(ranked[u])] if u < len(ranked) else []) for u in range(n)]
    if m == 0:
        return [[] for _ in range(n)]
    best_d = np.argmax(overlap, axis=1)  # ties -> lower id
    best_a = overlap[np.arange(n), best_d]
    seeds: list[list[int]] = [[] for _ in range(n)]
    taken = np.zeros(m, dtype=bool)
    # A domain that is the best of several tiles stays with the tile that overlaps it most
    # (ties -> lower tile index) ...
    order = np.lexsort((np.arange(n), -best_a))
    losers = []
    for u in order:
        if taken[best_d[u]]:
            losers.append(int(u))
        else:
            taken[best_d[u]] = True
            seeds[u] = [int(best_d[u])]
    # ... and the other tiles, in decreasing order of that overlap, take their best untaken one.
    for u in losers:
        if taken.all():
            break
        d = int(np.argmax(np.where(taken, -np.inf, overlap[u])))
        taken[d] = True
        seeds[u] = [d]
    return seeds


def assign_temporal(tiles: np.ndarray, rects: np.ndarray, sent: np.ndarray,
                    domain_bytes: np.ndarray, node_speed: np.ndarray, nonempty: np.ndarray,
                    eye: int | None = None) -> Assignment:
    """Algorithm 1 (§5.1): temporal-coherence domain assignment for n = P nodes.

    1. **Seeds.** Unit i takes tile i. Without ``eye``, its seed is the non-empty domain whose
       projected rectangle overlaps tile i most (ties -> lower id); a domain that is the best of
       several tiles stays with the tile that overlaps it most (ties -> lower tile), and the
       other tiles, in decreasing order of that overlap, take their best untaken domain
       (note S3, reading). With ``eye``, that domain seeds *every* unit (it is replicated) and
       the n other non-empty domains with the largest s(A) = sum_B s(A, B) seed units 0..n-1 in
       turn (ties -> lower id).
    2. **Grow.** While non-empty domains are unassigned, the unit U with the fewest domains
       (ties -> lower index) takes the unassigned domain D with the LOWEST
       trans(D, U) = sum_{A in U} [s(A, D) + s(D, A)] (ties -> lower id; the replicated domain
       counts as a member of every unit). A (units, D) transmission matrix is updated
       incrementally, so each step is O(D).
    3. **Bind.** Nodes sorted by ``node_speed`` descending get the units sorted by their total
       ``domain_bytes`` descending (stable sorts: ties -> lower id).

    With ``sent`` all zero (frame 0) the growth is a round robin over the units in domain order,
    which is still balanced.

    Parameters
    ----------
    tiles : (P, 4) int screen tiles, e.g. ``screen_tiles(width, height, P)``.
    rects : (D, 4) float projected rectangles, e.g. ``projected_rects(camera, lo, hi)``.
    sent : (D, D) s(A, B) of the previous frame (``FrameStats.sent``); the diagonal is ignored.
    domain_bytes : (D,) V(d), bytes of each domain on storage.
    node_speed : (P,) S_LOAD(n) (``FrameStats.s_load()``).
    nonempty : (D,) bool; empty domains are left out (owner -1).
    eye : id of the non-empty domain containing the eye (``eye_domain``), or None.

    Returns
    -------
    Assignment with ``owner`` (D,), ``tiles`` (P, 4) (tile of each node) and ``replicated`` =
    ``eye``. The replicated domain's ``owner`` is the fastest-loading node.
    """
    tiles = np.asarray(tiles, dtype=np.int64).reshape(-1, 4)
    n = len(tiles)
    node_speed = np.asarray(node_speed, dtype=np.float64).reshape(-1)
    if len(node_speed) != n:
        raise ValueError(f"{n} tiles but {len(node_speed)} node speeds")
    if n < 1:
        raise ValueError("assign_temporal needs at least one node")
    nonempty = np.asarray(nonempty, dtype=bool)
    n_domains = len(nonempty)
    domain_bytes = np.asarray(domain_bytes, dtype=np.float64).reshape(-1)
    rects = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    sent = np.asarray(sent)
    if sent.shape != (n_domains, n_domains) or len(rects) != n_domains or len(domain_bytes) != n_domains:
        raise ValueError(f"sent {sent.shape}, rects ({len(rects)}) and domain_bytes "
                         f"({len(domain_bytes)}) must match {n_domains} domains")
    cand = np.flatnonzero(nonempty)  # candidate domain ids; work in candidate indices below
    m = len(cand)
    eye_c = None
    if eye is not None:
        if not (0 <= eye < n_domains and nonempty[eye]):
            raise ValueError(f"eye domain {eye} is not a non-empty domain")
        eye_c = int(np.searchsorted(cand, eye))

    def sym_row(c: int) -> np.ndarray:
        """(m,) s(A, D) + s(D, A) for the domain A = cand[c] and every candidate D."""
        a = cand[c]
        return (sent[a, cand] + sent[cand, a]).astype(np.float64)

    sent_out = (sent.sum(axis=1) - np.diagonal(sent))[cand]  # s(A)
    seeds = _seeds(_overlap(tiles, rects[cand]), sent_out, eye_c)

    # Step 2: grow. trans[u, c] = sum over members A of u of s(A, c) + s(c, A); +inf once taken.
    unit_of = np.full(m, -1, dtype=np.int64)
    trans = np.zeros((n, m), dtype=np.float64)
    sizes = np.zeros(n, dtype=np.int64)
    eye_row = sym_row(eye_c) if eye_c is not None else None
    for u, members in enumerate(seeds):
        for c in members:
            trans[u] += eye_row if c == eye_c else sym_row(c)
            if c != eye_c:
                unit_of[c] = u
        sizes[u] = len(members)
    taken = unit_of >= 0
    if eye_c is not None:
        taken[eye_c] = True
    trans[:, taken] = np.inf
    for _ in range(int(np.count_nonzero(~taken))):
        u = int(np.argmin(sizes))
        c = int(np.argmin(trans[u]))
        unit_of[c] = u
        sizes[u] += 1
        trans[:, c] = np.inf
        trans[u] += sym_row(c)

    # Step 3: bind units (by bytes, descending) to nodes (by S_LOAD, descending).
    unit_bytes = np.bincount(unit_of[unit_of >= 0], weights=domain_bytes[cand][unit_of >= 0],
                             minlength=n)
    if eye_c is not None:
        unit_bytes = unit_bytes + domain_bytes[eye]
    node_order = np.argsort(-node_speed, kind="stable")
    unit_order = np.argsort(-unit_bytes, kind="stable")
    node_of_unit = np.empty(n, dtype=np.int64)
    node_of_unit[unit_order] = node_order
    owner = np.full(n_domains, -1, dtype=np.int64)
    owner[cand] = np.where(unit_of >= 0, node_of_unit[np.maximum(unit_of, 0)], -1)
    if eye is not None:
        owner[eye] = node_order[0]
    node_tiles = np.empty_like(tiles)
    node_tiles[node_of_unit] = tiles
    return Assignment(owner, node_tiles, None if eye is None else int(eye))


def _bind_to_holders(owner: np.ndarray, tiles: np.ndarray, held: np.ndarray,
                     domain_bytes: np.ndarray, node_speed: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Re-bind Algorithm 1's units to the nodes that already hold most of them.

    Unit u is the group ``owner == u``. Binding it to node n saves the loads of the domains
    of u that n holds, sum V(d) / S_LOAD(n) seconds. The pairs are taken greedily, the largest
    saving first (ties -> lower unit, then lower node); units that no free node holds anything
    of keep Algorithm 1's node if it is free, else take the free nodes in rank order.

    Returns
    -------
    owner : (D,) int64 with units renamed to their nodes (-1 kept); tiles : (P, 4) per node.
    """
    p = len(tiles)
    member = owner >= 0
    # saving[unit, node]: the load time of the unit's domains that the node holds
    load_s = domain_bytes[member, None] / node_speed[None, :]  # (m, P)
    saving = np.zeros((p, p))
    np.add.at(saving, owner[member], held[:, member].T * load_s)
    node_of = np.full(p, -1, np.int64)
    taken = np.zeros(p, bool)
    units, nodes = np.nonzero(saving > 0)
    for k in np.lexsort((nodes, units, -saving[units, nodes])):
        u, n = units[k], nodes[k]
        if node_of[u] < 0 and not taken[n]:
            node_of[u], taken[n] = n, True
    for u in np.flatnonzero(node_of < 0):  # the rest: Algorithm 1's node, else the first free
        n = u if not taken[u] else int(np.flatnonzero(~taken)[0])
        node_of[u], taken[n] = n, True
    bound = np.where(member, node_of[np.maximum(owner, 0)], -1)
    node_tiles = np.empty_like(tiles)
    node_tiles[node_of] = tiles
    return bound, node_tiles


def assign_affinity(paper: Assignment, held: np.ndarray, sent: np.ndarray,
                    domain_bytes: np.ndarray, node_speed: np.ndarray, rays_per_reload: float
                    ) -> Assignment:
    """Algorithm 1 with the cost of moving a domain counted: what a node holds stays its own
    unless Algorithm 1's placement is predicted to save more than the load it costs.

    1. **Bind by holding.** Algorithm 1's units (tile and group) go to the nodes that hold
       most of them (``_bind_to_holders``), in place of its step 3 (bytes to load speed).
    2. **Hysteresis.** A domain d held by node h at the last frame's end but placed on node
       o != h moves to o only if Algorithm 1's reason for moving it outweighs the load the move
       costs. Algorithm 1 places d where it trades the fewest rays inside its group;
       keeping d in h's group instead adds trans(d, h) - trans(d, o) rays traded inside a
       group (``trans`` as in Algorithm 1, over the groups after step 1), which last frame
       cost a reload per ``rays_per_reload`` rays: the predicted gain of the move is
       (trans(d, h) - trans(d, o)) / rays_per_reload loads of d on h,
       x V(d) / S_LOAD(h) seconds, and its cost one load of d on o, V(d) / S_LOAD(o). A
       domain several nodes hold (none, in a temporal run, but the replicated eye domain) is
       counted for the fastest-loading of them; the replicated domain itself never moves.

    A greedy with hysteresis rather than a min-cost assignment: the gain is an estimate from
    one frame, the only exact part is the load a move costs, and the greedy keeps Algorithm
    1's grouping everywhere the caches hold nothing (DESIGN.md, "Temporal assignment with
    cache affinity"). Unit sizes may differ by up to a cache's worth of domains.

    Parameters
    ----------
    paper : Algorithm 1's assignment (``assign_temporal``) for this frame.
    held : (P, D) the domains each node held at the last frame's end (``FrameStats.held``).
    sent : (D, D) s(A, B) of the last frame.
    domain_bytes : (D,) V(d); node_speed : (P,) S_LOAD(n).
    rays_per_reload : rays processed per reload in the last frame (loads of a domain beyond
        its first; inf: no reloads, so no move pays).

    Returns
    -------
    Assignment with the same tiles as ``paper`` (re-bound) and ``replicated``.
    """
    held = np.asarray(held) > 0
    if paper.replicated is not None:  # any node may load it: holding it binds nothing
        held = held.copy()
        held[:, paper.replicated] = False
    speed = np.asarray(node_speed, dtype=np.float64)
    volume = np.asarray(domain_bytes, dtype=np.float64)
    owner, tiles = _bind_to_holders(np.asarray(paper.owner, np.int64), paper.tiles, held,
                                    volume, speed)
    sym = (np.asarray(sent) + np.asarray(sent).T).astype(np.float64)
    np.fill_diagonal(sym, 0.0)
    member = owner >= 0
    trans = np.zeros((len(tiles), len(owner)))  # trans[n, d]: rays d trades with n's group
    np.add.at(trans, owner[member], sym[member])
    holder = np.argmax(np.where(held, speed[:, None], -np.inf), axis=0)  # fastest holder
    moved = member & held.any(axis=0) & ~held[np.maximum(owner, 0), np.arange(len(owner))]
    d = np.flatnonzero(moved)
    h, o = holder[d], owner[d]
    extra = np.maximum(trans[h, d] - trans[o, d], 0.0)
    gain = extra / max(float(rays_per_reload), 1e-300) * volume[d] / speed[h]
    cost = volume[d] / speed[o]
    keep = d[gain <= cost]
    owner = owner.copy()
    owner[keep] = holder[keep]
    return Assignment(owner, tiles, paper.replicated)


def sequential_owners(n_domains: int, n_nodes: int, nonempty: np.ndarray, width: int,
                      height: int) -> Assignment:
    """Table 2's *sequential* assignment: domain d goes to node d mod n (as vastray's
    ``round_robin_owners``), empty domains to -1; node i renders tile i of
    ``screen_tiles(width, height, n_nodes)``.

    Returns
    -------
    Assignment with ``owner`` (D,) int64, ``tiles`` (P, 4), ``replicated`` None.
    """
    owner = np.arange(int(n_domains), dtype=np.int64) % int(n_nodes)
    owner[~np.asarray(nonempty, dtype=bool)] = -1
    return Assignment(owner, screen_tiles(width, height, n_nodes), None)


def spatial_owners(lo: np.ndarray, hi: np.ndarray, n_nodes: int, nonempty: np.ndarray,
                   width: int, height: int) -> Assignment:
    """Table 2's *spatial-based* assignment: the non-empty domains sorted along the Morton
    (z-order) curve of their box centres (10 bits per axis over the centres' bounding box, as
    vastray's ``zorder_owners``), cut into ``n_nodes`` contiguous runs whose sizes differ by at
    most 1; empty domains get -1. Node i renders tile i of ``screen_tiles(width, height, n)``.

    Parameters
    ----------
    lo, hi : (D, 3) domain boxes.

    Returns
    -------
    Assignment with ``owner`` (D,) int64, ``tiles`` (P, 4), ``replicated`` None.
    """
    nonempty = np.asarray(nonempty, dtype=bool)
    owner = np.full(len(nonempty), -1, dtype=np.int64)
    cand = np.flatnonzero(nonempty)
    if len(cand):
        center = (np.asarray(lo, np.float64)[cand] + np.asarray(hi, np.float64)[cand]) / 2.0
        low = center.min(axis=0)
        span = np.maximum(center.max(axis=0) - low, 1e-300)
        grid = np.clip(((center - low) / span * 1023).astype(np.uint64), 0, 1023)
        code = np.zeros(len(cand), np.uint64)
        for bit in range(10):
            for axis in range(3):
                code |= ((grid[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
        order = np.argsort(code, kind="stable")
        owner[cand[order]] = np.arange(len(cand)) * int(n_nodes) // len(cand)
    return Assignment(owner, screen_tiles(width, height, n_nodes), None)


def groups_fit(assignment: Assignment, capacity: int | None) -> bool:
    """Whether every node's group (its own domains, the replicated one included) fits a cache
    of ``capacity`` domains (None: no bound)."""
    if capacity is None:
        return True
    owner = np.asarray(assignment.owner, np.int64)
    sizes = np.bincount(owner[owner >= 0], minlength=len(assignment.tiles))
    if assignment.replicated is not None:  # every node may load it; its owner counted it
        sizes = sizes + 1
        sizes[owner[assignment.replicated]] -= 1
    return int(sizes.max(initial=0)) <= int(capacity)


def assign_frame(kind: str, camera: Camera, lo: np.ndarray, hi: np.ndarray, nonempty: np.ndarray,
                 domain_bytes: np.ndarray, width: int, height: int, size: int,
                 previous: FrameStats | None, capacity: int | None = None) -> Assignment:
    """A frame's assignment units of kind ``kind`` (one of ``ASSIGNMENTS``); the same on every
    node, since it depends only on the domains, the camera, the previous frame's summed
    statistics and the caches' capacity (the job's, the same on every node). Frame 0
    (``previous`` None) has no statistics to plan from: ``paper``, ``affinity`` and ``fit``
    fall back to ``spatial`` there.

    ``fit`` keeps the static ``spatial`` groups while each node's group fits its cache of
    ``capacity`` domains (then nothing is ever loaded twice, and Algorithm 1's splitting of
    domains that trade rays only sends more rays between nodes: 0.84-0.97 of the cache-aware
    baseline's speed in ``bench/temporal.py --fig7`` from 2 to 16 slots a node), and is
    ``affinity`` where a group does not fit (where Algorithm 1's groups, keeping domains
    that trade rays apart, save loads: 1.46x the baseline at one slot).

    Parameters
    ----------
    camera : this frame's ``Camera``.
    lo, hi : (D, 3) domain boxes; nonempty : (D,) bool; domain_bytes : (D,) V(d).
    width, height : image size in pixels; size : P, the number of nodes.
    previous : the previous frame's statistics summed over nodes, or None.
    capacity : domains a node's cache holds (``fit`` only; None: unbounded).
    """
    if kind == "sequential":
        return sequential_owners(len(lo), size, nonempty, width, height)
    if kind not in ASSIGNMENTS:
        raise ValueError(f"unknown assignment {kind!r}; expected one of {ASSIGNMENTS}")
    if kind == "spatial" or previous is None:
        return spatial_owners(lo, hi, size, nonempty, width, height)
    if kind == "fit":
        static = spatial_owners(lo, hi, size, nonempty, width, height)
        if groups_fit(static, capacity):
            return static
    paper = assign_temporal(screen_tiles(width, height, size), projected_rects(camera, lo, hi),
                            previous.sent, domain_bytes, previous.s_load(), nonempty,
                            eye_domain(camera.position, lo, hi, nonempty))
    if kind == "paper":
        return paper
    # a domain's first load in a frame is needed wherever it goes; the reloads are what
    # rays traded inside a group cost (none when the caches hold every group)
    reloads = int(np.maximum(previous.loads - 1, 0).sum())
    rays_per_reload = previous.proc_rays.sum() / reloads if reloads else np.inf
    return assign_affinity(paper, previous.held, previous.sent, domain_bytes,
                           previous.s_load(), rays_per_reload)
