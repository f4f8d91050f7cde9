"""The domain crossings of one frame, traced once, for the simulator's replay (``sim.replay``).

The rays a lossless render traces do not depend on its schedule: every scheduler's rays visit
the same domains in the same front-to-back order (``schedule.image``), and a speculative one
sends copies into the domains a ray crosses beyond the ones it needs. So one real render,
traced with Embree on one process, says everything the schedules' costs depend on: for each
*segment* (a camera or continuation ray, or a shadow ray) the path it belongs to, the segment
whose hit spawned it, the domains it was traced in (``visits``) and the domains its line
crosses up to its limit (``crossed``: where a speculative schedule's copies go). Replaying
those for every scheduler and node count costs a few array operations per activation instead
of a trace, which is what lets the simulator reach the papers' work per node (issue 38).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from vastray.actors.render_setup import RenderSetup
from vastray.render.driver import path_context
from vastray.render.film import Film
from vastray.render.integrators import RenderSettings, camera_rays
from vastray.render.scene_config import SceneConfig
from vastray.scene.embree.launch import cpu_time
from vastray.scene.errors import InputError
from vastray.scene.store import Store
from vastray.schedule.geometry import DomainGeometry
from vastray.schedule.image import ImageSchedule
from vastray.schedule.soa import GrowingArray, SoA

RADIANCE, SHADOW = 0, 1
#: What a recording's file holds, and the version a reader accepts.
FORMAT = 2


@dataclass
class Crossings:
    """One frame's segments and the domains each visits (structure of arrays, S segments).

    Attributes
    ----------
    kind : (S,) int8, ``RADIANCE`` (a camera or continuation ray) or ``SHADOW``.
    path : (S,) int64, the pass-wide id of the segment's path (``pixel * spp + sample``).
    depth : (S,) int16, bounces before the segment (a shadow ray: its hit's radiance ray's).
    parent : (S,) int64, the radiance segment whose hit spawned it (-1: a camera ray).
    visit_first : (S + 1,) int64 offsets into ``visit_domain``.
    visit_domain : (V,) int32, the domains each segment was traced in, in order (a
        lossless non-speculative schedule's activations: the last is where a radiance ray's
        closest hit was final or a shadow ray was blocked or left the scene).
    crossed_first : (S + 1,) int64 offsets into ``crossed_domain``.
    crossed_domain : (C,) int32, the occupied domains along each segment's line, front to
        back, up to its limit (a radiance ray: none; a shadow ray: its light): where a
        speculative schedule sends copies before any hit is known.
    n_domains, n_paths : the store's domains and the frame's paths.
    ray_bytes : (2,) bytes of one radiance and one shadow ray on the wire (their SoA rows).
    activation_rays : (A, 2) int64 radiance and shadow rays of each activation of the
        recording run (one process, every domain in memory).
    activation_cpu_s : (A,) CPU seconds each of those activations took (the recording's own
        bookkeeping left out): what this store's activations cost, to which
        ``sim.replay.fit_activation_costs`` fits a fixed and a per-ray cost.
    decision_cpu_s : (A,) CPU seconds the schedule took to choose each activation's domain.
    query_rays : (Q, 2) int64, each Embree query call of the recording: its kind
        (``RADIANCE``: closest hit, ``SHADOW``: occlusion) and rays.
    query_cpu_s : (Q,) CPU seconds of each.
    """

    kind: np.ndarray
    path: np.ndarray
    depth: np.ndarray
    parent: np.ndarray
    visit_first: np.ndarray
    visit_domain: np.ndarray
    crossed_first: np.ndarray
    crossed_domain: np.ndarray
    n_domains: int
    n_paths: int
    ray_bytes: np.ndarray
    activation_rays: np.ndarray
    activation_cpu_s: np.ndarray
    decision_cpu_s: np.ndarray
    query_rays: np.ndarray
    query_cpu_s: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def visits(self) -> np.ndarray:
        """(S,) int64 domains each segment is traced in."""
        return np.diff(self.visit_first)

    @property
    def copies(self) -> np.ndarray:
        """(S,) int64 domains each segment's line crosses (its speculative copies)."""
        return np.diff(self.crossed_first)

    def children(self) -> tuple[np.ndarray, np.ndarray]:
        """The segments each segment's hit spawned, as CSR: ``first`` ((S + 1,) int64) and
        ``child`` (segment ids grouped by parent, in launch order)."""
        spawned = np.nonzero(self.parent >= 0)[0]
        order = spawned[np.argsort(self.parent[spawned], kind="stable")]
        counts = np.bincount(self.parent[spawned], minlength=len(self))
        return np.concatenate([[0], np.cumsum(counts)]), order

    def repeated(self, times: int) -> Crossings:
        """The frame's paths ``times`` over, as more samples of the same pixels would trace
        (the same rays: a workload of ``times`` the paths with the same crossings per path,
        for weak scaling). Path ``p`` of copy ``k`` is path ``k * n_paths + p``."""
        if times == 1:
            return self
        n, k = len(self), np.arange(times)
        seg_shift = np.repeat(k * n, n)

        def offsets(first: np.ndarray) -> np.ndarray:
            step = first[-1]
            return np.concatenate([(first[:-1][None, :] + step * k[:, None]).ravel(),
                                   [step * times]]).astype(np.int64)

        parent = np.tile(self.parent, times)
        parent = np.where(parent >= 0, parent + seg_shift, -1)
        # the recording run's costs stay: the same store's
        repeated = replace(self, kind=np.tile(self.kind, times),
                           path=np.tile(self.path, times) + np.repeat(k * self.n_paths, n),
                           depth=np.tile(self.depth, times), parent=parent,
                           visit_first=offsets(self.visit_first),
                           visit_domain=np.tile(self.visit_domain, times),
                           crossed_first=offsets(self.crossed_first),
                           crossed_domain=np.tile(self.crossed_domain, times),
                           n_paths=self.n_paths * times)
        #: paths of the frame repeated (not saved with the recording): a replay may give
        #: work on the same paths of each copy the same result
        repeated.period = self.n_paths
        return repeated

    def subset(self, stride: int) -> Crossings:
        """Every ``stride``-th path of the frame (an image-wide sample of its work), path
        ``stride * q`` becoming path ``q``."""
        if stride <= 1:
            return self
        keep = self.path % stride == 0
        kept = np.nonzero(keep)[0]
        new_id = np.cumsum(keep) - 1
        parent = self.parent[kept]
        parent = np.where(parent >= 0, new_id[np.maximum(parent, 0)], -1)

        def rows(first: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            counts = first[kept + 1] - first[kept]
            return (np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                    values[ranges(first[kept], counts)])

        visit_first, visit_domain = rows(self.visit_first, self.visit_domain)
        crossed_first, crossed_domain = rows(self.crossed_first, self.crossed_domain)
        return replace(self, kind=self.kind[kept], path=self.path[kept] // stride,
                       depth=self.depth[kept], parent=parent, visit_first=visit_first,
                       visit_domain=visit_domain, crossed_first=crossed_first,
                       crossed_domain=crossed_domain, n_paths=-(-self.n_paths // stride))

    def save(self, path: str | Path) -> None:
        """Write the recording as one ``.npz`` (to a temporary name, then renamed)."""
        path = Path(path)
        partial = path.with_name(path.name + ".partial.npz")
        np.savez(partial, format=FORMAT, **{f.name: getattr(self, f.name) for f in fields(self)})
        partial.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> Crossings:
        """Read a recording written by ``save``; a clear ``InputError`` names a bad file."""
        path = Path(path)
        try:
            with np.load(path) as data:
                if int(data["format"]) != FORMAT:
                    raise InputError(path, f"crossings format {int(data['format'])} is not "
                                           f"{FORMAT}; record it again")
                values = {f.name: data[f.name] for f in fields(cls)}
        except (OSError, KeyError, ValueError) as exc:
            raise InputError(path, f"not a crossings recording: {exc}") from None
        values["n_domains"] = int(values["n_domains"])
        values["n_paths"] = int(values["n_paths"])
        return cls(**values)


class CrossingLog:
    """What ``ImageSchedule`` tells a recording (its ``crossing_log``): segments as they are
    launched, batches as they are traced."""

    def __init__(self, geometry: DomainGeometry):
        self.geometry = geometry
        self.kind = GrowingArray(np.int8)
        self.path = GrowingArray(np.int64)
        self.depth = GrowingArray(np.int16)
        self.parent = GrowingArray(np.int64)
        self.traced_seg = GrowingArray(np.int64)
        self.traced_domain = GrowingArray(np.int32)
        self.crossed_seg = GrowingArray(np.int64)
        self.crossed_domain = GrowingArray(np.int32)
        self.ray_bytes = np.zeros(2, np.int64)
        self.activation_rays = GrowingArray(np.int64)
        self.activation_cpu_s = GrowingArray(np.float64)
        self.decision_cpu_s = GrowingArray(np.float64)
        self.query_rays = GrowingArray(np.int64)
        self.query_cpu_s = GrowingArray(np.float64)
        self.own_cpu_s = 0.0  # the log's own CPU time, left out of the activations'

    def launched(self, schedule: ImageSchedule, rays: SoA, parent: np.ndarray | None
                 ) -> np.ndarray:
        """(n,) int64 segment ids for new rays ``rays`` of ``schedule``'s tile (``parent``:
        their spawning segments, None for camera rays); records each one's line's domains."""
        cpu = cpu_time()
        n = len(rays)
        kind = RADIANCE if "hit_t" in rays.fields else SHADOW
        ids = np.arange(len(self.kind), len(self.kind) + n, dtype=np.int64)
        parent = np.full(n, -1, np.int64) if parent is None else parent.astype(np.int64)
        if kind == RADIANCE:
            depth = rays["depth"].astype(np.int16)
            limit = np.full(n, np.inf, np.float32)
        else:
            depth = self.depth.values[parent]
            limit = rays["t_max"].astype(np.float32)
        self.kind.append(np.full(n, kind, np.int8))
        self.path.append(schedule._path_ids(rays["path"]))
        self.depth.append(depth)
        self.parent.append(parent)
        self.ray_bytes[kind] = max(self.ray_bytes[kind], rays.nbytes() // max(n, 1))
        self._walk(ids, rays["origin"], rays["direction"], limit)
        self.own_cpu_s += cpu_time() - cpu
        return ids

    def _walk(self, ids, origin, direction, limit) -> None:
        """Record the occupied domains along each ray before ``limit``, front to back (one
        vectorised step per domain crossed)."""
        at_t = np.full(len(ids), -np.inf, np.float32)
        at_d = np.full(len(ids), -1, np.int32)
        rows = np.arange(len(ids))
        while len(rows):
            nxt, entry = self.geometry.next_domain(origin[rows], direction[rows], at_t[rows],
                                                   at_d[rows], limit[rows])
            moving = nxt >= 0
            rows, nxt, entry = rows[moving], nxt[moving], entry[moving]
            self.crossed_seg.append(ids[rows])
            self.crossed_domain.append(nxt.astype(np.int32))
            at_t[rows], at_d[rows] = entry, nxt

    def traced(self, domain: int, seg: np.ndarray) -> None:
        """Segments ``seg`` ((m,)) traced in ``domain``."""
        cpu = cpu_time()
        self.traced_seg.append(seg.astype(np.int64))
        self.traced_domain.append(np.full(len(seg), domain, np.int32))
        self.own_cpu_s += cpu_time() - cpu

    def activation(self, radiance: int, shadow: int, cpu_s: float, decision_s: float) -> None:
        """One activation of the recording run traced these rays in ``cpu_s`` CPU seconds,
        the log's own share included (left out here), after ``decision_s`` choosing it."""
        self.activation_rays.append(np.array([radiance, shadow], np.int64))
        self.activation_cpu_s.append(np.array([max(cpu_s - self.own_cpu_s, 0.0)]))
        self.decision_cpu_s.append(np.array([decision_s]))
        self.own_cpu_s = 0.0

    def query(self, kind: int, rays: int, cpu_s: float) -> None:
        """One Embree query call of ``rays`` rays took ``cpu_s``."""
        self.query_rays.append(np.array([kind, rays], np.int64))
        self.query_cpu_s.append(np.array([cpu_s]))

    def crossings(self, n_domains: int, n_paths: int) -> Crossings:
        """The recording (each segment's visits in the order they were traced)."""
        n = len(self.kind)
        visit_first, visit_domain = _csr(self.traced_seg.values, self.traced_domain.values, n)
        crossed_first, crossed_domain = _csr(self.crossed_seg.values,
                                             self.crossed_domain.values, n)
        return Crossings(self.kind.values.copy(), self.path.values.copy(),
                         self.depth.values.copy(), self.parent.values.copy(), visit_first,
                         visit_domain, crossed_first, crossed_domain, n_domains, n_paths,
                         self.ray_bytes.copy(), self.activation_rays.values.reshape(-1, 2).copy(),
                         self.activation_cpu_s.values.copy(),
                         self.decision_cpu_s.values.copy(),
                         self.query_rays.values.reshape(-1, 2).copy(),
                         self.query_cpu_s.values.copy())


class _TimedQueries:
    """A domain's BVH whose query calls tell the log their rays and CPU time (everything
    else is the BVH's own)."""

    def __init__(self, bvh, log: CrossingLog):
        self._bvh, self._log = bvh, log

    def __getattr__(self, name):
        return getattr(self._bvh, name)

    def intersect(self, origins, *args, **kwargs):
        start = cpu_time()
        result = self._bvh.intersect(origins, *args, **kwargs)
        self._log.query(RADIANCE, len(origins), cpu_time() - start)
        return result

    def occluded(self, origins, *args, **kwargs):
        start = cpu_time()
        result = self._bvh.occluded(origins, *args, **kwargs)
        self._log.query(SHADOW, len(origins), cpu_time() - start)
        return result


def ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The concatenated ranges ``start .. start + count`` ((sum counts,) int64)."""
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.empty(0, np.int64)
    offsets = np.repeat(np.asarray(starts, np.int64) - np.cumsum(counts) + counts, counts)
    return offsets + np.arange(total, dtype=np.int64)


def _csr(seg: np.ndarray, value: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Values grouped by segment (a stable sort keeps each segment's order): offsets (n + 1,)
    and the values."""
    order = np.argsort(seg, kind="stable")
    first = np.concatenate([[0], np.cumsum(np.bincount(seg, minlength=n))]).astype(np.int64)
    return first, value[order]


def record_crossings(store: Store, settings: RenderSettings, config: SceneConfig | None = None,
                     tile: int = 65536, get_domain=None) -> tuple[Crossings, Film]:
    """Trace one frame on one process, every domain in memory, and record its crossings.

    Parameters
    ----------
    store, settings, config : the render.
    tile : paths traced at once (the recording does not depend on it).
    get_domain : ``domain id -> DomainBVH`` (default: a ``sim.cache.Domains`` built here).

    Returns
    -------
    The crossings, and the frame's film (the render's image: equal to the reference).
    """
    from vastray.sim.cache import Domains

    config = SceneConfig() if config is None else config
    setup = RenderSetup.of(store, config, settings)
    own = get_domain is None
    domains = Domains(store, setup.keep) if own else None
    get_domain = domains.get if own else get_domain
    log = CrossingLog(setup.geometry)
    film = Film(settings.width, settings.height)
    total = setup.total_paths
    try:
        for first in range(0, total, tile):
            ctx = path_context(setup.shading, settings, first, min(first + tile, total),
                               setup.ao_distance)
            policy = ImageSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range)
            policy.crossing_log = log
            policy.start(camera_rays(setup.camera, ctx))
            while True:
                start = cpu_time()
                domain = policy.next_domain()
                decision = cpu_time() - start
                if domain is None:
                    break
                bvh = _TimedQueries(get_domain(domain), log)
                rays = (policy.radiance.count(domain), policy.shadow.count(domain))
                log.own_cpu_s = 0.0
                start = cpu_time()
                policy.process(domain, bvh)
                log.activation(int(rays[0]), int(rays[1]), cpu_time() - start,
                               decision)
            film.add_paths(ctx.pixel, ctx.sample, policy.result)
    finally:
        if own:
            domains.close()
    return log.crossings(len(store.domains), total), film
