"""The simplified whole-scene model (paper §6.1, §7.3.2): every object of every domain
decimated by quadric edge collapse, concatenated into one mesh each render node keeps resident.

Per domain and per object slot (the ``objects`` array; the whole domain when it has none), the
triangles are decimated with ``fast_simplification.simplify`` (the quadric edge-collapse
library trimesh's ``simplify_quadric_decimation`` wraps) to ``ratio`` of their count. Pieces with
fewer than ``min_faces`` triangles are kept whole ("except for some objects with too few
faces"), and so is everything when ``ratio`` is 1 (an identity model, bit for bit).

Attributes. Each vertex of a decimated piece is a surviving input vertex moved to the quadric
optimum; the library's collapse history (``return_collapses=True``: ``[i0, i1]`` = ``i1`` was
merged into ``i0``) tells exactly which input vertices were merged into it. Its per-vertex
scalar and colour are those of the nearest of these input vertices (its collapse cluster,
which always holds the survivor itself). This needs no spatial search, and never takes a value
from across a thin gap the way a global nearest-neighbour query can. Every triangle keeps its
piece's material slot.

Bounds. A quadric optimum may lie slightly outside the piece it came from (a few hundredths of
a domain at 1 %); vertices are clamped to the box of the piece's input vertices, so the model
stays inside its domain boxes and the scene bounds.

Memory: one domain's arrays at a time (memory-mapped) plus the growing result, ``ratio`` of the
scene. The library keeps its mesh in module-global state: not thread-safe.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass

import numpy as np

from vastray.scene.errors import InputError
from vastray.scene.manifest import SimplifiedInfo
from vastray.scene.progressbar import Bar
from vastray.scene.store import DomainArrays, Store, check_simplified_replaceable, write_simplified

log = logging.getLogger(__name__)

#: Object pieces with fewer triangles than this are kept whole (the paper's "objects with too
#: few faces"), unless the caller says otherwise.
DEFAULT_MIN_FACES = 1000

_HINT = "pip install fast-simplification (a dependency of vastray)"


def check_ratio(ratio: float) -> float:
    """``ratio`` as a float in (0, 1].

    Raises
    ------
    InputError
        Outside (0, 1] or not finite.
    """
    value = float(ratio)
    if not (0.0 < value <= 1.0):
        raise InputError(None, f"the simplification ratio (the fraction of triangles kept) must "
                               f"be in (0, 1], got {ratio!r}")
    return value


def _simplifier():
    try:
        import fast_simplification
    except ImportError:  # a dependency; only a broken install lacks it
        raise InputError(None, f"building a simplified model needs fast-simplification: {_HINT}") \
            from None
    return fast_simplification


@dataclass
class Piece:
    """One simplified object piece: its triangles and, per output vertex, the input vertex its
    attributes come from."""

    vertices: np.ndarray  # (V, 3) float32
    indices: np.ndarray   # (T, 3) int64, into vertices
    source: np.ndarray    # (V,) int64, into the input vertices


def simplify_piece(vertices: np.ndarray, indices: np.ndarray, ratio: float,
                   min_faces: int = DEFAULT_MIN_FACES) -> Piece:
    """Decimate one triangle mesh to about ``ratio`` of its triangles.

    Parameters
    ----------
    vertices : (V, 3) float vertex positions.
    indices : (T, 3) int triangles into ``vertices``.
    ratio : the fraction of triangles kept, in (0, 1].
    min_faces : meshes with fewer triangles (and any mesh when ``ratio`` is 1) are returned
        whole.

    Returns
    -------
    The decimated piece: only vertices its triangles use, each clamped to the box of the input
    vertices used; ``source`` maps each to the input vertex (in its collapse cluster) nearest
    to it.
    """
    indices = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    used, local = np.unique(indices, return_inverse=True)
    local = local.reshape(-1, 3)
    points = np.asarray(vertices, dtype=np.float32)[used]
    if ratio >= 1.0 or len(indices) < max(int(min_faces), 1):
        return Piece(points, local, used)
    # index-degenerate triangles (a repeated vertex) have no plane for a quadric; dropped
    solid = (local[:, 0] != local[:, 1]) & (local[:, 1] != local[:, 2]) & (local[:, 0] != local[:, 2])
    faces = local[solid]
    if not len(faces):
        return Piece(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64),
                     np.zeros(0, np.int64))
    out_points, out_faces, collapses = _simplifier().simplify(
        points.astype(np.float64), faces, target_reduction=1.0 - ratio, return_collapses=True)
    survivor = _survivors(len(points), faces, collapses, out_faces, len(out_points))
    if not np.isfinite(out_points).all():  # a zero-area triangle's quadric: keep the input
        log.warning("simplification gave non-finite vertices for a piece of %d triangles; kept "
                    "it whole", len(indices))
        return Piece(points, local, used)
    lo, hi = points.min(axis=0), points.max(axis=0)
    out_points = np.clip(out_points, lo, hi).astype(np.float32)
    nearest = _nearest_in_cluster(points, survivor, out_points)
    return Piece(out_points, out_faces.astype(np.int64), used[nearest])


def _survivors(n_points: int, faces: np.ndarray, collapses: np.ndarray, out_faces: np.ndarray,
               n_out: int) -> np.ndarray:
    """For every input vertex, the output vertex it was merged into (-1: none survives).

    The library never re-indexes before its final compaction, which keeps the input vertices
    still used, in input order; so the survivor of a vertex is the end of its chain of
    collapses, and output vertex k is the k-th surviving input vertex. Checked against the
    library's own output triangles.
    """
    root = np.arange(n_points)
    collapses = np.asarray(collapses, dtype=np.int64).reshape(-1, 2)
    root[collapses[:, 1]] = collapses[:, 0]
    while True:  # pointer jumping: O(log chain) passes
        nxt = root[root]
        if np.array_equal(nxt, root):
            break
        root = nxt
    mapped = root[faces]
    kept = mapped[(mapped[:, 0] != mapped[:, 1]) & (mapped[:, 1] != mapped[:, 2])
                  & (mapped[:, 0] != mapped[:, 2])]
    alive = np.unique(kept)
    if len(alive) != n_out or not np.array_equal(alive[out_faces], kept):
        raise RuntimeError("fast-simplification's collapse history does not match its output "
                           "(an unexpected library version?); cannot map vertex attributes")
    out_of = np.full(n_points, -1, dtype=np.int64)
    out_of[alive] = np.arange(n_out)
    return out_of[root]


def _nearest_in_cluster(points: np.ndarray, survivor: np.ndarray,
                        out_points: np.ndarray) -> np.ndarray:
    """(V_out,) the input vertex nearest to each output vertex among those merged into it."""
    member = np.flatnonzero(survivor >= 0)
    cluster = survivor[member]
    dist = ((points[member].astype(np.float64) - out_points[cluster]) ** 2).sum(axis=1)
    order = np.lexsort((member, dist, cluster))  # by cluster, then distance, then index
    first = np.ones(len(order), dtype=bool)
    first[1:] = cluster[order][1:] != cluster[order][:-1]
    nearest = np.empty(len(out_points), dtype=np.int64)
    nearest[cluster[order][first]] = member[order][first]
    return nearest


def simplify_domains(store: Store, ratio: float, min_faces: int = DEFAULT_MIN_FACES,
                     progress: bool = False) -> DomainArrays:
    """The simplified model of a whole store: every object piece of every domain decimated.

    Parameters
    ----------
    store : the open store.
    ratio : the fraction of triangles kept, in (0, 1].
    min_faces : object pieces (one slot of one domain) with fewer triangles are kept whole.
    progress : tqdm bar over the domains on stderr (after a second).

    Returns
    -------
    One mesh of the whole scene: float32 vertices inside the scene bounds, uint32 indices,
    and the store's attributes (``objects`` = each triangle's slot; per-vertex ``scalars`` and
    ``colors`` from the nearest merged input vertex).

    Raises
    ------
    InputError
        ``ratio`` outside (0, 1], or a domain that does not load.
    """
    ratio = check_ratio(ratio)
    has = {kind: bool(store.manifest.get("attributes", {}).get(kind))
           for kind in ("objects", "scalars", "colors")}
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("vertices", "indices", "objects",
                                                           "scalars", "colors")}
    offset = 0
    for info in Bar(store.domains, desc="simplify", unit="domain", delay=1.0,
                     disable=not progress, leave=False):
        if not info.n_triangles:
            continue
        dom = store.load_domain(info.id)
        if dom.objects is None:
            slots = [(0, slice(None))]
        else:
            objects = np.asarray(dom.objects)
            slots = [(int(s), objects == s) for s in np.unique(objects)]
        for slot, rows in slots:
            piece = simplify_piece(dom.vertices, np.asarray(dom.indices)[rows], ratio, min_faces)
            parts["vertices"].append(piece.vertices)
            parts["indices"].append(piece.indices + offset)
            offset += len(piece.vertices)
            if has["objects"]:
                parts["objects"].append(np.full(len(piece.indices), slot, dtype=np.uint16))
            for kind in ("scalars", "colors"):
                if has[kind] and getattr(dom, kind) is not None:
                    parts[kind].append(np.asarray(getattr(dom, kind))[piece.source])

    def joined(kind, dtype, shape):
        if kind not in ("vertices", "indices") and not has[kind]:
            return None
        if not parts[kind]:
            return np.zeros(shape, dtype)
        return np.ascontiguousarray(np.concatenate(parts[kind]), dtype=dtype)

    return DomainArrays(
        vertices=joined("vertices", np.float32, (0, 3)),
        indices=joined("indices", np.uint32, (0, 3)),
        objects=joined("objects", np.uint16, (0,)),
        scalars=joined("scalars", np.float32, (0,)),
        colors=joined("colors", np.float32, (0, 3)),
    )


@dataclass
class SimplifyResult:
    """What :func:`build_simplified` wrote: the checked manifest entry and the build time."""

    entry: SimplifiedInfo
    seconds: float

    def summary(self, store: str | os.PathLike) -> str:
        """One line: the store, the model's size and rates, and the build time."""
        e = self.entry
        return (f"{store}: simplified model of {e.n_triangles:,} triangles, "
                f"{e.n_vertices:,} vertices: triangle rate {e.rate:.2%} (asked {e.ratio:.2%}), "
                f"memory rate {e.memory_rate:.2%} of the domains' bytes, built in "
                f"{self.seconds:.2f} s")


def build_simplified(store: Store, ratio: float, min_faces: int = DEFAULT_MIN_FACES,
                     force: bool = False, progress: bool = False) -> SimplifyResult:
    """Build the simplified model of ``store`` and write it into the store.

    Raises
    ------
    InputError
        A simplified model exists and not ``force`` (checked before any work), ``ratio``
        outside (0, 1], or a domain that does not load.
    """
    ratio = check_ratio(ratio)
    check_simplified_replaceable(store, force)
    _simplifier()
    start = time.perf_counter()
    model = simplify_domains(store, ratio, min_faces=min_faces, progress=progress)
    entry = write_simplified(store, model, ratio, min_faces=min_faces, force=force)
    return SimplifyResult(entry, time.perf_counter() - start)
