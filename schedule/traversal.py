"""SpRay's front-to-back traversal score (Park et al., §4.1.2): which domains the queued rays
reach first.

``Counter[i][j]`` counts the queued rays for which domain i is the j-th box still ahead along
the ray (j = 0: the nearest); ``Score[i] = sum_j (M - j) * Counter[i][j]`` for ``Counter``
(N, M). ``spec_ooc`` keeps its counter as it queues rays and orders a round by the score
(``traversal_order``); the temporal scheduler's ``spray`` priority counts the rays queued at a
node (``count_ahead``) and scores them the same way.
"""

from __future__ import annotations

import numpy as np

from vastray.schedule.geometry import DomainGeometry

__all__ = ["count_ahead", "traversal_score"]


def traversal_score(counter: np.ndarray) -> np.ndarray:
    """``Score[i] = sum_j (M - j) * Counter[i][j]``.

    Parameters
    ----------
    counter : (N, M) int, rays per domain (row) and position along the ray (column).

    Returns
    -------
    (N,) of ``counter``'s dtype (int64 for an int64 counter: exact).
    """
    m = counter.shape[1]
    return counter @ (m - np.arange(m))


def count_ahead(counter: np.ndarray, geometry: DomainGeometry, origins: np.ndarray,
                directions: np.ndarray, limit: np.ndarray, start: np.ndarray) -> None:
    """Add rays to ``counter``: ``counter[d, j] += 1`` for every ray whose j-th domain still
    ahead is d, the domains ahead being those it enters at or after ``start`` and before
    ``limit`` (``DomainGeometry.crossings``).

    Parameters
    ----------
    counter : (D, M) int64, updated in place; M must exceed the most domains one ray crosses
        (M = D always does).
    geometry : the domain boxes.
    origins, directions : (n, 3) float32 rays.
    limit : (n,) float32, where each ray ends (its closest hit so far, a shadow ray's length).
    start : (n,) where each ray is now (a box entered before it lies behind the ray).
    """
    ray, domain, entry, _ = geometry.crossings(origins, directions, limit)
    ahead = entry >= start[ray]
    ray, domain = ray[ahead], domain[ahead]
    # crossings come sorted by ray, then entry: a ray's j-th row is its j-th domain ahead
    first = np.full(len(origins), len(ray), np.int64)
    np.minimum.at(first, ray, np.arange(len(ray)))
    np.add.at(counter, (domain, np.arange(len(ray)) - first[ray]), 1)
