"""An estimate of what each path of a sort-first sweep costs, from the domain boxes its
camera ray crosses, so the nodes' bands of the image cost alike
(``ownership.weighted_band_cuts``).

A path whose camera ray misses every domain costs one ray; one that enters the data costs a
path's bounces, more where its ray crosses more domains. The estimate is read off a coarse
grid of camera rays (at most ``GRID`` x ``GRID``, one ray a cell) against the domain boxes
(their occupied cells where the store has masks), before anything is loaded: a few thousand
box walks, the same integers on every node.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: Cells along each image axis the estimate is read at (fewer where the image has fewer pixels).
GRID = 64
#: Weight of a domain crossed by a cell's camera ray, against 1 for the ray itself: a path
#: that enters the data traces its bounces (measured by replay: cuts at 1 + 4 x crossings
#: gave 0.81 / 0.99 weak efficiency at 4 / 64 nodes, the paths' own recorded work 0.80 /
#: 0.97, equal bands 0.58 / 0.78).
PER_DOMAIN = 4
#: The schedulers whose bands are cut by this estimate (the others': equal paths). ``image``
#: gains (replayed at 2^18 paths on 1,439 domains, session 49: speed-up at 64 / 1,024 nodes
#: 7.33 / 18.85 against 5.93 / 15.75, weak efficiency 0.97 against 0.78). ``spec-ooc`` keeps
#: bands of equal paths: replayed round by round as its nodes go (session 51), the cut wins at
#: 2^20 paths (4.14 / 2.96 / 2.09 s on 64 / 256 / 1,024 nodes against 4.93 / 3.70 / 2.54 s,
#: weak efficiency at 1,024 nodes 1.03 against 0.83) but loses at 2^18 (speed-up at 64 nodes
#: 4.78 against 5.46, weak efficiency 0.77 against 0.88, winning only at 1,024: 7.61 against
#: 6.47): a narrow band over the data still loads and activates most of its domains, which a
#: weight per path cannot say. Real nodes on this 2-core machine cannot tell them apart (rm
#: 128³, 2 nodes: the busier node 1.76 / 1.84 s cut against 1.82 / 1.93 s; 4 nodes sharing
#: the cores 6.77 against 6.69 s, 398 loads against 367). Equal bands hold the weak-scaling
#: goal (0.80) at both sizes. ``bench/replay_variants.py`` section 4 prints both for both.
CUT_BY_COST = frozenset({"image"})


def pixel_weights(camera, geometry, width: int, height: int) -> np.ndarray:
    """(width * height,) int64 estimated cost of each pixel's paths: 1 + ``PER_DOMAIN`` x the
    domains the camera ray through its cell of the coarse grid crosses.

    Parameters
    ----------
    camera : the render's ``Camera`` (in the domains' frame).
    geometry : the domains' ``DomainGeometry``.
    """
    cols, rows = min(GRID, width), min(GRID, height)
    cell_col = (np.arange(cols) * width + width // 2) // cols  # a pixel inside each cell
    cell_row = (np.arange(rows) * height + height // 2) // rows
    pixel = (cell_row[:, None] * width + cell_col[None, :]).ravel().astype(np.uint32)
    origin, direction = camera.generate(pixel, np.zeros(len(pixel), np.uint32), 0)
    limit = np.full(len(pixel), np.inf, np.float32)
    ray, _, _, _ = geometry.crossings(origin.astype(np.float32), direction.astype(np.float32),
                                      limit)
    cell = 1 + PER_DOMAIN * np.bincount(ray, minlength=len(pixel)).astype(np.int64)
    col_cell = np.arange(width) * cols // width  # each pixel's cell
    row_cell = np.arange(height) * rows // height
    return cell.reshape(rows, cols)[row_cell[:, None], col_cell[None, :]].ravel()


class SweepWeights:
    """The summed weight before any path of a sweep of passes, and of each pass alone
    (``of_pass``: ``ownership.weighted_band_cuts``' ``weight_before`` of that pass, as
    ``ownership.sort_first_sweep_paths`` cuts each pass): pass after pass, each pixel-major
    (as ``driver.paths_context`` and ``sort_first.PassSpans`` number paths), every sample of
    a pixel weighing the pixel's weight.

    Parameters
    ----------
    pixel : (W * H,) int64 each pixel's weight (``pixel_weights``).
    per_pixel : (K,) int64 samples a pixel in each pass of the sweep.
    """

    def __init__(self, pixel: np.ndarray, per_pixel: np.ndarray):
        self.pixel = np.asarray(pixel, np.int64)
        self.before_pixel = np.concatenate([[0], np.cumsum(self.pixel)])  # (W * H + 1,)
        self.per_pixel = np.asarray(per_pixel, np.int64)
        n = len(self.pixel)
        self.offsets = np.concatenate([[0], np.cumsum(n * self.per_pixel)])  # (K + 1,) paths
        self.weight_offsets = np.concatenate(  # (K + 1,) weight before each pass
            [[0], np.cumsum(int(self.before_pixel[-1]) * self.per_pixel)])

    def of_pass(self, k: int) -> Callable[[np.ndarray], np.ndarray]:
        """Pass ``k`` alone's ``weight_before``: (n,) int64 ids of its own paths (0 to its
        paths) to (n,) int64 the weight of its paths before each."""
        offset, before = int(self.offsets[k]), int(self.weight_offsets[k])
        return lambda ids: self(np.asarray(ids, np.int64) + offset) - before

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        """(n,) int64 the weight of the sweep's paths before each of (n,) ``ids``."""
        ids = np.asarray(ids, np.int64)
        k = np.clip(np.searchsorted(self.offsets, ids, side="right") - 1, 0,
                    len(self.per_pixel) - 1)
        local = ids - self.offsets[k]
        spp = self.per_pixel[k]
        px = np.minimum(local // spp, len(self.pixel))
        inside = np.where(px < len(self.pixel), local % spp, 0)
        safe = np.minimum(px, len(self.pixel) - 1)
        return (self.weight_offsets[k] + spp * self.before_pixel[px]
                + inside * self.pixel[safe])
