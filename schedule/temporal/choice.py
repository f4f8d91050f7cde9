"""What one node traces next and loads meanwhile under the temporal-coherence scheduler (Xu et
al., TVCG 2022, §5.2): a policy object over plain data, no queues, cache or asyncio.

``TemporalChoice`` holds what a frame knows before it starts (the previous frame's summed
``FrameStats``, this node's domains, Dep', the domain sizes); each call of ``choose`` is given
what the node sees now (rays waiting per domain, the cache's contents, loads since the frame
began, rays arrived from other nodes) and answers with a ``Choice``: the active domain, the
domain to preload, and the priorities and protected set the cache evicts by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vastray.schedule.temporal.priority import (
    PRIORITIES,
    PriorityInputs,
    best,
    bootstrap_priority,
    priority,
    resident_after_load,
    victim,
)
from vastray.schedule.temporal.stats import FrameStats

__all__ = ["CacheView", "Choice", "TemporalChoice", "worth_loading"]


@dataclass(frozen=True)
class CacheView:
    """The node's domain cache as the policy sees it.

    Attributes
    ----------
    resident : ids cached or being loaded.
    capacity : most domains resident at once.
    """

    resident: frozenset[int]
    capacity: int


@dataclass(frozen=True)
class Choice:
    """One answer of ``TemporalChoice.choose``.

    Attributes
    ----------
    active : the domain to trace now.
    preload : the domain to load meanwhile, or None (nothing worth a load).
    priorities : (D,) float64 the cache evicts by (lowest first; -inf: no candidate).
    protect : ids never to evict for a preload: the active domain and d*.
    """

    active: int
    preload: int | None
    priorities: np.ndarray
    protect: frozenset[int]


class TemporalChoice:
    """The d* rule of §5.2: activate d* if it has rays, else the best-scored domain with rays;
    then score the rest with the active domain's expected sends (Eq 3), name the best one d*
    and load it meanwhile if that is worth a load.

    ``cost-rate`` picks the active domain by the rays queued now (its score with Q_POT and the
    act term left out) and keeps the predicted rays for d* (the preload) and eviction. The
    paper's rule activates d* whenever it has a ray: with our short render steps, a domain
    ranked first for the rays it is predicted to receive was activated for the few it held,
    again and again, and the render time of a frame with every domain cached grew frame by
    frame as the statistics fed on those activations (bench/README.md, issue 26: 0.55 s of
    tracing per node, then 0.75, then 1.05; 0.55 each frame with this rule).

    Parameters
    ----------
    kind : one of ``PRIORITIES``; frame 0 (``previous`` None) uses ``bootstrap_priority``.
    previous : the previous frame's statistics summed over nodes, or None (frame 0).
    rank : this node (its S_LOAD is ``previous.s_load()[rank]``).
    local : (D,) bool, this node's domains (``Assignment.owns``).
    dep : (D,) Dep'(d) (``dep_prime``).
    domain_bytes : (D,) V(d).
    """

    def __init__(self, kind: str, previous: FrameStats | None, rank: int, local: np.ndarray,
                 dep: np.ndarray, domain_bytes: np.ndarray):
        if kind not in PRIORITIES:
            raise ValueError(f"unknown priority {kind!r}; expected one of {PRIORITIES}")
        self.kind = bootstrap_priority(kind) if previous is None else kind
        self.local, self.dep, self.domain_bytes = local, dep, domain_bytes
        n = len(local)
        self.upcoming: int | None = None  # d*, named by the last call
        if previous is not None:
            self.R = previous.transmission_ratio()
            self.R_pair = previous.pair_ratio()
            self.s_proc = previous.s_proc()
            self.s_load = float(previous.s_load()[rank % len(previous.load_s)])
            self.q_pre = previous.sent[~local].sum(axis=0).astype(np.float64)
            self.n_pre = previous.loads.astype(np.float64)
        else:
            self.R, self.R_pair = np.zeros(n), np.zeros((n, n))
            self.s_proc, self.s_load = np.ones(n), 1.0
            self.q_pre, self.n_pre = np.zeros(n), np.zeros(n)

    @property
    def needs_traversal_score(self) -> bool:
        """Whether ``choose`` needs SpRay's traversal score of the queued rays."""
        return self.kind == "spray"

    def choose(self, waiting: np.ndarray, cache: CacheView | None, n_cur: np.ndarray,
               arrived: np.ndarray, traversal_score: np.ndarray | None = None) -> Choice:
        """The active domain, the one to preload, and what the cache evicts by.

        Parameters
        ----------
        waiting : (D,) int rays queued at this node per domain (Q_CUR); at least one > 0.
        cache : the cache now, or None (no cache: nothing counts as resident, d* is the
            preload unguarded).
        n_cur : (D,) loads of each domain since the frame began (N_CUR of Eq 4).
        arrived : (D,) rays received from other nodes' domains this frame (Q_CUR_RECV).
        traversal_score : (D,) SpRay's score of the queued rays (``needs_traversal_score``).

        Returns
        -------
        Choice; the cache should be handed ``priorities`` and ``protect``. With a cache the
        preload is d* only when ``worth_loading``.
        """
        now = _Now(waiting, cache, n_cur, arrived, traversal_score)
        present = self.kind == "cost-rate"  # pick by the rays queued now, no d* carry-over
        previous = None if present else self.upcoming
        if previous is not None and waiting[previous]:
            active = previous
        else:
            scores = np.where(waiting > 0, self._scores(now, None, 0, present=present), -np.inf)
            active = best(scores)
            if active is None:  # rays only in domains that are no candidates: the fullest
                active = int(np.argmax(waiting))
        scores = self._scores(now, active, int(waiting[active]), self._resident_after(now, active))
        upcoming = best(scores)
        self.upcoming = upcoming
        protect = frozenset({active} | ({upcoming} if upcoming is not None else set()))
        if cache is None:
            return Choice(active, upcoming, scores, protect)
        worth = worth_loading(upcoming, scores, protect, cache)
        return Choice(active, upcoming if worth else None, scores, protect)

    def _resident_after(self, now: _Now, active: int) -> set[int] | None:
        """The domains resident once ``active`` is (None: no cache). Loading it into a full
        cache evicts the lowest-scored other one, which must not then count as cached when d*
        is picked: with one slot, d* would be the domain the load just evicted, and the node
        would load two domains that trade rays in turn, one activation each."""
        if now.cache is None:
            return None
        resident = now.cache.resident
        if active in resident or len(resident) < now.cache.capacity:
            return set(resident) | {active}  # nothing is evicted: skip scoring twice
        return resident_after_load(resident, now.cache.capacity, active,
                                   self._scores(now, active, int(now.waiting[active])))

    def _scores(self, now: _Now, active: int | None, q_act: int,
                resident_set: set[int] | None = None, present: bool = False) -> np.ndarray:
        """Every domain's priority (``priority``) for what is queued now, with the domains of
        ``resident_set`` counted as cached (default: the cache's); ``present``: for the rays
        queued now alone (no Q_POT)."""
        resident = np.zeros(len(now.waiting), bool)
        if resident_set is None and now.cache is not None:
            resident_set = now.cache.resident
        if resident_set:
            resident[list(resident_set)] = True
        inputs = PriorityInputs(
            q_cur=now.waiting.astype(np.float64), active=active, q_act=q_act, R=self.R,
            R_pair=self.R_pair, q_pre=np.zeros_like(self.q_pre) if present else self.q_pre,
            q_cur_recv=now.arrived.astype(np.float64),
            n_pre=self.n_pre, n_cur=now.n_cur, s_proc=self.s_proc,
            domain_bytes=self.domain_bytes, s_load_n=self.s_load, resident=resident,
            dep=self.dep, local=self.local, spray_score=now.traversal_score)
        return priority(self.kind, inputs)


def worth_loading(domain: int | None, scores: np.ndarray, protect: frozenset[int],
                  cache: CacheView) -> bool:
    """Whether to preload ``domain`` now: it is not resident, and the cache has room or the
    domain it would evict (the lowest of ``scores`` outside ``protect``) ranks below it. Our
    render steps are short (a domain's queue takes milliseconds, not the paper's seconds), so
    without this guard a fresh d* every step would evict domains worth more than itself."""
    if domain is None or domain in cache.resident:
        return False
    if len(cache.resident) < cache.capacity:
        return True
    going = victim(scores, list(cache.resident), set(protect))
    return going is not None and scores[going] < scores[domain]


@dataclass(frozen=True)
class _Now:
    """The inputs of one ``choose`` call (see there)."""

    waiting: np.ndarray
    cache: CacheView | None
    n_cur: np.ndarray
    arrived: np.ndarray
    traversal_score: np.ndarray | None
