"""The sizes of scene float32 ray tracing resolves, and the refusal of the others.

Embree intersects in float32. Scaled up, the scene breaks where its ray-triangle test's
products of three coordinate differences overflow float32 (3.4e38, the cube of 7e12): the far
scene of ``tests/scenes.py`` renders exactly 5.2e12 across and 12 % too dark 7.8e12 across.
Scaled down, camera rays still find the right surfaces 1e-12 across, but rays leaving a
surface miss nearby ones: the image is exact 2.6e-7 across, within the seed-to-seed noise
1.6e-8 across (mean +0.02 %), and 0.3 % off 1e-8 across, 8-10 % below. Either way the image
is wrong with no error, so a scene outside the bounds below is refused, with a factor to
rescale it by. (Moving a scene away from the origin is another matter, handled by the
store's frame: ``store.frame_for``.)

Measured with ``python bench/numerics.py --scales`` (the scene scaled with its camera and
light, against the unit-scale image, 64x48, 8 spp); a 200x200 terrain 4 units across (AO and
path tracing) breaks at the same scales. The bounds keep a margin of 5-7 times above the
large break and 10 times below the small one.
"""

from __future__ import annotations

import math
import os

import numpy as np

from vastray.scene.errors import InputError

#: The smallest scene (its largest side) vastray renders: 10 times the 1e-8 wide one that
#: came out 0.3 % wrong, 20 times under the 2e-6 wide ones the tests render exactly.
MIN_EXTENT = 1e-7

#: The largest scene vastray renders: 5 times under the 5.2e12 wide one that rendered
#: exactly, 8 times under the 7.8e12 wide one that came out wrong.
MAX_EXTENT = 1e12


def check_extent(bounds: np.ndarray, where: str | os.PathLike, redo: str) -> None:
    """Refuse a scene too small or too large for float32 ray tracing.

    Parameters
    ----------
    bounds : (2, 3) float64 the scene's box (any frame: only its size counts).
    where : the store or mesh file to name.
    redo : what to do once the data is rescaled ("partition it again").

    Raises
    ------
    InputError
        Naming ``where``, the scene's extent, the bound it crosses and a factor to rescale by.
    """
    extent = float(np.max(np.asarray(bounds, np.float64)[1] - np.asarray(bounds)[0]))
    if not math.isfinite(extent) or extent == 0.0:  # no triangles, or the store's own checks
        return
    if MIN_EXTENT <= extent <= MAX_EXTENT:
        return
    factor = 10.0 ** -round(math.log10(extent))  # to about one unit across
    if extent < MIN_EXTENT:
        problem = f"is below the {MIN_EXTENT:g} that float32 ray tracing resolves"
    else:
        problem = f"is above the {MAX_EXTENT:g} that float32 ray tracing holds"
    raise InputError(where, f"scene extent {extent:.3g} {problem} (rays would miss surfaces); "
                            f"rescale the data, e.g. multiply its coordinates by {factor:g}, "
                            f"and {redo}")
