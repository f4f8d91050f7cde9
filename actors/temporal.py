"""``temporal``: the temporal-coherence paper's scheduler (Xu et al., TVCG 2022) on the
asynchronous runtime of ``async``.

Each frame every node owns one *assignment unit*: a screen tile (it makes the camera rays of
those pixels) and a group of domains (the only ones it may load). Rays for another node's
domain travel there without global rounds, as in ``async``; the frame ends with one
termination detection. What the previous frame taught drives this one:

- **assignment** (``--assignment``): ``temporal`` is Algorithm 1 over the previous frame's ray
  transmissions s(A, B) and the nodes' loading speeds (frame 0, with no statistics yet, uses
  ``spatial``); ``spatial`` gives each node a contiguous z-order run of domains; ``sequential``
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
"""

from __future__ import annotations

import numpy as np

from vastray.actors.decomposition import _AsyncFrame
from vastray.scene.errors import InputError
from vastray.schedule import temporal as plan
from vastray.schedule.image import ImageSchedule

#: Most domains the temporal scheduler plans for: its statistics hold a (D, D) matrix of
#: transmissions (8 MB at 1,024 domains), summed over nodes once per frame.
MAX_TEMPORAL_DOMAINS = 2048


def frame_assignment(kind: str, store, camera, width: int, height: int, size: int,
                     previous: plan.FrameStats | None) -> plan.Assignment:
    """This frame's assignment units (the same on every node: it depends only on the store,
    the camera and the previous frame's summed statistics)."""
    lo, hi = store.domain_boxes()
    nonempty = np.array([d.n_triangles > 0 for d in store.domains])
    if kind == "sequential":
        return plan.sequential_owners(len(lo), size, nonempty, width, height)
    if kind == "spatial" or previous is None:  # frame 0: no statistics to plan from
        return plan.spatial_owners(lo, hi, size, nonempty, width, height)
    if kind != "temporal":
        raise ValueError(f"unknown assignment {kind!r}; expected one of {plan.ASSIGNMENTS}")
    tiles = plan.screen_tiles(width, height, size)
    rects = plan.projected_rects(camera, lo, hi)
    eye = plan.eye_domain(camera.position, lo, hi, nonempty)
    domain_bytes = np.array([d.nbytes for d in store.domains], np.float64)
    return plan.assign_temporal(tiles, rects, previous.sent, domain_bytes, previous.s_load(),
                                nonempty, eye)


class TemporalFrame(_AsyncFrame):
    """One node's frame under ``temporal`` (see the module docstring).

    Parameters
    ----------
    assignment : this frame's units; node ``rank`` renders ``assignment.tiles[rank]``.
    priority : one of ``schedule.temporal.PRIORITIES``.
    previous : the previous frame's statistics summed over nodes, or None (frame 0).
    Others as for ``_AsyncFrame``.
    """

    def __init__(self, node, setup, settings, assignment: plan.Assignment, rank: int,
                 size: int, tile: int, film, store, priority: str,
                 previous: plan.FrameStats | None, on_tile=None, base: int = 0,
                 status_label: int = 0, simple=None):
        owner = np.where(assignment.owner >= 0, assignment.owner, rank)
        if assignment.replicated is not None:  # the eye's domain: every node may load it
            owner[assignment.replicated] = rank
        super().__init__(node, setup, settings, owner, rank, size, tile, film, on_tile,
                         base=base, status_label=status_label, simple=simple)
        if priority not in plan.PRIORITIES:
            raise ValueError(f"unknown priority {priority!r}; expected one of "
                             f"{plan.PRIORITIES}")
        if previous is None:
            priority = plan.bootstrap_priority(priority)
        self.assignment, self.priority_kind, self.previous = assignment, priority, previous
        n = len(owner)
        self.local = assignment.owns(rank)
        self.pixel_node = plan.pixel_tiles(assignment.tiles, settings.width, settings.height)
        self.stats = plan.FrameStats.zeros(n, size)  # this node's share, summed at frame end
        self.arrived = np.zeros(n, np.int64)  # Q_CUR_RECV: rays received from other nodes
        lo, hi = store.domain_boxes()
        nonempty = np.array([d.n_triangles > 0 for d in store.domains])
        self.dep = plan.dep_prime(setup.camera.position, lo, hi, nonempty)
        self.domain_bytes = np.array([d.nbytes for d in store.domains], np.float64)
        self.upcoming: int | None = None  # d*, being preloaded
        self.nonlocal_loads = 0  # loads of domains outside this node's group (none, ever)
        self.loads_before: dict[int, int] = {}
        if previous is not None:
            self.R = previous.transmission_ratio()
            self.R_pair = previous.pair_ratio()
            self.s_proc = previous.s_proc()
            self.s_load = float(previous.s_load()[rank % len(previous.load_s)])
            self.q_pre = previous.sent[~self.local].sum(axis=0).astype(np.float64)
            self.n_pre = previous.loads.astype(np.float64)
        else:
            self.R, self.R_pair = np.zeros(n), np.zeros((n, n))
            self.s_proc, self.s_load = np.ones(n), 1.0
            self.q_pre, self.n_pre = np.zeros(n), np.zeros(n)

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
        """Activate d* if it has rays, else the best-scored domain with rays; then score the
        rest with the active domain's expected sends (Eq. 3), preload the best (d*) and evict
        by the scores, never the active domain or d*."""
        previous = self.upcoming
        if previous is not None and waiting[previous]:
            active = previous
        else:
            scores = self._scores(waiting, None, 0)
            scores = np.where(waiting > 0, scores, -np.inf)
            active = plan.best(scores)
            if active is None:  # rays only in domains that are no candidates: the fullest
                active = int(np.argmax(waiting))
        scores = self._scores(waiting, active, int(waiting[active]), self._resident_after(
            waiting, active))
        upcoming = plan.best(scores)
        self.upcoming = upcoming
        if self.preloader is None:
            return active, upcoming
        protect = {active} | ({upcoming} if upcoming is not None else set())
        self.preloader.prioritise(scores, protect)
        return active, upcoming if self._worth_loading(upcoming, scores, protect) else None

    def _worth_loading(self, domain: int | None, scores: np.ndarray, protect: set) -> bool:
        """Whether to preload ``domain`` now: it is not resident, and the cache has room or
        the domain it would evict (the lowest priority) ranks below it. Our render steps are
        short (a domain's queue takes milliseconds, not the paper's seconds), so without this
        guard a fresh d* every step would evict domains worth more than itself."""
        if domain is None:
            return False
        resident = self.preloader.resident()
        if domain in resident:
            return False
        if len(resident) < self.preloader.capacity:
            return True
        victim = plan.victim(scores, list(resident), protect)
        return victim is not None and scores[victim] < scores[domain]

    def _resident_after(self, waiting: np.ndarray, active: int) -> set[int] | None:
        """The domains resident once ``active`` is (None: no preloader). Loading it into a
        full cache evicts the lowest-scored other one, which must not then count as cached
        when d* is picked: with one slot, d* would be the domain the load just evicted, and
        the node would load two domains that trade rays in turn, one activation each."""
        if self.preloader is None:
            return None
        resident = self.preloader.resident()
        if active in resident or len(resident) < self.preloader.capacity:
            return set(resident) | {active}  # nothing is evicted: skip scoring twice
        return plan.resident_after_load(resident, self.preloader.capacity, active,
                                        self._scores(waiting, active, int(waiting[active])))

    def _scores(self, waiting: np.ndarray, active: int | None, q_act: int,
                resident_set: set[int] | None = None) -> np.ndarray:
        """Every domain's priority (``plan.priority``) for what this node has queued now,
        with the domains of ``resident_set`` counted as cached (default: the cache's)."""
        resident = np.zeros(len(waiting), bool)
        if resident_set is None and self.preloader is not None:
            resident_set = self.preloader.resident()
        if resident_set:
            resident[list(resident_set)] = True
        n_cur = np.zeros(len(waiting))
        if self.preloader is not None:
            for d, count in self.preloader.loads_per_domain().items():
                n_cur[d] = count - self.loads_before.get(d, 0)
        inputs = plan.PriorityInputs(
            q_cur=waiting.astype(np.float64), active=active, q_act=q_act, R=self.R,
            R_pair=self.R_pair, q_pre=self.q_pre, q_cur_recv=self.arrived.astype(np.float64),
            n_pre=self.n_pre, n_cur=n_cur, s_proc=self.s_proc,
            domain_bytes=self.domain_bytes, s_load_n=self.s_load, resident=resident,
            dep=self.dep, local=self.local,
            spray_score=self._spray_score() if self.priority_kind == "spray" else None)
        return plan.priority(self.priority_kind, inputs)

    def _spray_score(self) -> np.ndarray:
        """SpRay's front-to-back traversal score over the rays queued here: a ray waiting in
        a domain adds M - j to the j-th domain still ahead of it (j = 0 its queue's)."""
        n = len(self.owner)
        score = np.zeros(n)
        for policy in self.policies.values():
            for queues, limit in ((policy.radiance, "hit_t"), (policy.shadow, "t_max")):
                for rays in (c for d in np.nonzero(queues.counts())[0] for c in queues.peek(d)):
                    ray, domain, entry, _ = self.setup.geometry.crossings(
                        rays["origin"], rays["direction"], rays[limit])
                    ahead = entry >= rays["at_t"][ray]
                    ray, domain = ray[ahead], domain[ahead]
                    first = np.full(len(rays), len(ray), np.int64)
                    np.minimum.at(first, ray, np.arange(len(ray)))
                    rank = np.arange(len(ray)) - first[ray]
                    np.add.at(score, domain, n - rank)
        return score

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


async def summed_stats(tree, stats: plan.FrameStats) -> plan.FrameStats:
    """The frame's statistics summed over every node (the same on each), by the tree-reduce
    actor: ceil(log2 P) steps up, then down."""
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
