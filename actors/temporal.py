"""``temporal``: the temporal-coherence paper's scheduler (Xu et al., TVCG 2022) on the
asynchronous runtime of ``async``.

Each frame every node owns one *assignment unit*: a screen tile (it makes the camera rays of
those pixels) and a group of domains (the only ones it may load). Rays for another node's
domain travel there without global rounds, as in ``async``; the frame ends with one
termination detection. What the previous frame taught drives this one:

- **assignment** (``--assignment``): ``paper`` is Algorithm 1 over the previous frame's ray
  transmissions s(A, B) and the nodes' loading speeds; ``affinity`` (the default) is
  Algorithm 1 where the domains a node held at the last frame's end stay its own unless
  moving one is predicted to save more than its load (frame 0, with no statistics yet, uses
  ``spatial`` for both); ``spatial`` gives each node a contiguous z-order run of domains; ``sequential``
  deals domains round robin.
- **priority** (``--priority``): which local domain to trace next and which to load meanwhile,
  scored by Q_CUR (``queue``), SpRay's traversal score (``spray``), Q_CUR plus the rays the
  active domain will send (``queue+act``), the paper's cost-benefit Eq. 1-4 as written
  (``cost-benefit``: predicted work minus load time), Eq. 1's terms as a ratio (``cost-rate``,
  the default: predicted work per second of loading) or Q_CUR with cached domains first
  (``queue+resident``, the cache-aware baseline); frame 0, with no statistics yet, uses
  ``schedule.temporal.bootstrap_priority``. The preloader loads the best-scored domain while
  the active one is traced, and evicts the lowest-scored one.
- **statistics**: s(A, B), r(A), loads per domain, S_PROC and S_LOAD are counted during the
  frame and summed over nodes by the tree-reduce actor at its end, so every node plans the
  next frame from the same numbers (and so computes the same assignment, with no coordinator
  in the loop).

Rays meet the same domains in the same order as on one node, so the image is the reference
image whatever the assignment and priority.

Every decision is ``schedule.temporal``'s (``assign_frame``, ``TemporalChoice``); this module
feeds them from the queues, the messages and the preloader, and passes their answers on.
"""

from __future__ import annotations

import numpy as np

from vastray.actors.async_frame import AsyncFrame
from vastray.scene.errors import InputError
from vastray.schedule import temporal as plan
from vastray.schedule.image import ImageSchedule
from vastray.schedule.traversal import count_ahead, traversal_score

#: Most domains the temporal scheduler plans for: its statistics hold a (D, D) matrix of
#: transmissions (8 MB at 1,024 domains), summed over nodes once per frame.
MAX_TEMPORAL_DOMAINS = 2048


def domain_table(store) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi, nonempty, domain_bytes) of the store's domains: what the temporal policies
    read of a store ((D, 3), (D, 3), (D,) bool, (D,) float64)."""
    lo, hi = store.domain_boxes()
    nonempty = np.array([d.n_triangles > 0 for d in store.domains])
    return lo, hi, nonempty, np.array([d.nbytes for d in store.domains], np.float64)


def frame_assignment(kind: str, store, camera, width: int, height: int, size: int,
                     previous: plan.FrameStats | None, capacity: int | None = None
                     ) -> plan.Assignment:
    """This frame's assignment units (``plan.assign_frame`` over the store's domains; a node's
    cache holds ``capacity`` domains, the same on every node of a job)."""
    return plan.assign_frame(kind, camera, *domain_table(store), width, height, size, previous,
                             capacity)


class TemporalFrame(AsyncFrame):
    """One node's frame under ``temporal`` (see the module docstring).

    Parameters
    ----------
    assignment : this frame's units; node ``rank`` renders ``assignment.tiles[rank]``.
    priority : one of ``schedule.temporal.PRIORITIES``.
    previous : the previous frame's statistics summed over nodes, or None (frame 0).
    Others as for ``AsyncFrame``.
    """

    def __init__(self, node, setup, settings, assignment: plan.Assignment, rank: int,
                 size: int, tile: int, film, store, priority: str,
                 previous: plan.FrameStats | None, on_tile=None, base: int = 0,
                 status_label: int = 0, simple=None):
        owner = assignment.routes_from(rank)
        super().__init__(node, setup, settings, owner, rank, size, tile, film, on_tile,
                         base=base, status_label=status_label, simple=simple)
        self.assignment, self.previous = assignment, previous
        self.local = assignment.owns(rank)
        self.pixel_node = plan.pixel_tiles(assignment.tiles, settings.width, settings.height)
        n = len(owner)
        self.stats = plan.FrameStats.zeros(n, size)  # this node's share, summed at frame end
        self.arrived = np.zeros(n, np.int64)  # Q_CUR_RECV: rays received from other nodes
        lo, hi, nonempty, domain_bytes = domain_table(store)
        self.plan = plan.TemporalChoice(priority, previous, rank, self.local,
                                        plan.dep_prime(setup.camera.position, lo, hi, nonempty),
                                        domain_bytes)
        self.nonlocal_loads = 0  # loads of domains outside this node's group (none, ever)
        self.loads_before: dict[int, int] = {}

    # -- the async frame's hooks ------------------------------------------------------------
    def policy(self, tile: int) -> ImageSchedule:
        policy = super().policy(tile)
        policy.tally = self.stats
        return policy

    def my_paths(self, policy) -> np.ndarray:
        """Rows of the tile's paths whose pixel lies in this node's screen tile."""
        return np.nonzero(self.pixel_node[policy.ctx.pixel] == self.rank)[0]

    def accept(self, message) -> bool:
        delivered = super().accept(message)
        if delivered and message.arrays:  # Q_CUR_RECV: rays from other nodes' domains
            np.add.at(self.arrived, np.asarray(message.arrays["domain"], np.int64), 1)
        return delivered

    def choose(self, waiting: np.ndarray) -> tuple[int, int | None]:
        """The policy's choice (``TemporalChoice.choose``) for what this node holds now; the
        cache is handed the priorities and protected set it evicts by."""
        cache = plan.CacheView(self.preloader.resident(), self.preloader.capacity)
        n_cur = np.zeros(len(waiting))  # N_CUR: loads since the frame began
        for d, count in self.preloader.loads_per_domain().items():
            n_cur[d] = count - self.loads_before.get(d, 0)
        score = self._traversal_score() if self.plan.needs_traversal_score else None
        choice = self.plan.choose(waiting, cache, n_cur, self.arrived, score)
        self.preloader.prioritise(choice.priorities, choice.protect)
        return choice.active, choice.preload

    def _traversal_score(self) -> np.ndarray:
        """SpRay's front-to-back traversal score (``schedule.traversal``) over the rays queued
        here, each counted from where it is now (a radiance ray up to its closest hit so far)."""
        n = len(self.owner)
        counter = np.zeros((n, n), np.int64)
        for policy in self.policies.values():
            for queues, limit in ((policy.radiance, "hit_t"), (policy.shadow, "t_max")):
                for rays in (c for d in np.nonzero(queues.counts())[0] for c in queues.peek(d)):
                    count_ahead(counter, self.setup.geometry, rays["origin"], rays["direction"],
                                rays[limit], rays["at_t"])
        return traversal_score(counter).astype(np.float64)

    def traced(self, domain: int, rays: int, seconds: float) -> None:
        self.stats.proc_rays[domain] += rays
        self.stats.proc_s[domain] += seconds

    async def run(self) -> None:
        preloader = self.preloader
        self.loads_before = preloader.loads_per_domain()
        before = preloader.stats()
        await super().run()
        after = preloader.stats()
        for d, count in preloader.loads_per_domain().items():
            self.stats.loads[d] += count - self.loads_before.get(d, 0)
        self.nonlocal_loads = int(self.stats.loads[~self.local].sum())
        self.stats.load_bytes[self.rank] += after["bytes_loaded"] - before["bytes_loaded"]
        self.stats.load_s[self.rank] += after["load_s"] - before["load_s"]
        self.stats.held[self.rank, sorted(preloader.resident())] = 1


async def summed_stats(tree, stats: plan.FrameStats) -> plan.FrameStats:
    """The frame's statistics summed over every node (the same on each), by the tree-reduce
    actor's all-reduction (log2 P butterfly steps)."""
    arrays = stats.to_arrays()
    total = await tree.allreduce(arrays, {name: "sum" for name in arrays})
    return plan.FrameStats.from_arrays(total)


def check_temporal_domains(store) -> None:
    """Refuse a store too large for the (D, D) transmission statistics, saying what to do."""
    n_domains = len(store.domains)
    if n_domains > MAX_TEMPORAL_DOMAINS:
        raise InputError(store.path, f"--scheduler temporal plans at most "
                                     f"{MAX_TEMPORAL_DOMAINS} domains (its statistics are a "
                                     f"domains x domains matrix); this store has {n_domains}: "
                                     "use --scheduler async, or partition into fewer domains")
