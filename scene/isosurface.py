"""Brick-by-brick marching cubes over volumes that are never loaded whole.

A volume of ``(nx, ny, nz)`` voxels (indexed ``[x, y, z]``) has ``n - 1`` cells per axis. The
cells are cut into bricks of at most ``brick`` cells per axis; neighbouring bricks share one
voxel layer, so every cell is marched by exactly one brick and the surface has no cracks: a
vertex on a shared brick face is interpolated from the same two voxel values on both sides and
gets bit-identical coordinates, so :func:`vastray.scene.meshops.weld` joins the pieces exactly.

Only one brick of voxels, ``(brick + 1)**3`` values converted to float32, is in memory at a time
(64 cells -> 1.1 MB), plus the faces bricks share with bricks not yet marched (at most about one
plane of the volume, ``ny * nz`` float32). Vertices come out in world coordinates:
``origin + index * spacing``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from itertools import pairwise

import numpy as np
from skimage.measure import marching_cubes

log = logging.getLogger(__name__)

DEFAULT_BRICK = 64
"""Cells per brick edge: a brick holds at most 65**3 float32 voxels (1.1 MB)."""

Field = Callable[[range, range, range], "np.ndarray | None"]


def axis_bricks(n: int, brick: int = DEFAULT_BRICK,
                cuts: Sequence[int] | None = None) -> list[tuple[int, int]]:
    """Voxel ranges of the bricks along one axis.

    Parameters
    ----------
    n : voxels along the axis (>= 2).
    brick : most cells per brick.
    cuts : optional increasing voxel indices from 0 to n - 1 that must be brick boundaries
        (e.g. the planes of a domain grid); each interval between cuts is split evenly.

    Returns
    -------
    list of (start, stop): the brick reads voxels ``start:stop``; the next brick starts at
    ``stop - 1`` (one shared voxel), so the cells ``start .. stop - 2`` belong to this brick.
    """
    if n < 2:
        raise ValueError(f"need at least 2 voxels along each axis, got {n}")
    cuts = [0, n - 1] if cuts is None else [int(c) for c in cuts]
    if cuts[0] != 0 or cuts[-1] != n - 1 or any(b <= a for a, b in pairwise(cuts)):
        raise ValueError(f"cuts must increase strictly from 0 to {n - 1}, got {cuts}")
    ranges = []
    for a, b in pairwise(cuts):
        pieces = -(-(b - a) // brick)
        edges = np.linspace(a, b, pieces + 1).round().astype(int)
        ranges += [(int(s), int(e) + 1) for s, e in pairwise(edges)]
    return ranges


def march_brick(block: np.ndarray, level: float, start: Sequence[int],
                spacing: Sequence[float] = (1.0, 1.0, 1.0),
                origin: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes (Lewiner, scikit-image defaults) on one brick.

    Parameters
    ----------
    block : (bx, by, bz) voxel values of the brick, each >= 2.
    level : iso value.
    start : (3,) voxel index of ``block[0, 0, 0]`` in the whole volume.
    spacing, origin : (3,) world size of a voxel step and world position of voxel (0, 0, 0).

    Returns
    -------
    vertices : (V, 3) float32 world coordinates.
    indices : (T, 3) uint32 into ``vertices``; (0, 3) when the level is not crossed.

    Raises
    ------
    ValueError : the brick holds NaN or infinite values.
    """
    block = np.asarray(block, dtype=np.float32)
    lo, hi = float(block.min()), float(block.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"volume holds NaN or infinite values near voxel {tuple(start)}")
    if not lo <= level <= hi or lo == hi:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    verts, faces, _normals, _values = marching_cubes(block, level)
    world = (verts.astype(np.float64) + np.asarray(start, np.float64)) * np.asarray(
        spacing, np.float64) + np.asarray(origin, np.float64)
    return world.astype(np.float32), faces.astype(np.uint32)


def brick_grid(shape: Sequence[int], brick: int = DEFAULT_BRICK,
               cuts: Sequence[Sequence[int]] | None = None):
    """All bricks of a volume, x slowest.

    Parameters
    ----------
    shape : (3,) voxels per axis.
    brick : most cells per brick edge.
    cuts : optional per-axis voxel cut planes (see :func:`axis_bricks`).

    Returns
    -------
    list of ((i, j, k) brick index, (start (3,), stop (3,)) voxel ranges).
    """
    per_axis = [axis_bricks(int(shape[a]), brick, None if cuts is None else cuts[a])
                for a in range(3)]
    return [
        ((i, j, k), ((rx[0], ry[0], rz[0]), (rx[1], ry[1], rz[1])))
        for i, rx in enumerate(per_axis[0])
        for j, ry in enumerate(per_axis[1])
        for k, rz in enumerate(per_axis[2])
    ]


def iter_brick_triangles(volume, level: float, brick: int = DEFAULT_BRICK,
                         spacing: Sequence[float] = (1.0, 1.0, 1.0),
                         origin: Sequence[float] = (0.0, 0.0, 0.0),
                         progress: bool = False, cuts: Sequence[Sequence[int]] | None = None
                         ) -> Iterator[tuple[tuple[int, int, int], np.ndarray, np.ndarray]]:
    """Isosurface a volume brick by brick, x slowest.

    Parameters
    ----------
    volume : array-like of shape (nx, ny, nz) indexed ``[x, y, z]`` that supports basic
        slicing (numpy array, ``np.memmap``, a transposed memmap, a nibabel ArrayProxy, or
        :class:`FieldVolume`); only one brick is read at a time. A slice may return ``None``
        to say "no surface in this brick" (procedural fields).
    level : iso value.
    brick : most cells per brick edge.
    spacing, origin : (3,) world voxel size and position of voxel (0, 0, 0).
    progress : show a tqdm bar on stderr.
    cuts : optional per-axis voxel planes that must be brick boundaries (see
        :func:`axis_bricks`), e.g. the planes of a domain grid.

    Yields
    ------
    brick_index : (i, j, k) position in the brick grid (see :func:`brick_grid`)
    vertices : (V, 3) float32 world coordinates
    indices : (T, 3) uint32 into this brick's vertices
        Only bricks the level crosses are yielded.

    Notes
    -----
    The voxel layer a brick shares with an earlier neighbour is copied from that neighbour
    (:class:`_Stitcher`) rather than read again, so a field whose evaluation is not bit-exactly
    repeatable (a sum whose order depends on the brick) still gives identical vertices on both
    sides of a brick face. At most one plane of brick faces is held for this.
    """
    from vastray.scene.progressbar import Bar

    shape = tuple(int(n) for n in volume.shape)
    stitcher = _Stitcher(shape)
    for index, (start, stop) in Bar(brick_grid(shape, brick, cuts), desc="isosurface",
                                     unit="brick", disable=not progress, leave=False):
        raw = volume[start[0]:stop[0], start[1]:stop[1], start[2]:stop[2]]
        if raw is None:
            stitcher.skip(start, stop)
            continue
        block = np.array(raw, dtype=np.float32)
        stitcher.apply(block, start, stop)
        verts, faces = march_brick(block, level, start, spacing, origin)
        if len(faces):
            yield index, verts, faces


class _Stitcher:
    """Carries each brick's high faces to the neighbour that shares them.

    Bricks come x slowest; a brick's low face along an axis is the high face of the brick just
    before it along that axis, stored under (axis, plane, the other two voxel ranges).
    """

    def __init__(self, shape: Sequence[int]):
        self.shape = tuple(shape)
        self.faces: dict[tuple, np.ndarray] = {}

    @staticmethod
    def _key(axis: int, plane: int, start, stop) -> tuple:
        others = tuple((start[a], stop[a]) for a in range(3) if a != axis)
        return (axis, plane, others)

    def apply(self, block: np.ndarray, start, stop) -> None:
        """Overwrite the brick's low faces with its neighbours', then keep its high faces."""
        for axis in range(3):
            face = self.faces.pop(self._key(axis, start[axis], start, stop), None)
            if face is not None:
                np.moveaxis(block, axis, 0)[0] = face
        for axis in range(3):
            if stop[axis] < self.shape[axis]:
                self.faces[self._key(axis, stop[axis] - 1, start, stop)] = (
                    np.moveaxis(block, axis, 0)[-1].copy())

    def skip(self, start, stop) -> None:
        """A brick without surface: forget the faces stored for it."""
        for axis in range(3):
            self.faces.pop(self._key(axis, start[axis], start, stop), None)


class FieldVolume:
    """A lazily evaluated volume: slicing calls a field function on index ranges.

    Parameters
    ----------
    field : ``field(x_range, y_range, z_range) -> (nx, ny, nz) float32 array``, or ``None`` when
        the field is known not to cross any iso level of interest in that box (the brick is
        then skipped without evaluation).
    shape : (3,) voxels per axis.
    """

    def __init__(self, field: Field, shape: Sequence[int]):
        self.field = field
        self.shape = tuple(int(s) for s in shape)

    def __getitem__(self, key: tuple[slice, slice, slice]) -> np.ndarray | None:
        ranges = [range(*s.indices(n)) for s, n in zip(key, self.shape, strict=True)]
        return self.field(*ranges)


def iter_field_triangles(field: Field, shape: Sequence[int], level: float,
                         brick: int = DEFAULT_BRICK,
                         spacing: Sequence[float] = (1.0, 1.0, 1.0),
                         origin: Sequence[float] = (0.0, 0.0, 0.0),
                         progress: bool = False, cuts: Sequence[Sequence[int]] | None = None):
    """:func:`iter_brick_triangles` over a procedural field evaluated brick by brick.

    Parameters
    ----------
    field : ``field(x_range, y_range, z_range) -> (nx, ny, nz) float32`` or ``None``
        (see :class:`FieldVolume`).
    shape : (3,) voxels per axis.
    level, brick, spacing, origin, progress, cuts : as in :func:`iter_brick_triangles`.
    """
    return iter_brick_triangles(FieldVolume(field, shape), level, brick, spacing, origin,
                                progress, cuts)
