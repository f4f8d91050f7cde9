"""Screen side of the temporal-coherence assignment (Xu et al., TVCG 2022, Algorithm 1, lines
11-12): one screen tile per node, the tile of every pixel, and the pixel rectangles the domain
boxes project to.

Conventions: pixel index ``y * width + x`` with row 0 at the top of the image
(``Camera.generate``); tiles and pixel rectangles are ``(x0, y0, x1, y1)``, half-open; ties go
to the lower id.
"""

from __future__ import annotations

from fractions import Fraction
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from vastray.render.camera import Camera

__all__ = ["pixel_tiles", "projected_rects", "screen_tiles"]


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
