"""Temporal-coherence scheduling (Xu et al., TVCG 2022, §4-§5): pure functions, no asyncio.

Frame t uses the counters of frame t-1 (``FrameStats``, SUM-reduced over nodes) twice:

* **Domain assignment** (Algorithm 1, ``assign_temporal``; with cache affinity,
  ``assign_affinity``, the default): the image is cut into one screen
  tile per node (``screen_tiles``); each tile's *AssignmentUnit* is seeded with the domain whose
  projected box overlaps the tile most (``projected_rects``); the units then grow, the unit with
  the fewest domains taking the unassigned domain that exchanged the *fewest* rays with it (rays
  between nodes are cheaper than loads, so domains that trade rays go to different nodes); the
  units are bound to nodes, the unit with the most bytes to the node that loads fastest. The
  comparators of the paper's Table 2 are ``sequential_owners`` and ``spatial_owners``.
* **Preload priority** (Eq 1-4, ``priority``): while the active domain renders, every other local
  domain is scored by Eq 1's terms, as the paper's difference
  ``P(n,d) = (1 - Dep'(d)) * (Q_PRED(d)/S_PROC(d) - T_LOAD(n,d))`` (``cost-benefit``) or as
  a ratio, work per second of loading (``cost-rate``, the default: see ``priority``), or by
  one of the Table 2 ablation priorities (``PRIORITIES``). ``best`` is the next active
  domain (d* is picked among the domains still cached once the active one is loaded,
  ``resident_after_load``), ``victim`` the domain to evict.

Readings (implementation note ``shared/notes/temporal-coherence.md``, S12): R(A,B) = s(A,B)/s(A)
(the paper's literal s(A,B)/r(A) behind ``literal=True``); r(A) counts every ray A processes; the
diagonal s(A,A) is ignored everywhere; Eq 4 is guarded; Eq 1 is implemented literally, so when
its bracket is negative (1 - Dep') favours *far* domains (S12.4).

Conventions: D domains, P nodes (= units = tiles); pixel index ``y * width + x`` with row 0 at
the top of the image (``Camera.generate``); tiles and pixel rectangles are ``(x0, y0, x1, y1)``,
half-open; ties go to the lower id everywhere.

Modules, one job each: ``screen`` (screen tiles, projected boxes), ``stats`` (``FrameStats``),
``assignment`` (Algorithm 1, the Table 2 comparators, a frame's assignment by kind),
``priority`` (Eq 1-4 and the picks made from the scores), ``choice`` (``TemporalChoice``, a
node's d* rule: what to trace, preload and evict). This package re-exports their public names,
so callers write ``from vastray.schedule import temporal as plan``.
"""

from vastray.schedule.temporal.assignment import (
    ASSIGNMENTS,
    Assignment,
    assign_affinity,
    assign_frame,
    assign_temporal,
    eye_domain,
    groups_fit,
    sequential_owners,
    spatial_owners,
)
from vastray.schedule.temporal.choice import CacheView, Choice, TemporalChoice
from vastray.schedule.temporal.priority import (
    PRIORITIES,
    RESIDENT_COST_S,
    PriorityInputs,
    best,
    bootstrap_priority,
    dep_prime,
    load_time,
    potential,
    priority,
    resident_after_load,
    victim,
)
from vastray.schedule.temporal.screen import pixel_tiles, projected_rects, screen_tiles
from vastray.schedule.temporal.stats import FrameStats

__all__ = [
    "ASSIGNMENTS",
    "PRIORITIES",
    "RESIDENT_COST_S",
    "Assignment",
    "CacheView",
    "Choice",
    "FrameStats",
    "assign_affinity",
    "assign_frame",
    "PriorityInputs",
    "TemporalChoice",
    "assign_temporal",
    "best",
    "bootstrap_priority",
    "dep_prime",
    "eye_domain",
    "groups_fit",
    "load_time",
    "pixel_tiles",
    "potential",
    "priority",
    "projected_rects",
    "resident_after_load",
    "screen_tiles",
    "sequential_owners",
    "spatial_owners",
    "victim",
]
