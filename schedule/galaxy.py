"""The asynchronous domain-decomposition baseline's decisions (Galaxy, as the temporal-coherence
paper runs it, Xu et al. 2022 §7): when a node takes in the camera rays of its next tile, which
of its domains it traces now and which it loads meanwhile."""

from __future__ import annotations

from collections.abc import Set

import numpy as np

from vastray.schedule.image import fullest


class GalaxyPolicy:
    """One node's choices in the ``async`` schedule.

    Parameters
    ----------
    credit : most rays waiting on the node before it injects another tile's camera rays
        (credit-based flow control: the tile size).
    resident_first : trace a cached domain with waiting rays before loading another, the
        fullest first (the out-of-core schedules' rule); False is Galaxy's own order, the
        fullest queue whatever it costs to load.
    """

    def __init__(self, credit: int, resident_first: bool = True):
        self.credit, self.resident_first = credit, resident_first

    def admits_tile(self, waiting: np.ndarray) -> bool:
        """Whether to inject the next tile now: fewer than ``credit`` rays wait ((D,) counts)."""
        return int(waiting.sum()) < self.credit

    def choose(self, waiting: np.ndarray, cached: Set[int] = frozenset()
               ) -> tuple[int, int | None]:
        """The domain to trace now and the one to load meanwhile, for ``waiting`` ((D,) rays
        per domain, some > 0) and the domains in memory: the fullest queue and the second
        fullest (lowest id on ties); with ``resident_first`` the fullest cached domain with
        rays goes before any other, for both."""
        cached = frozenset(cached) if self.resident_first else frozenset()
        active = fullest(waiting, cached)
        rest = waiting.copy()
        rest[active] = 0
        upcoming = fullest(rest, cached - {active}) if rest.any() else None
        return active, upcoming
