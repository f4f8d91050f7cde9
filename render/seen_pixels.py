"""The pixels whose camera rays can meet something: the image's cover of the scene's occupied
cells, so that camera rays elsewhere are neither made nor queried.

A render already leaves out the camera rays that miss the box of everything (the store and its
quad lights, ``integrators.seen_camera_rays``). Inside that box most of a scan is empty: of the
embryo scan's camera rays at 256², 47 % enter its box and 9 % hit it. Each domain's occupancy
mask (``scene.occupancy``: a coarse grid over its box, a cell set where a triangle's box
meets it) says where triangles can be; projecting every occupied cell's box into the image
gives the pixels a hit can lie in (18 % of the embryo's), and camera rays of other pixels
escape at once, as those that miss the box do: the image is the same bit for bit.

Conservative by construction. A pinhole camera's ray through the image point (column, row)
holds exactly the points that project to (column, row) (``Camera.generate``: its direction is
``forward + sx right + sy up``). A hit Embree reports lies on a triangle, so in an occupied
cell, up to Embree's error (a few float32 ulps of the largest coordinate involved); the
float32 ray it was found on lies within float32 rounding of the float64 ray the camera made.
Each cell box is grown by ``pad`` (``seen_camera_rays``' pad, ``2^-18`` of the largest
coordinate involved: far beyond both), so the float64 ray meets the grown box, and its image
point lies in the grown box's image. Where every corner of a box lies in front of the camera
(depth above ``pad``), the box's image is the convex hull of its corners' (a perspective
projection keeps convexity in front of the camera), inside the rectangle of the corners'
columns and rows, which is rasterised with one pixel more on each side against the rounding of
float64's projection. A box reaching the camera's plane has no bounded image: then no pixel is
left out (``None``).

Cost. One projection per occupied cell (at most 4,096 a domain: ``occupancy.RESOLUTION``),
rasterised through a summed-area table (four writes a cell, whatever its size on screen), in
one compiled pass once per render. A store with more than ``MAX_BOXES`` occupied
cells projects its domain boxes instead (a looser cover, no more work than a domain's).
"""

from __future__ import annotations

import weakref

import numpy as np
from numba import njit

from vastray.render.camera import Camera
from vastray.scene import occupancy
from vastray.scene.store import Store

#: Most cell boxes projected: beyond it, the non-empty domains' boxes are.
MAX_BOXES = 1 << 20


#: ``occupied_boxes`` of each open store (and whether masks were on): every node's render
#: set-up asks, and a simulation's virtual nodes share one store (28 ms a time for 1,439
#: domains).
_BOXES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def occupied_boxes(store: Store) -> tuple[np.ndarray, np.ndarray]:
    """The boxes where triangles of ``store`` can be, in the store's frame: every occupied
    cell of each non-empty domain's occupancy mask, or the domain's box where it has none
    (an old store's, a tiny domain's one cell, or masks off: ``VASTRAY_OCCUPANCY=0``).
    Computed once per store (read-only arrays).

    Returns
    -------
    lo, hi : (n, 3) float64 each
    """
    enabled = occupancy.enabled()
    known = _BOXES.get(store)
    if known is None or known[0] != enabled:
        lo, hi = _occupied_boxes(store, enabled)
        lo.setflags(write=False)
        hi.setflags(write=False)
        known = _BOXES[store] = (enabled, lo, hi)
    return known[1], known[2]


def _occupied_boxes(store: Store, enabled: bool) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = store.domain_boxes()
    nonempty = [d for d, info in enumerate(store.domains) if info.n_triangles > 0]
    masks = {d: store.domains[d].occupancy for d in nonempty} if enabled else {}
    cells = sum(int(m.sum()) if (m := masks.get(d)) is not None else 1 for d in nonempty)
    if cells > MAX_BOXES:
        masks = {}
    los, his = [], []
    for d in nonempty:
        mask = masks.get(d)
        if mask is None:
            los.append(lo[d][None])
            his.append(hi[d][None])
            continue
        cell = occupancy.cell_size(lo[d], hi[d], mask.shape)
        index = np.argwhere(mask).astype(np.float64)
        los.append(lo[d] + index * cell)
        his.append(lo[d] + (index + 1.0) * cell)
    if not los:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(los), np.concatenate(his)


def pixel_cover(camera: Camera, lo: np.ndarray, hi: np.ndarray, pad: float
                ) -> np.ndarray | None:
    """The pixels a ray of ``camera`` can meet any of the boxes ``[lo, hi]`` ((n, 3) each,
    grown by ``pad`` here) through.

    Returns
    -------
    (H * W,) bool, pixel index ``row * width + column`` (row 0 at the top); None where a
    box reaches the camera's plane (every pixel can).
    """
    forward, right, up = camera.frame()
    covered = np.zeros(camera.width * camera.height, np.bool_)
    bounded = _cover(np.ascontiguousarray(lo, np.float64).reshape(-1, 3),
                     np.ascontiguousarray(hi, np.float64).reshape(-1, 3), float(pad),
                     np.asarray(camera.position, np.float64), forward, right, up,
                     float(np.tan(np.radians(camera.fov) / 2.0)), camera.width, camera.height,
                     covered)
    return covered if bounded else None


@njit(nogil=True, cache=True, error_model="numpy")
def _cover(lo, hi, pad, position, forward, right, up, tan_half, width, height, out):
    """``pixel_cover``'s pixels into ``out`` ((height * width,) bool, all False on entry);
    False (``out`` incomplete) where a box reaches the camera's plane.

    Each box's eight corners (grown by ``pad``) are projected as ``Camera.generate`` maps
    image points to directions, their columns' and rows' range widened by a pixel on each
    side, and the rectangles are summed in one table (+1 at a rectangle's first pixel, -1
    past its last column and past its last row, +1 past both): its 2-D running sum counts the
    rectangles over each pixel, at four writes a box whatever its size on screen.
    """
    aspect = width / height
    marks = np.zeros((height + 1, width + 1), np.int32)
    for b in range(lo.shape[0]):
        c_min, c_max, r_min, r_max = np.inf, -np.inf, np.inf, -np.inf
        for k in range(8):
            x = (hi[b, 0] + pad if k & 1 else lo[b, 0] - pad) - position[0]
            y = (hi[b, 1] + pad if k & 2 else lo[b, 1] - pad) - position[1]
            z = (hi[b, 2] + pad if k & 4 else lo[b, 2] - pad) - position[2]
            depth = x * forward[0] + y * forward[1] + z * forward[2]
            if not depth > pad:
                return False
            sx = (x * right[0] + y * right[1] + z * right[2]) / depth
            sy = (x * up[0] + y * up[1] + z * up[2]) / depth
            column = (sx / (tan_half * aspect) + 1.0) * (width / 2.0)
            row = (1.0 - sy / tan_half) * (height / 2.0)
            c_min, c_max = min(c_min, column), max(c_max, column)
            r_min, r_max = min(r_min, row), max(r_max, row)
        c0, c1 = _span(c_min, c_max, width)
        r0, r1 = _span(r_min, r_max, height)
        if c0 <= c1 and r0 <= r1:  # on the image at all
            marks[r0, c0] += 1
            marks[r0, c1 + 1] -= 1
            marks[r1 + 1, c0] -= 1
            marks[r1 + 1, c1 + 1] += 1
    above = np.zeros(width + 1, np.int32)  # the running sums of the rows above
    for r in range(height):
        run = 0
        for c in range(width):
            run += marks[r, c]
            above[c] += run
            out[r * width + c] = above[c] > 0
    return True


@njit(inline="always", nogil=True, error_model="numpy")
def _span(first, last, size):
    """The pixel columns (or rows) ``[a, b]`` holding the image coordinates ``first .. last``
    with one more on each side, clipped to ``0 .. size - 1`` (``a > b``: none on the
    image)."""
    a = np.floor(min(max(first, -2.0), size + 2.0)) - 1.0
    b = np.floor(min(max(last, -2.0), size + 2.0)) + 1.0
    return np.int64(max(a, 0.0)), np.int64(min(b, size - 1.0))
