"""Simplified-model tracing and virtual portals (Xu et al. 2022, §4.2 and §6): which rays leave
the fine domains for the node's resident simplified model of the whole scene.

Policies (``--simplified POLICY``; the paper's Table 3 columns):

- ``portal`` (the paper's method, "D>0&R<t"): camera rays and their shadow rays are fine;
  a depth-1 ray is fine until it leaves the domain of the hit that spawned it, through that
  domain's virtual portal; there the portal's recorded radiance for the crossing cell and
  direction predicts what the ray will bring back, and a prediction at most ``threshold``
  sends it on through the simplified model from the portal point; every ray of depth >= 2
  is simplified.
- ``depth>K`` (K = 0, 1, 2): rays of depth > K are simplified from their origin; no portals.
- ``none``: nothing is simplified (the lossless control: the image is the reference image).

A shadow ray uses the model of the hit that spawned it, and a path that reached the
simplified model stays there: simplified rays are traced where they are, never sent to
another node.

Recording frames (every ``--portal-interval``-th) trace every depth-1 ray fine and record, in
the cell where it crossed its portal, the direct light its hit receives divided by the ray's
throughput (luminance; a miss or a fully shadowed hit records 0), keeping the maximum per cell.

Prediction accuracy (ACC, notes S9) is measured in a separate instrumented run (the job's
``portal_accuracy`` option): every frame is traced as a recording frame, each path's depth-1
crossing is logged with the radiance it brought back, and the crossings are classified with
the portals the timed run would predict that frame with (``schedule.portals``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

#: Depth of the first rays a policy simplifies regardless of portals (None: no such depth).
POLICY_PATTERN = re.compile(r"^(none|portal|depth>([0-2]))$")


def check_policy(policy: str) -> str:
    """``policy`` if it names a policy, else ValueError saying which exist."""
    if not POLICY_PATTERN.match(policy):
        raise ValueError(f"unknown simplified-model policy {policy!r}; expected portal, "
                         "depth>0, depth>1, depth>2 or none")
    return policy


def box_exit(origins: np.ndarray, directions: np.ndarray, lo: np.ndarray, hi: np.ndarray
             ) -> np.ndarray:
    """(n,) float64 distance at which each ray leaves its box ((n, 3) ``lo``/``hi``)."""
    o = origins.astype(np.float64)
    d = directions.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        far = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
    return np.nanmin(far, axis=1)


@dataclass
class SimplifiedRouting:
    """What a node's schedules need to route rays to the simplified model.

    Parameters
    ----------
    bvh : the simplified whole-scene model, built (``DomainBVH`` with id ``domain``), or None
        for the ``none`` policy.
    domain : the model's pseudo domain id (the store's domain count): hits on it carry it.
    policy : see the module docstring.
    lo, hi : (D, 3) domain boxes (portals sit on their faces).
    portals : the recorded portals (``schedule.portals.Portals``), or None without ``portal``.
    recording : this frame records portals (every depth-1 ray fine) rather than predicts.
    threshold : predicted radiance at or below which a depth-1 ray is simplified.
    log : an instrumented recording frame's ``schedule.portals.CrossingLog`` (which cell
        each path's depth-1 ray crossed, and the radiance it brought back), or None (the
        default: nothing logged, as in every timed run).
    reference : with ``log``, the portals a timed run would predict this frame with (those
        of the last recording frame), to classify the logged crossings with (ACC), or None.
    keeps_portals : whether the portals recorded this frame replace the ones predicted with
        (False on an instrumented run's frames that a timed run would not record).
    fresh : in a predicting frame that accumulates (``--portal-memory``), empty portals that
        record the depth-1 rays traced fine (predicted high or never recorded), folded into
        the portals at the frame's end (``Portals.refresh``); None: predicting frames record
        nothing (the paper).
    """

    bvh: object
    domain: int
    policy: str
    lo: np.ndarray
    hi: np.ndarray
    portals: object = None
    recording: bool = False
    threshold: float = 0.5
    log: object = None
    reference: object = None
    keeps_portals: bool = True
    fresh: object = None
    counters: dict = field(default_factory=lambda: {
        "simplified_rays": 0, "simplified_shadow_rays": 0, "portal_crossings": 0,
        "predicted_low": 0, "portal_records": 0})

    def __post_init__(self):
        check_policy(self.policy)
        match = POLICY_PATTERN.match(self.policy)
        self.first_simplified_depth = (int(match.group(2)) + 1 if match.group(2)
                                       else 2 if self.policy == "portal" else None)
        if self.policy == "portal" and self.portals is None:
            raise ValueError("the portal policy needs portals")

    @property
    def uses_portals(self) -> bool:
        return self.policy == "portal"

    @property
    def records(self) -> bool:
        """Whether this frame records the radiance of depth-1 rays that cross a portal: a
        recording frame every one of them, an accumulating one those it traces fine."""
        return self.uses_portals and (self.recording or self.fresh is not None)

    @property
    def record_into(self):
        """The portals this frame's records go into."""
        return self.portals if self.recording else self.fresh

    def simplified_at_start(self, depth: np.ndarray, spawned_in: np.ndarray | None
                            ) -> np.ndarray:
        """(n,) bool: new radiance rays traced on the simplified model from their origin: by
        depth, or because their path already reached the model."""
        out = np.zeros(len(depth), bool)
        if self.first_simplified_depth is not None:
            out |= depth >= self.first_simplified_depth
        if spawned_in is not None:
            out |= spawned_in == self.domain
        return out

    def portal_exit(self, origins, directions, spawned_in: np.ndarray) -> np.ndarray:
        """(n,) float32 distance to the portal of each ray's spawning domain (inf: none)."""
        out = np.full(len(spawned_in), np.inf, np.float32)
        valid = (spawned_in >= 0) & (spawned_in < self.domain)
        if valid.any():
            home = spawned_in[valid]
            out[valid] = box_exit(origins[valid], directions[valid], self.lo[home],
                                  self.hi[home])
        return out

    def trace(self, origins: np.ndarray, directions: np.ndarray, t_start: np.ndarray,
              t_far: np.ndarray) -> dict:
        """Closest hits on the simplified model between ``t_start`` and ``t_far`` (the
        ray restarts at the portal point); Embree output with ``tfar`` from the origin."""
        start = t_start.astype(np.float32)[:, None]
        moved = (origins + start * directions).astype(np.float32)
        limit = np.maximum(t_far - t_start, 0).astype(np.float32)
        r = self.bvh.intersect(moved, directions, limit)
        r["tfar"] = np.where(r["primID"] >= 0, r["tfar"] + t_start, r["tfar"]).astype(np.float32)
        return r

    def occluded(self, origins, directions, t_max) -> np.ndarray:
        return self.bvh.occluded(origins, directions, t_max)

