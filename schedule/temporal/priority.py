"""Runtime priorities of the temporal-coherence scheduler (Xu et al., TVCG 2022, Eq 1-4): how
node n scores its local domains while one renders, the Table 2 ablations, and the picks made
from the scores (``best``: the next active domain, ``victim``: the domain to evict)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from vastray.schedule.registry import PRIORITIES

__all__ = ["PRIORITIES", "RESIDENT_COST_S", "PriorityInputs", "best", "bootstrap_priority",
           "dep_prime", "load_time", "potential", "priority", "resident_after_load", "victim"]

# Preload priorities (``PRIORITIES``, named in ``schedule.registry``): the paper's Table 2
# ablation (Eq 1 is "cost-benefit"), Eq 1's terms as a ratio ("cost-rate", ``temporal``'s
# default) and the queue baseline made cache-aware ("queue+resident"), the strongest baseline
# of ``bench/temporal.py``.

#: T_LOAD floor of ``"cost-rate"``, seconds: what activating a resident domain costs (its
#: BVH is built; a queue pop and a dispatch remain). A resident domain outranks a domain that
#: must be loaded unless that one promises more than T_LOAD / RESIDENT_COST_S times the work.
RESIDENT_COST_S = 1e-3


def dep_prime(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray, nonempty: np.ndarray) -> np.ndarray:
    """Dep'(d), the normalised distance from the viewpoint to each domain (Eq 1; note S4).

    dist(eye, box d) / max over non-empty d' of |eye - farthest corner of box d'|, clipped to
    [0, 1) (a non-degenerate box is always nearer than its farthest corner, so the clip only
    bites for point boxes and for empty boxes beyond every non-empty one).

    Parameters
    ----------
    eye : (3,) viewpoint.
    lo, hi : (D, 3) domain boxes.
    nonempty : (D,) bool, the boxes that set the normalisation.

    Returns
    -------
    (D,) float64 in [0, 1); 0 for every box containing the eye; all 0 if there is no
    non-empty box (or every one is a point at the eye).
    """
    eye = np.asarray(eye, dtype=np.float64)
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    near = np.linalg.norm(np.maximum(np.maximum(lo - eye, eye - hi), 0.0), axis=1)
    far = np.linalg.norm(np.maximum(np.abs(eye - lo), np.abs(eye - hi)), axis=1)
    nonempty = np.asarray(nonempty, dtype=bool)
    scale = float(far[nonempty].max()) if nonempty.any() else 0.0
    if scale <= 0.0:
        return np.zeros(len(lo))
    return np.minimum(near / scale, np.nextafter(1.0, 0.0))


def load_time(domain_bytes: np.ndarray, s_load_n: float, resident: np.ndarray) -> np.ndarray:
    """T_LOAD(n, d) (Eq 2): 0 for a resident domain (or one being preloaded), else
    V(d) / S_LOAD(n).

    Parameters
    ----------
    domain_bytes : (D,) V(d).
    s_load_n : S_LOAD(n) of this node, bytes/s (> 0).
    resident : (D,) bool, in the cache or being loaded.

    Returns
    -------
    (D,) float64 seconds.
    """
    t = np.asarray(domain_bytes, dtype=np.float64) / float(s_load_n)
    return np.where(np.asarray(resident, dtype=bool), 0.0, t)


def potential(q_pre: np.ndarray, q_cur_recv: np.ndarray, n_pre: np.ndarray, n_cur: np.ndarray
              ) -> np.ndarray:
    """Q_POT(d) (Eq 4), guarded (note S4): max(0, Q_PRE - Q_CUR_RECV) / max(1, N_PRE - N_CUR).

    Parameters
    ----------
    q_pre : (D,) rays sent to d from non-local domains in the previous frame.
    q_cur_recv : (D,) rays d received from them so far in this frame.
    n_pre, n_cur : (D,) loads of d in the previous frame and so far in this one.

    Returns
    -------
    (D,) float64, finite and >= 0.
    """
    num = np.maximum(np.asarray(q_pre, np.float64) - np.asarray(q_cur_recv, np.float64), 0.0)
    den = np.maximum(np.asarray(n_pre, np.float64) - np.asarray(n_cur, np.float64), 1.0)
    return num / den


@dataclass
class PriorityInputs:
    """What node n knows when it scores its local domains (note S4).

    Attributes
    ----------
    q_cur : (D,) Q_CUR(d), rays queued at this node for d (radiance + shadow).
    active : the active domain ``act`` (being rendered), or None.
    q_act : Q_CUR(act), rays in act's popped queue (ignored when ``active`` is None).
    R : (D,) R(A) of the previous frame (``FrameStats.transmission_ratio``).
    R_pair : (D, D) R(A, B) of the previous frame (``FrameStats.pair_ratio``).
    q_pre, q_cur_recv, n_pre, n_cur : (D,) the inputs of Eq 4 (``potential``).
    s_proc : (D,) S_PROC(d), rays/s (``FrameStats.s_proc``).
    domain_bytes : (D,) V(d).
    s_load_n : S_LOAD(n) of this node, bytes/s.
    resident : (D,) bool, cached or being loaded.
    dep : (D,) Dep'(d) (``dep_prime``).
    local : (D,) bool, this node's local domains (``Assignment.owns``).
    spray_score : (D,) SpRay traversal score sum_j (M - j) Counter[d][j], or None (needed only
        by the "spray" priority).
    """

    q_cur: np.ndarray
    active: int | None
    q_act: int
    R: np.ndarray
    R_pair: np.ndarray
    q_pre: np.ndarray
    q_cur_recv: np.ndarray
    n_pre: np.ndarray
    n_cur: np.ndarray
    s_proc: np.ndarray
    domain_bytes: np.ndarray
    s_load_n: float
    resident: np.ndarray
    dep: np.ndarray
    local: np.ndarray
    spray_score: np.ndarray | None = None


def _act_term(inputs: PriorityInputs) -> np.ndarray:
    """(D,) Q_CUR(act) R(act) R(act, d), the rays act is expected to send to each d."""
    d = len(inputs.q_cur)
    if inputs.active is None:
        return np.zeros(d)
    act = int(inputs.active)
    return float(inputs.q_act) * float(inputs.R[act]) * np.asarray(inputs.R_pair[act], np.float64)


def priority(kind: str, inputs: PriorityInputs) -> np.ndarray:
    """The preload priority of every domain for node n.

    Candidates are the local domains other than the active one with
    Q_PRED(d) = Q_CUR(d) + Q_CUR(act) R(act) R(act, d) + Q_POT(d) > 0 (Eq 3); the same set for
    every kind, so the ablation only swaps the score:

    * ``"queue"``: Q_CUR(d) (the baseline, Table 2 "+Q_CUR");
    * ``"spray"``: the SpRay traversal score ``inputs.spray_score``;
    * ``"queue+act"``: Q_CUR(d) + Q_CUR(act) R(act) R(act, d);
    * ``"cost-benefit"``: Eq 1, literally,
      (1 - Dep'(d)) * (Q_PRED(d) / S_PROC(d) - T_LOAD(n, d)). When the bracket is negative
      (loading costs more than the predicted work), (1 - Dep') scales it towards 0 for *far*
      domains, so among such domains the far one ranks higher (note S12.4, kept literally).
      S_PROC is floored at a tiny epsilon against division by zero.
    * ``"cost-rate"``: Eq 1's benefit over its cost,
      (1 - Dep'(d)) * (Q_PRED(d) / S_PROC(d)) / max(T_LOAD(n, d), RESIDENT_COST_S): predicted
      seconds of work per second of loading. The difference form compares seconds of work
      with seconds of loading on one scale, so wherever a domain's queue traces faster than it
      loads (ours: milliseconds against tens), -T_LOAD decides alone and the node loads small
      domains holding few rays; the ratio keeps the work in every score, ranks a resident
      domain by its work alone, and is never negative, so (1 - Dep') always favours the near.
    * ``"queue+resident"``: Q_CUR(d), every resident domain (cached or being loaded) ahead of
      every one that must be loaded: the baseline given the cache awareness that the
      cost-based priorities have through T_LOAD (ties -> lower id as everywhere).

    Returns
    -------
    (D,) float64, -inf where d is not a candidate.
    """
    if kind not in PRIORITIES:
        raise ValueError(f"unknown priority {kind!r}; expected one of {PRIORITIES}")
    q_cur = np.asarray(inputs.q_cur, dtype=np.float64)
    act_term = _act_term(inputs)
    q_pot = potential(inputs.q_pre, inputs.q_cur_recv, inputs.n_pre, inputs.n_cur)
    q_pred = q_cur + act_term + q_pot
    cand = np.asarray(inputs.local, dtype=bool) & (q_pred > 0)
    if inputs.active is not None:
        cand[int(inputs.active)] = False
    if kind == "queue":
        score = q_cur
    elif kind == "spray":
        if inputs.spray_score is None:
            raise ValueError('priority "spray" needs inputs.spray_score')
        score = np.asarray(inputs.spray_score, dtype=np.float64)
    elif kind == "queue+act":
        score = q_cur + act_term
    elif kind == "queue+resident":
        # Q_CUR >= 0, so adding more than the largest one puts every resident domain first.
        lead = float(q_cur.max(initial=0.0)) + 1.0
        score = q_cur + np.where(np.asarray(inputs.resident, dtype=bool), lead, 0.0)
    else:
        t_load = load_time(inputs.domain_bytes, inputs.s_load_n, inputs.resident)
        s_proc = np.maximum(np.asarray(inputs.s_proc, dtype=np.float64), 1e-300)
        near = 1.0 - np.asarray(inputs.dep, dtype=np.float64)
        if kind == "cost-benefit":
            score = near * (q_pred / s_proc - t_load)
        else:
            score = near * (q_pred / s_proc) / np.maximum(t_load, RESIDENT_COST_S)
    return np.where(cand, score, -np.inf)


def bootstrap_priority(kind: str) -> str:
    """The priority frame 0 uses in place of ``kind``: it has no statistics yet (S_PROC,
    S_LOAD, R), so Eq 1's forms fall back to queued rays, as the paper's bootstrap frame
    does (``cost-benefit``, ``queue+act`` -> ``queue``), and ``cost-rate`` keeps its cache rule
    (-> ``queue+resident``: cached domains first, by queued rays); the others need none."""
    return {"cost-benefit": "queue", "queue+act": "queue",
            "cost-rate": "queue+resident"}.get(kind, kind)


def best(priorities: np.ndarray) -> int | None:
    """The domain with the highest priority (ties -> lower id); None if every one is -inf (or
    NaN, which counts as -inf)."""
    p = np.asarray(priorities, dtype=np.float64)
    p = np.where(np.isnan(p), -np.inf, p)
    if not len(p) or (p == -np.inf).all():
        return None
    return int(np.argmax(p))


def resident_after_load(resident: Iterable[int], capacity: int, active: int,
                        priorities: np.ndarray) -> set[int]:
    """The domains cached once ``active`` is loaded: a full cache gives up its lowest of
    ``priorities`` (``victim``) to make room. d* must be picked from these, or a domain about
    to be evicted would count as cached.

    Parameters
    ----------
    resident : ids cached (or being loaded) now.
    capacity : the cache's size in domains.
    active : the domain about to be traced (loaded first if not resident).
    priorities : (D,) from ``priority``.

    Returns
    -------
    set of ids, ``active`` included, at most ``max(capacity, 1)`` of them.
    """
    after = {int(d) for d in resident}
    if active not in after and len(after) >= capacity:
        after.discard(victim(priorities, list(after), {active}))
    return after | {int(active)}


def victim(priorities: np.ndarray, resident: list[int], protect: set[int]) -> int | None:
    """The resident domain to evict: the lowest priority among ``resident`` not in ``protect``
    (e.g. act and d*); non-candidates (-inf, NaN) rank lowest; ties -> the lower id.

    Parameters
    ----------
    priorities : (D,) from ``priority``.
    resident : ids of the cached domains.
    protect : ids never to evict.

    Returns
    -------
    The domain id, or None if every resident domain is protected.
    """
    ids = np.array(sorted({int(d) for d in resident} - {int(d) for d in protect}), dtype=np.int64)
    if not len(ids):
        return None
    p = np.asarray(priorities, dtype=np.float64)[ids]
    p = np.where(np.isnan(p), -np.inf, p)
    return int(ids[np.argmin(p)])
