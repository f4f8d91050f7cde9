"""Occupancy masks: a coarse grid of bits per domain, set where the domain has triangles.

A domain's box is often much larger than the space its triangles fill (a slab of an
isosurface cut by the partition grid), and a ray that crosses only the box's empty part can
never hit anything in it. The mask lets the ray-domain enumeration (``schedule.geometry``)
drop such (ray, domain) pairs before a ray is queued into the domain, so a schedule never
loads a domain for rays that cross only its empty corner.

Layout. The grid spans the domain's box ``[lo, hi]`` (the manifest's ``bounds``, in the
store's frame) with ``grid`` = (a, b, c) cells per axis, ``a * b * c`` bits in C order
(``(i * b + j) * c + k``, x slowest), packed with ``np.packbits`` (the last byte's unused
bits zero) and stored base64 in the domain's manifest entry (format version 5)::

    "occupancy": {"grid": [16, 16, 8], "bits": "..."}

The finest axis gets :data:`RESOLUTION` cells and the others as many in proportion to their
extent (a flat axis: one), halved while the packed bits exceed :data:`MAX_SHARE` of the
domain's bytes (so at most 512 bytes, and nothing for tiny domains: one cell, every ray kept).

Conservative by construction. A cell is set where the box of some triangle (its float32
vertices, exact in float64) meets it; cell indices are ``floor((x - lo) / cell)`` in float64,
clamped to the grid, and that function is monotone in ``x``, so every point of a triangle's
box has an index within the triangle's index range. A query (``crosses``) splits the ray's
segment through the box at the cell boundaries it crosses (a 3-D DDA) and, for each piece,
tests every cell meeting the piece's box grown by ``radius``: a piece's box holds the piece
whatever the rounding of the DDA's bookkeeping, so the pieces together cover the whole
segment. ``radius`` (16 times the slab test's pad) covers Embree's error on where a hit lies
(a robust-mode hit is within a few float32 ulps of the largest coordinate involved), so any
point a hit can be reported at lies in a tested cell that a triangle's box meets, including
rays grazing cell faces and triangles lying exactly on a cell boundary.

Skipping empty neighbourhoods. Each piece lies in the cell the DDA's bookkeeping names, up
to rounding far below ``radius`` (each axis's index counts the boundaries crossed, computed
from the same float64 plane positions), and ``radius`` is under a quarter of a cell: its box
grown by ``radius`` meets only that cell and the 26 around it. So where none of those 27 is
occupied (``Occupancy.near``, the mask dilated by one cell, made when a store is opened) the
query steps on without testing the piece; the answers are the full test's bit for bit
(``tests/test_occupancy.py``; the 1.06 M pairs sampled from the 100 M-triangle store's render
and 307 k from ``bench/ooc.py --large``'s), at about half the cost a pair (380 -> 195 ns on
``--large``'s). A grid whose cells are not four radii wide tests every piece, and so does a
ray whose direction is zero (its one piece has no end).
"""

from __future__ import annotations

import base64
import binascii
import os

import numpy as np

#: Cells along a domain's longest axis.
RESOLUTION = 16
#: Largest share of a domain's bytes its packed mask may take.
MAX_SHARE = 0.01
#: Most cells per axis a manifest may give (readers accept more than writers make).
MAX_CELLS = 64
#: Set to "0", "off" or "no" to ignore every mask (measurements: loads with and without).
ENV = "VASTRAY_OCCUPANCY"
#: The query's radius, in slab-test pads (``RaySlabs.pad``).
RADIUS_PADS = 16.0


def enabled() -> bool:
    """Whether renders use occupancy masks (``VASTRAY_OCCUPANCY``, default on)."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "off", "no", "false")


# --- building ----------------------------------------------------------------------------------


def grid_dims(lo: np.ndarray, hi: np.ndarray, nbytes: float,
              resolution: int = RESOLUTION) -> tuple[int, int, int]:
    """Cells per axis for a domain of box ``[lo, hi]`` and ``nbytes`` bytes of arrays.

    The longest axis gets ``resolution`` cells (halved until the packed bits fit in
    ``MAX_SHARE`` of ``nbytes``; ``inf``: no cap), the others in proportion to their
    extent, at least one.
    """
    extent = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    longest = float(extent.max(initial=0.0))
    if not np.isfinite(longest) or longest <= 0:
        return (1, 1, 1)
    r = resolution
    while r > 1:
        dims = np.clip(np.ceil(r * extent / longest - 1e-9), 1, r).astype(np.int64)
        if (int(np.prod(dims)) + 7) // 8 <= MAX_SHARE * nbytes:
            return tuple(int(d) for d in dims)
        r //= 2
    return (1, 1, 1)


def cell_size(lo: np.ndarray, hi: np.ndarray, dims) -> np.ndarray:
    """(3,) float64 cell edge per axis (0 where the box is flat)."""
    return (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)) / np.asarray(dims, np.float64)


def compute(vertices: np.ndarray, indices: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            dims) -> np.ndarray:
    """The occupancy of a domain's triangles over its box.

    Parameters
    ----------
    vertices : (V, 3) float32 in the store's frame; indices : (T, 3) uint32.
    lo, hi : (3,) the domain's box; dims : (3,) cells per axis.

    Returns
    -------
    (a, b, c) bool
    """
    dims = np.asarray(dims, np.int64)
    out = np.zeros(int(np.prod(dims)), np.uint8)
    if len(indices):
        lo = np.asarray(lo, np.float64)
        from vastray.scene.occupancy_kernels import mark

        mark(np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(indices, np.uint32),
             lo, cell_size(lo, hi, dims), dims, out)
    return out.astype(bool).reshape(tuple(int(d) for d in dims))


def of_domain(vertices: np.ndarray, indices: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              nbytes: int) -> np.ndarray:
    """The mask a writer stores for a domain: ``compute`` on ``grid_dims``."""
    return compute(vertices, indices, lo, hi, grid_dims(lo, hi, nbytes))


def encode(bits: np.ndarray) -> dict:
    """The manifest's ``"occupancy"`` value of ``bits`` ((a, b, c) bool)."""
    packed = np.packbits(np.asarray(bits, bool).ravel())
    return {"grid": [int(d) for d in bits.shape],
            "bits": base64.b64encode(packed.tobytes()).decode("ascii")}


def decode(value) -> np.ndarray:
    """``bits`` ((a, b, c) bool) of a manifest's ``"occupancy"`` value.

    Raises
    ------
    ValueError
        Not ``{"grid": [a, b, c], "bits": base64}`` with 1..``MAX_CELLS`` cells per axis and
        exactly the packed bytes of a * b * c bits (unused bits zero).
    """
    if not isinstance(value, dict) or set(value) != {"grid", "bits"}:
        raise ValueError('must be {"grid": [a, b, c], "bits": "<base64>"}')
    grid, text = value["grid"], value["bits"]
    if not (isinstance(grid, list) and len(grid) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= MAX_CELLS
                    for n in grid)):
        raise ValueError(f"'grid' must be 3 whole numbers in 1..{MAX_CELLS}")
    if not isinstance(text, str):
        raise ValueError("'bits' must be a base64 string")
    try:
        raw = base64.b64decode(text.encode("ascii"), validate=True)
    except (binascii.Error, UnicodeEncodeError):
        raise ValueError("'bits' is not valid base64") from None
    n = grid[0] * grid[1] * grid[2]
    if len(raw) != (n + 7) // 8:
        raise ValueError(f"'bits' holds {len(raw)} bytes; a {grid[0]}x{grid[1]}x{grid[2]} grid "
                         f"packs into {(n + 7) // 8}")
    bits = np.unpackbits(np.frombuffer(raw, np.uint8))
    if bits[n:].any():
        raise ValueError("'bits' has bits set past the grid's last cell")
    return bits[:n].astype(bool).reshape(grid)


# --- querying ----------------------------------------------------------------------------------


#: Fewest (ray, domain) pairs per thread when a query is split.
_SPLIT_MIN_PAIRS = 8192


def split_pairs(part, n: int) -> None:
    """Run ``part(lo, hi)`` over the pairs ``0..n`` on the threads this process may use
    (``embree.launch.run_in_parts``; the kernel is serial and releases the GIL, and each
    piece writes only its own rows), or on the calling thread when ``n`` is small."""
    if n < 2 * _SPLIT_MIN_PAIRS:  # (before available_cpus, which reads cgroup files)
        part(0, n)
        return
    from vastray.scene.cpus import available_cpus
    from vastray.scene.embree.launch import run_in_parts

    run_in_parts(part, n, min(available_cpus(), n // _SPLIT_MIN_PAIRS))


def dilated(mask: np.ndarray) -> np.ndarray:
    """(a, b, c) bool: the cells of ``mask`` ((a, b, c) bool) that are occupied or have an
    occupied neighbour among the 26 around them."""
    out = np.array(mask, bool)
    for axis in range(3):  # the 3x3x3 cube is three 3-cell lines: one axis at a time
        line = out.copy()
        ahead = [slice(None)] * 3
        behind = [slice(None)] * 3
        ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
        line[tuple(behind)] |= out[tuple(ahead)]
        line[tuple(ahead)] |= out[tuple(behind)]
        out = line
    return out


class Occupancy:
    """Every domain's mask, packed for the compiled query.

    Parameters
    ----------
    lo, hi : (D, 3) domain boxes (the grids' boxes).
    masks : D masks ((a, b, c) bool each), None for a domain without one (every cell
        occupied: an old store's).
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, masks: list):
        n = len(masks)
        self.lo = np.ascontiguousarray(lo, np.float64).reshape(n, 3)
        self.hi = np.ascontiguousarray(hi, np.float64).reshape(n, 3)
        self.dims = np.ones((n, 3), np.int64)
        self.cell = np.zeros((n, 3), np.float64)
        #: Domains whose mask can drop a ray: one with an empty cell.
        self.useful = np.zeros(n, np.bool_)
        self.base = np.zeros(n, np.int64)
        flat, near = [], []
        at = 0
        for d, mask in enumerate(masks):
            if mask is None or mask.all():
                continue
            self.dims[d] = mask.shape
            self.cell[d] = cell_size(self.lo[d], hi[d], mask.shape)
            self.useful[d] = True
            self.base[d] = at
            flat.append(mask.ravel().astype(np.uint8))
            near.append(dilated(mask).ravel().astype(np.uint8))
            at += mask.size
        self.bits = np.concatenate(flat) if flat else np.zeros(1, np.uint8)
        #: Per cell (laid out as ``bits``): whether it or a cell next to it (of the 26) is
        #: occupied; the query skips a piece whose cell has none (``crosses``).
        self.near = np.concatenate(near) if near else np.zeros(1, np.uint8)
        #: (D,) the smallest cell edge of each domain's grid (inf where it has one cell)
        self.min_cell = np.where(self.dims > 1, self.cell, np.inf).min(axis=1)

    @property
    def any_useful(self) -> bool:
        return bool(self.useful.any())

    def crosses(self, origins: np.ndarray, directions: np.ndarray, ray: np.ndarray,
                domain: np.ndarray, limit: np.ndarray, pad: float) -> np.ndarray:
        """Whether ray ``ray[p]``'s segment ``[0, limit]`` crosses an occupied cell of domain
        ``domain[p]`` (grown by ``RADIUS_PADS * pad``), for every pair ``p``.

        Parameters
        ----------
        origins, directions : (n, 3) float32 rays; limit : (n,) float32 where each ends.
        ray : (m,) int rows of the rays; domain : (m,) int domain ids.
        pad : the slab test's pad (``RaySlabs.pad``) for these rays.

        Returns
        -------
        (m,) bool: False only where no triangle of the domain can be hit by the ray.
        """
        out = np.ones(len(ray), np.bool_)
        if len(ray) and self.any_useful:
            from vastray.scene.occupancy_kernels import crosses

            n = len(origins)
            whole = (np.ascontiguousarray(origins, np.float32),
                     np.ascontiguousarray(directions, np.float32))
            ends = np.ascontiguousarray(np.broadcast_to(limit, (n,)), np.float32)
            pairs = (np.ascontiguousarray(ray, np.int64), np.ascontiguousarray(domain, np.int64))
            grids = (float(RADIUS_PADS * pad), self.lo, self.hi, self.cell, self.dims,
                     self.useful, self.base, self.bits, self.near, self.min_cell)

            def part(lo: int, hi: int) -> None:  # pairs lo..hi; each writes its own rows of out
                crosses(*whole, pairs[0][lo:hi], pairs[1][lo:hi], ends, *grids, out[lo:hi])

            split_pairs(part, len(ray))
        return out
