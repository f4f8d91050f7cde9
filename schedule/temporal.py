"""Temporal-coherence scheduling (Xu et al., TVCG 2022, §4-§5): pure functions, no asyncio.

Frame t uses the counters of frame t-1 (``FrameStats``, SUM-reduced over nodes) twice:

* **Domain assignment** (Algorithm 1, ``assign_temporal``): the image is cut into one screen
  tile per node (``screen_tiles``); each tile's *AssignmentUnit* is seeded with the domain whose
  projected box overlaps the tile most (``projected_rects``); the units then grow, the unit with
  the fewest domains taking the unassigned domain that exchanged the *fewest* rays with it (rays
  between nodes are cheaper than loads, so domains that trade rays go to different nodes); the
  units are bound to nodes, the unit with the most bytes to the node that loads fastest. The
  comparators of the paper's Table 2 are ``sequential_owners`` and ``spatial_owners``.
* **Preload priority** (Eq 1-4, ``priority``): while the active domain renders, every other local
  domain is scored by Eq 1's terms, as the paper's difference
  ``P(n,d) = (1 - Dep'(d)) * (Q_PRED(d)/S_PROC(d) - T_LOAD(n,d))`` (``cost-benefit``) or as
  a ratio, work per second of loading (``cost-rate``, the default: see ``priority``), or by
  one of the Table 2 ablation priorities (``PRIORITIES``). ``best`` is the next active
  domain (d* is picked among the domains still cached once the active one is loaded,
  ``resident_after_load``), ``victim`` the domain to evict.

Readings (implementation note ``shared/notes/temporal-coherence.md``, S12): R(A,B) = s(A,B)/s(A)
(the paper's literal s(A,B)/r(A) behind ``literal=True``); r(A) counts every ray A processes; the
diagonal s(A,A) is ignored everywhere; Eq 4 is guarded; Eq 1 is implemented literally, so when
its bracket is negative (1 - Dep') favours *far* domains (S12.4).

Conventions: D domains, P nodes (= units = tiles); pixel index ``y * width + x`` with row 0 at
the top of the image (``Camera.generate``); tiles and pixel rectangles are ``(x0, y0, x1, y1)``,
half-open; ties go to the lower id everywhere.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from fractions import Fraction
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:
    from vastray.render.camera import Camera

__all__ = [
    "ASSIGNMENTS",
    "PRIORITIES",
    "Assignment",
    "FrameStats",
    "PriorityInputs",
    "assign_temporal",
    "best",
    "bootstrap_priority",
    "dep_prime",
    "eye_domain",
    "load_time",
    "pixel_tiles",
    "potential",
    "priority",
    "projected_rects",
    "resident_after_load",
    "screen_tiles",
    "sequential_owners",
    "spatial_owners",
    "victim",
]

#: Preload priorities: the paper's Table 2 ablation (Eq 1 is "cost-benefit"), Eq 1's terms as
#: a ratio ("cost-rate", ``temporal``'s default) and the queue baseline made cache-aware
#: ("queue+resident"), the strongest baseline of ``bench/temporal.py``.
PRIORITIES = ("queue", "spray", "queue+act", "cost-benefit", "cost-rate", "queue+resident")
#: T_LOAD floor of ``"cost-rate"``, seconds: what activating a resident domain costs (its
#: BVH is built; a queue pop and a dispatch remain). A resident domain outranks a domain that
#: must be loaded unless that one promises more than T_LOAD / RESIDENT_COST_S times the work.
RESIDENT_COST_S = 1e-3
#: Domain assignments of Table 2.
ASSIGNMENTS = ("sequential", "spatial", "temporal")

#: Below this, a ray processing speed (rays/s) is "zero" (``FrameStats.s_proc``'s floor).
_S_PROC_EPS = 1e-6


# -- screen tiles ------------------------------------------------------------------------------
def screen_tiles(width: int, height: int, n: int) -> np.ndarray:
    """One screen tile per node: an a x b grid (a columns, b rows, a * b = n).

    a / b is the closest to width / height in ratio (|log(a/b) - log(W/H)|, compared exactly);
    grids whose tiles are all at least one pixel wide and high are preferred; an exact tie goes
    to the grid with more columns. 8 nodes at 16:9 give 4 x 2. Uneven splits spread the
    remainder (edges at ``i * width // a``).

    Parameters
    ----------
    width, height : image size in pixels (>= 1).
    n : number of tiles (>= 1).

    Returns
    -------
    tiles : (n, 4) int64 rows ``(x0, y0, x1, y1)``, half-open, in row-major order (tile
        ``row * a + column``, row 0 at the top); they cover the image exactly once.
    """
    width, height, n = int(width), int(height), int(n)
    if width < 1 or height < 1 or n < 1:
        raise ValueError(f"screen_tiles needs width, height, n >= 1 (got {width}, {height}, {n})")
    target = Fraction(width, height)

    def key(a: int) -> tuple:
        b = n // a
        ratio = Fraction(a, b) / target
        return (not (a <= width and b <= height), max(ratio, 1 / ratio), -a)

    a = min((a for a in range(1, n + 1) if n % a == 0), key=key)
    b = n // a
    xs = np.arange(a + 1, dtype=np.int64) * width // a
    ys = np.arange(b + 1, dtype=np.int64) * height // b
    row, col = np.divmod(np.arange(n), a)
    return np.stack([xs[col], ys[row], xs[col + 1], ys[row + 1]], axis=1).astype(np.int64)


def pixel_tiles(tiles: np.ndarray, width: int, height: int) -> np.ndarray:
    """The tile of every pixel.

    Parameters
    ----------
    tiles : (n, 4) int ``(x0, y0, x1, y1)`` half-open rectangles (e.g. ``screen_tiles``).
    width, height : image size in pixels.

    Returns
    -------
    tile : (width * height,) int64 tile index of pixel ``y * width + x``; -1 where no tile
        covers the pixel (where tiles overlap, the later tile wins).
    """
    out = np.full((int(height), int(width)), -1, dtype=np.int64)
    for i, (x0, y0, x1, y1) in enumerate(np.asarray(tiles, dtype=np.int64).reshape(-1, 4)):
        out[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = i
    return out.reshape(-1)


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(D, 8, 3) corners of the boxes ``[lo, hi]``."""
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1  # (8, 3)
    return np.where(bits[None, :, :] == 1, hi[:, None, :], lo[:, None, :])


def projected_rects(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Pixel bounding rectangles of the projected domain boxes (Algorithm 1, lines 11-12).

    The 8 corners of each box are projected with the pinhole model of ``Camera.generate``
    (column ``(x/z / (tan(fov/2) * W/H) + 1) * W/2``, row ``(1 - y/z / tan(fov/2)) * H/2``
    in camera coordinates x = right, y = up, z = forward), their bounding rectangle is taken and
    clipped to the screen ``[0, W] x [0, H]``. A box with a corner at or behind the eye plane
    (z <= 0) gets the whole screen. A box wholly off screen gets a rectangle of zero area.

    Parameters
    ----------
    camera : ``vastray.render.camera.Camera``.
    lo, hi : (D, 3) domain boxes.

    Returns
    -------
    rects : (D, 4) float64 ``(x0, y0, x1, y1)`` in pixels, x0 <= x1, y0 <= y1.
    """
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    width, height = float(camera.width), float(camera.height)
    forward, right, up = camera.frame()
    rel = _box_corners(lo, hi) - np.asarray(camera.position, dtype=np.float64)  # (D, 8, 3)
    z = rel @ forward
    behind = (z <= 0.0).any(axis=1)
    z = np.where(z > 0.0, z, 1.0)
    tan_half = np.tan(np.radians(camera.fov) / 2.0)
    column = ((rel @ right) / z / (tan_half * width / height) + 1.0) * (width / 2.0)
    row = (1.0 - (rel @ up) / z / tan_half) * (height / 2.0)
    rects = np.stack([column.min(axis=1), row.min(axis=1), column.max(axis=1), row.max(axis=1)],
                     axis=1)
    rects[:, 0::2] = np.clip(rects[:, 0::2], 0.0, width)
    rects[:, 1::2] = np.clip(rects[:, 1::2], 0.0, height)
    rects[behind] = (0.0, 0.0, width, height)
    return rects


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


# -- per-frame statistics ----------------------------------------------------------------------
def _fallback_mean(value: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``value`` where ``known``, else the mean of the known values, else 1.0."""
    fill = float(value[known].mean()) if known.any() else 1.0
    return np.where(known, value, fill)


@dataclass
class FrameStats:
    """One frame's counters, summed over nodes (§4.1, §4.3; note S2).

    Attributes
    ----------
    sent : (D, D) int64, s(A, B): rays forwarded from domain A to domain B != A (on one node or
        between nodes). The diagonal is ignored by every derived quantity.
    received : (D,) int64, r(A): rays A processed (from other domains, from the camera or
        spawned in A; note S12.2).
    loads : (D,) int64, N(d): loads of domain d.
    proc_rays : (D,) int64 and proc_s : (D,) float64: rays processed in d and the seconds of
        d's activations that processed them, from the activation to the end of its tracing
        and shading: the wait for d's load (what preloading did not hide) is included (for
        S_PROC). Reading: S_PROC(d) is the speed at which the node processed d's rays, as the
        node spent its time. Timing the tracing alone made Eq. 1's load term swamp Q/S_PROC
        wherever a domain's queue takes less time to trace than to load, so every domain not
        cached ranked near -T_LOAD whatever its rays, and the node loaded cheap domains
        holding few rays (bench/README.md, temporal.py: 1,152 loads per frame against 546).
    load_bytes : (P,) float64 and load_s : (P,) float64: bytes loaded by node n and seconds
        spent loading them (for S_LOAD).

    Every field is a sum over nodes, so a SUM all-reduce of ``to_arrays()`` merges nodes.
    """

    sent: np.ndarray
    received: np.ndarray
    loads: np.ndarray
    proc_rays: np.ndarray
    proc_s: np.ndarray
    load_bytes: np.ndarray
    load_s: np.ndarray

    DTYPES: ClassVar[dict[str, type]] = {
        "sent": np.int64, "received": np.int64, "loads": np.int64, "proc_rays": np.int64,
        "proc_s": np.float64, "load_bytes": np.float64, "load_s": np.float64,
    }

    def __post_init__(self):
        for name, dtype in self.DTYPES.items():
            setattr(self, name, np.asarray(getattr(self, name), dtype=dtype))
        d = len(self.received)
        p = len(self.load_bytes)
        shapes = {"sent": (d, d), "received": (d,), "loads": (d,), "proc_rays": (d,),
                  "proc_s": (d,), "load_bytes": (p,), "load_s": (p,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"FrameStats.{name} has shape {getattr(self, name).shape}, "
                                 f"expected {shape}")

    @classmethod
    def zeros(cls, n_domains: int, n_nodes: int) -> FrameStats:
        """All counters 0 for D = ``n_domains`` domains and P = ``n_nodes`` nodes."""
        d, p = int(n_domains), int(n_nodes)
        return cls(np.zeros((d, d), np.int64), np.zeros(d, np.int64), np.zeros(d, np.int64),
                   np.zeros(d, np.int64), np.zeros(d), np.zeros(p), np.zeros(p))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fields by name (the arrays themselves, not copies), for a SUM all-reduce."""
        return {name: getattr(self, name) for name in self.DTYPES}

    @classmethod
    def from_arrays(cls, d: dict[str, np.ndarray]) -> FrameStats:
        """The inverse of ``to_arrays`` (copies, cast to the field dtypes, shapes checked)."""
        return cls(**{name: np.array(d[name], dtype=dtype) for name, dtype in cls.DTYPES.items()})

    def _sent_off_diagonal(self) -> np.ndarray:
        """(D, D) int64 s(A, B) with the diagonal zeroed."""
        sent = self.sent.copy()
        np.fill_diagonal(sent, 0)
        return sent

    def transmission_ratio(self) -> np.ndarray:
        """R(A) = s(A) / r(A), 0 where r(A) = 0.

        Returns
        -------
        (D,) float64
        """
        s = self._sent_off_diagonal().sum(axis=1).astype(np.float64)
        r = self.received.astype(np.float64)
        return np.divide(s, r, out=np.zeros_like(s), where=r > 0)

    def pair_ratio(self, literal: bool = False) -> np.ndarray:
        """R(A, B) = s(A, B) / s(A) (note S12.1), 0 where the denominator is 0.

        Parameters
        ----------
        literal : use the paper's literal s(A, B) / r(A) instead (ablation; with it
            Q_CUR(act) R(act) R(act, d) counts R(act) twice).

        Returns
        -------
        (D, D) float64, row A, column B; zero diagonal.
        """
        sent = self._sent_off_diagonal().astype(np.float64)
        denom = self.received.astype(np.float64) if literal else sent.sum(axis=1)
        return np.divide(sent, denom[:, None], out=np.zeros_like(sent), where=denom[:, None] > 0)

    def s_proc(self, eps: float = _S_PROC_EPS) -> np.ndarray:
        """S_PROC(d), rays per second processed in each domain.

        A domain with no rays or no time recorded gets the mean speed of the domains that have
        both (1.0 if none has); the result is floored at ``eps``.

        Returns
        -------
        (D,) float64, >= eps
        """
        known = (self.proc_rays > 0) & (self.proc_s > 0)
        speed = np.divide(self.proc_rays.astype(np.float64), self.proc_s,
                          out=np.zeros(len(self.proc_s)), where=known)
        return np.maximum(_fallback_mean(speed, known), eps)

    def s_load(self) -> np.ndarray:
        """S_LOAD(n), bytes per second loaded by each node (§4.3).

        A node with no bytes or no time recorded gets the mean of the nodes that have both
        (1.0 if none has).

        Returns
        -------
        (P,) float64
        """
        known = (self.load_bytes > 0) & (self.load_s > 0)
        speed = np.divide(self.load_bytes, self.load_s, out=np.zeros(len(self.load_s)),
                          where=known)
        return _fallback_mean(speed, known)


# -- domain assignment -------------------------------------------------------------------------
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


# -- runtime priorities (Eq 1-4) ---------------------------------------------------------------
def dep_prime(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray, nonempty: np.ndarray) -> np.ndarray:
    """Dep'(d), the normalised distance from the viewpoint to each domain (Eq 1; note S4).

    dist(eye, box d) / max over non-empty d' of |eye - farthest corner of box d'|, clipped to
    [0, 1) (a non-degenerate box is always nearer than its farthest corner, so the clip only
    bites for point boxes and for empty boxes beyond every non-empty one).

    Parameters
    ----------
    eye : (3,) viewpoint.
    lo, hi : (D, 3) domain boxes.
    nonempty : (D,) bool, the boxes that set the normalisation.

    Returns
    -------
    (D,) float64 in [0, 1); 0 for every box containing the eye; all 0 if there is no
    non-empty box (or every one is a point at the eye).
    """
    eye = np.asarray(eye, dtype=np.float64)
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    near = np.linalg.norm(np.maximum(np.maximum(lo - eye, eye - hi), 0.0), axis=1)
    far = np.linalg.norm(np.maximum(np.abs(eye - lo), np.abs(eye - hi)), axis=1)
    nonempty = np.asarray(nonempty, dtype=bool)
    scale = float(far[nonempty].max()) if nonempty.any() else 0.0
    if scale <= 0.0:
        return np.zeros(len(lo))
    return np.minimum(near / scale, np.nextafter(1.0, 0.0))


def load_time(domain_bytes: np.ndarray, s_load_n: float, resident: np.ndarray) -> np.ndarray:
    """T_LOAD(n, d) (Eq 2): 0 for a resident domain (or one being preloaded), else
    V(d) / S_LOAD(n).

    Parameters
    ----------
    domain_bytes : (D,) V(d).
    s_load_n : S_LOAD(n) of this node, bytes/s (> 0).
    resident : (D,) bool, in the cache or being loaded.

    Returns
    -------
    (D,) float64 seconds.
    """
    t = np.asarray(domain_bytes, dtype=np.float64) / float(s_load_n)
    return np.where(np.asarray(resident, dtype=bool), 0.0, t)


def potential(q_pre: np.ndarray, q_cur_recv: np.ndarray, n_pre: np.ndarray, n_cur: np.ndarray
              ) -> np.ndarray:
    """Q_POT(d) (Eq 4), guarded (note S4): max(0, Q_PRE - Q_CUR_RECV) / max(1, N_PRE - N_CUR).

    Parameters
    ----------
    q_pre : (D,) rays sent to d from non-local domains in the previous frame.
    q_cur_recv : (D,) rays d received from them so far in this frame.
    n_pre, n_cur : (D,) loads of d in the previous frame and so far in this one.

    Returns
    -------
    (D,) float64, finite and >= 0.
    """
    num = np.maximum(np.asarray(q_pre, np.float64) - np.asarray(q_cur_recv, np.float64), 0.0)
    den = np.maximum(np.asarray(n_pre, np.float64) - np.asarray(n_cur, np.float64), 1.0)
    return num / den


@dataclass
class PriorityInputs:
    """What node n knows when it scores its local domains (note S4).

    Attributes
    ----------
    q_cur : (D,) Q_CUR(d), rays queued at this node for d (radiance + shadow).
    active : the active domain ``act`` (being rendered), or None.
    q_act : Q_CUR(act), rays in act's popped queue (ignored when ``active`` is None).
    R : (D,) R(A) of the previous frame (``FrameStats.transmission_ratio``).
    R_pair : (D, D) R(A, B) of the previous frame (``FrameStats.pair_ratio``).
    q_pre, q_cur_recv, n_pre, n_cur : (D,) the inputs of Eq 4 (``potential``).
    s_proc : (D,) S_PROC(d), rays/s (``FrameStats.s_proc``).
    domain_bytes : (D,) V(d).
    s_load_n : S_LOAD(n) of this node, bytes/s.
    resident : (D,) bool, cached or being loaded.
    dep : (D,) Dep'(d) (``dep_prime``).
    local : (D,) bool, this node's local domains (``Assignment.owns``).
    spray_score : (D,) SpRay traversal score sum_j (M - j) Counter[d][j], or None (needed only
        by the "spray" priority).
    """

    q_cur: np.ndarray
    active: int | None
    q_act: int
    R: np.ndarray
    R_pair: np.ndarray
    q_pre: np.ndarray
    q_cur_recv: np.ndarray
    n_pre: np.ndarray
    n_cur: np.ndarray
    s_proc: np.ndarray
    domain_bytes: np.ndarray
    s_load_n: float
    resident: np.ndarray
    dep: np.ndarray
    local: np.ndarray
    spray_score: np.ndarray | None = None


def _act_term(inputs: PriorityInputs) -> np.ndarray:
    """(D,) Q_CUR(act) R(act) R(act, d), the rays act is expected to send to each d."""
    d = len(inputs.q_cur)
    if inputs.active is None:
        return np.zeros(d)
    act = int(inputs.active)
    return float(inputs.q_act) * float(inputs.R[act]) * np.asarray(inputs.R_pair[act], np.float64)


def priority(kind: str, inputs: PriorityInputs) -> np.ndarray:
    """The preload priority of every domain for node n.

    Candidates are the local domains other than the active one with
    Q_PRED(d) = Q_CUR(d) + Q_CUR(act) R(act) R(act, d) + Q_POT(d) > 0 (Eq 3); the same set for
    every kind, so the ablation only swaps the score:

    * ``"queue"``: Q_CUR(d) (the baseline, Table 2 "+Q_CUR");
    * ``"spray"``: the SpRay traversal score ``inputs.spray_score``;
    * ``"queue+act"``: Q_CUR(d) + Q_CUR(act) R(act) R(act, d);
    * ``"cost-benefit"``: Eq 1, literally,
      (1 - Dep'(d)) * (Q_PRED(d) / S_PROC(d) - T_LOAD(n, d)). When the bracket is negative
      (loading costs more than the predicted work), (1 - Dep') scales it towards 0 for *far*
      domains, so among such domains the far one ranks higher (note S12.4, kept literally).
      S_PROC is floored at a tiny epsilon against division by zero.
    * ``"cost-rate"``: Eq 1's benefit over its cost,
      (1 - Dep'(d)) * (Q_PRED(d) / S_PROC(d)) / max(T_LOAD(n, d), RESIDENT_COST_S): predicted
      seconds of work per second of loading. The difference form compares seconds of work
      with seconds of loading on one scale, so wherever a domain's queue traces faster than it
      loads (ours: milliseconds against tens), -T_LOAD decides alone and the node loads small
      domains holding few rays; the ratio keeps the work in every score, ranks a resident
      domain by its work alone, and is never negative, so (1 - Dep') always favours the near.
    * ``"queue+resident"``: Q_CUR(d), every resident domain (cached or being loaded) ahead of
      every one that must be loaded: the baseline given the cache awareness that the
      cost-based priorities have through T_LOAD (ties -> lower id as everywhere).

    Returns
    -------
    (D,) float64, -inf where d is not a candidate.
    """
    if kind not in PRIORITIES:
        raise ValueError(f"unknown priority {kind!r}; expected one of {PRIORITIES}")
    q_cur = np.asarray(inputs.q_cur, dtype=np.float64)
    act_term = _act_term(inputs)
    q_pot = potential(inputs.q_pre, inputs.q_cur_recv, inputs.n_pre, inputs.n_cur)
    q_pred = q_cur + act_term + q_pot
    cand = np.asarray(inputs.local, dtype=bool) & (q_pred > 0)
    if inputs.active is not None:
        cand[int(inputs.active)] = False
    if kind == "queue":
        score = q_cur
    elif kind == "spray":
        if inputs.spray_score is None:
            raise ValueError('priority "spray" needs inputs.spray_score')
        score = np.asarray(inputs.spray_score, dtype=np.float64)
    elif kind == "queue+act":
        score = q_cur + act_term
    elif kind == "queue+resident":
        # Q_CUR >= 0, so adding more than the largest one puts every resident domain first.
        lead = float(q_cur.max(initial=0.0)) + 1.0
        score = q_cur + np.where(np.asarray(inputs.resident, dtype=bool), lead, 0.0)
    else:
        t_load = load_time(inputs.domain_bytes, inputs.s_load_n, inputs.resident)
        s_proc = np.maximum(np.asarray(inputs.s_proc, dtype=np.float64), 1e-300)
        near = 1.0 - np.asarray(inputs.dep, dtype=np.float64)
        if kind == "cost-benefit":
            score = near * (q_pred / s_proc - t_load)
        else:
            score = near * (q_pred / s_proc) / np.maximum(t_load, RESIDENT_COST_S)
    return np.where(cand, score, -np.inf)


def bootstrap_priority(kind: str) -> str:
    """The priority frame 0 uses in place of ``kind``: it has no statistics yet (S_PROC,
    S_LOAD, R), so Eq 1's forms fall back to queued rays, as the paper's bootstrap frame
    does (``cost-benefit``, ``queue+act`` -> ``queue``), and ``cost-rate`` keeps its cache rule
    (-> ``queue+resident``: cached domains first, by queued rays); the others need none."""
    return {"cost-benefit": "queue", "queue+act": "queue",
            "cost-rate": "queue+resident"}.get(kind, kind)


def best(priorities: np.ndarray) -> int | None:
    """The domain with the highest priority (ties -> lower id); None if every one is -inf (or
    NaN, which counts as -inf)."""
    p = np.asarray(priorities, dtype=np.float64)
    p = np.where(np.isnan(p), -np.inf, p)
    if not len(p) or (p == -np.inf).all():
        return None
    return int(np.argmax(p))


def resident_after_load(resident: Iterable[int], capacity: int, active: int,
                        priorities: np.ndarray) -> set[int]:
    """The domains cached once ``active`` is loaded: a full cache gives up its lowest of
    ``priorities`` (``victim``) to make room. d* must be picked from these, or a domain about
    to be evicted would count as cached.

    Parameters
    ----------
    resident : ids cached (or being loaded) now.
    capacity : the cache's size in domains.
    active : the domain about to be traced (loaded first if not resident).
    priorities : (D,) from ``priority``.

    Returns
    -------
    set of ids, ``active`` included, at most ``max(capacity, 1)`` of them.
    """
    after = {int(d) for d in resident}
    if active not in after and len(after) >= capacity:
        after.discard(victim(priorities, list(after), {active}))
    return after | {int(active)}


def victim(priorities: np.ndarray, resident: list[int], protect: set[int]) -> int | None:
    """The resident domain to evict: the lowest priority among ``resident`` not in ``protect``
    (e.g. act and d*); non-candidates (-inf, NaN) rank lowest; ties -> the lower id.

    Parameters
    ----------
    priorities : (D,) from ``priority``.
    resident : ids of the cached domains.
    protect : ids never to evict.

    Returns
    -------
    The domain id, or None if every resident domain is protected.
    """
    ids = np.array(sorted({int(d) for d in resident} - {int(d) for d in protect}), dtype=np.int64)
    if not len(ids):
        return None
    p = np.asarray(priorities, dtype=np.float64)[ids]
    p = np.where(np.isnan(p), -np.inf, p)
    return int(ids[np.argmin(p)])
