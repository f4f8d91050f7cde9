"""Ambient occlusion and path tracing with next-event estimation, one batch of paths at a time.

Every path is a row of structure-of-arrays state; each step below shrinks the set of live rows
with masks, never looping over rays in Python. All randomness comes from ``render.rng`` keyed by
(seed, pixel, sample, bounce, purpose, index), so a path's radiance does not depend on which
batch, domain order or process traced it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vastray.render.lights import AmbientLight, Light, QuadLight, SampleKeys
from vastray.render.materials import MaterialTable, blinn_phong_lobe
from vastray.render.rng import Purpose, uniform2
from vastray.render.sampling import cosine_hemisphere
from vastray.render.tracer import DomainTracer, Hits

#: Spawned rays start this far (relative to the hit's coordinate magnitude plus the distance it
#: was reached from) off the surface: about 64 float32 ulps, so they never re-hit it.
SPAWN_EPSILON = 4e-6


@dataclass(frozen=True)
class RenderSettings:
    """What to render and how; see ``vastray render --help`` for meanings and defaults."""

    width: int = 320
    height: int = 240
    spp: int = 4
    integrator: str = "pt"
    bounces: int = 3
    shadow_samples: int = 16
    ao_distance: float | None = None
    seed: int = 0
    batch_size: int = 65536


@dataclass(frozen=True)
class Shading:
    """Everything the integrators need besides geometry."""

    lights: list[Light]
    materials: MaterialTable
    has_color: bool


@dataclass
class PathBatch:
    """Paths of one batch: the key of each and its accumulated radiance.

    Attributes
    ----------
    pixel, sample : (n,) uint32
    radiance : (n, 3) float64
    first_t : (n,) float32 camera-ray hit distance (inf for a miss)
    first_normal : (n, 3) float32 facing normal at the camera hit
    """

    pixel: np.ndarray
    sample: np.ndarray
    radiance: np.ndarray
    first_t: np.ndarray
    first_normal: np.ndarray


def spawn(points: np.ndarray, normals: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Ray origins just off a surface, on the side of ``normals``.

    Parameters
    ----------
    points : (k, 3) float64 hit points; normals : (k, 3) unit normals of the side to leave by;
    reach : (k,) distance from which the point was reached (its rounding error grows with it).

    Returns
    -------
    (k, 3) float64
    """
    scale = np.abs(points).max(axis=1) + reach
    return points + normals * (SPAWN_EPSILON * scale)[:, None]


def _surface(origins: np.ndarray, directions: np.ndarray, hits: Hits):
    """Hit points (float64) and normals facing the incoming ray for rows that hit."""
    rows = np.nonzero(hits.hit)[0]
    o = origins[rows].astype(np.float64)
    d = directions[rows].astype(np.float64)
    t = hits.t[rows]
    p = o + d * t[:, None]
    n = hits.normal[rows]
    facing = np.where(np.einsum("ij,ij->i", n, d) > 0, -1.0, 1.0)
    return rows, p, n * facing[:, None], d, t


def render_ao(tracer: DomainTracer, camera, shading: Shading, settings: RenderSettings,
              pixel: np.ndarray, sample: np.ndarray, ao_distance: float) -> PathBatch:
    """Ambient occlusion: the unoccluded fraction of ``shadow_samples`` cosine-weighted rays
    of length ``ao_distance`` from each camera hit, times the surface colour when there is one.
    """
    n = len(pixel)
    radiance = np.zeros((n, 3))
    o, d = camera.generate(pixel, sample, settings.seed)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    hits = tracer.intersect(o32, d32, kind="camera")
    rows, p, nf, _, t = _surface(o32, d32, hits)
    first_normal = np.zeros((n, 3), np.float32)
    first_normal[rows] = nf
    m = settings.shadow_samples
    if len(rows) and m:
        # One row per (hit, shadow sample j).
        rep = np.repeat(np.arange(len(rows)), m)
        j = np.tile(np.arange(m, dtype=np.uint64), len(rows))
        u, v = uniform2(settings.seed, pixel[rows][rep], sample[rows][rep], 1,
                        Purpose.AO_DIRECTION, j)
        wi = cosine_hemisphere(nf[rep], u, v)
        origin = spawn(p, nf, t)[rep]
        blocked = tracer.occluded(origin.astype(np.float32), wi.astype(np.float32),
                                  np.full(len(rep), ao_distance, np.float32))
        visible = np.bincount(rep, weights=~blocked, minlength=len(rows)) / m
        color = hits.color[rows] if hits.color is not None else 1.0
        radiance[rows] = visible[:, None] * color
    return PathBatch(pixel, sample, radiance, hits.t.astype(np.float32), first_normal)


def render_pt(tracer: DomainTracer, camera, shading: Shading, settings: RenderSettings,
              pixel: np.ndarray, sample: np.ndarray) -> PathBatch:
    """Path tracing: next-event estimation to every light at each of up to ``bounces + 1``
    path vertices, one cosine-weighted diffuse continuation ray per vertex.

    Emitters (quad lights, the ambient environment) are added where camera rays see them
    directly; later vertices get light only through next-event estimation, so nothing is
    counted twice.
    """
    n = len(pixel)
    radiance = np.zeros((n, 3))
    # Path state: live rows, their rays and throughput.
    live = np.arange(n)
    o, d = camera.generate(pixel, sample, settings.seed)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    beta = np.ones((n, 3))
    first_t = np.full(n, np.inf, np.float32)
    first_normal = np.zeros((n, 3), np.float32)
    for bounce in range(settings.bounces + 1):
        hits = tracer.intersect(o32, d32, kind="camera" if bounce == 0 else "bounce")
        if bounce == 0:
            first_t[:] = hits.t
            _add_visible_emitters(radiance, shading.lights, o32, d32, hits.t)
        rows, p, nf, dirs, t = _surface(o32, d32, hits)
        if bounce == 0:
            first_normal[rows] = nf
        if len(rows) == 0:
            break
        path = live[rows]
        albedo = shading.materials.diffuse[hits.material[rows]]
        if hits.color is not None:
            albedo = albedo * hits.color[rows]
        origin = spawn(p, nf, t)
        # Direct light: next-event estimation toward every light.
        keys = SampleKeys(settings.seed, pixel[path], sample[path], bounce)
        _next_event(tracer, shading, settings, radiance, path, keys, origin, nf, -dirs,
                    albedo, hits.material[rows], beta[rows])
        if bounce == settings.bounces:
            break
        # Continue the path: one cosine-weighted diffuse bounce (weight = albedo).
        u, v = uniform2(settings.seed, pixel[path], sample[path], bounce,
                        Purpose.BOUNCE_DIRECTION)
        new_dir = cosine_hemisphere(nf, u, v)
        beta = beta[rows] * albedo
        keep = np.any(beta > 0, axis=1)
        live, beta = path[keep], beta[keep]
        o32 = origin[keep].astype(np.float32)
        d32 = new_dir[keep].astype(np.float32)
        if len(live) == 0:
            break
    return PathBatch(pixel, sample, radiance, first_t, first_normal)


def _add_visible_emitters(radiance, lights, o32, d32, t_hit) -> None:
    """Camera rays see quad lights in front of the first surface, and the environment."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    for light in lights:
        if isinstance(light, QuadLight):
            seen = light.intersect(o, d) < t_hit
            radiance[seen] += light.radiance
        elif isinstance(light, AmbientLight):
            radiance[~np.isfinite(t_hit)] += light.radiance


def _next_event(tracer, shading, settings, radiance, path, keys, origin, nf, wo, albedo,
                material, beta) -> None:
    """Shadow rays from ``k`` path vertices to every light; adds unoccluded light to paths.

    Parameters
    ----------
    radiance : (n, 3) float64 per-path accumulator (modified).
    path : (k,) rows of ``radiance`` the vertices belong to.
    origin, nf, wo : (k, 3) spawned origin, facing normal, direction to the viewer.
    albedo : (k, 3); material : (k,) slots; beta : (k, 3) path throughput.
    """
    mats = shading.materials
    throughput_diffuse = beta * albedo / np.pi  # (k, 3) throughput times the Lambertian BRDF
    vertex_all, o_all, d_all, t_all, c_all = [], [], [], [], []
    for index, light in enumerate(shading.lights):
        m = settings.shadow_samples if light.stochastic else 1
        if m == 0:
            continue
        # One row per (vertex, shadow sample j), vertex-major.
        if m == 1:
            o_rep, n_rep, rep_keys, j = origin, nf, keys, 0
        else:
            o_rep, n_rep = np.repeat(origin, m, axis=0), np.repeat(nf, m, axis=0)
            rep_keys = SampleKeys(keys.seed, np.repeat(keys.pixel, m),
                                  np.repeat(keys.sample, m), keys.bounce)
            j = np.tile(np.arange(m, dtype=np.uint64), len(path))
        wi, dist, incident = light.sample(o_rep, n_rep, rep_keys, index, j)
        cos_i = np.einsum("ij,ij->i", n_rep, wi)
        useful = np.nonzero((cos_i > 0) & (incident.sum(axis=1) > 0))[0]
        if len(useful) == 0:
            continue
        vertex = useful // m
        weight = (cos_i[useful] / m)[:, None] * incident[useful]
        contribution = throughput_diffuse[vertex] * weight
        if mats.has_specular:
            lobe = blinn_phong_lobe(mats.shininess[material[vertex]], nf[vertex], wo[vertex],
                                    wi[useful])
            contribution += beta[vertex] * mats.specular[material[vertex]] * lobe[:, None] * weight
        vertex_all.append(vertex)
        o_all.append(o_rep[useful])
        d_all.append(wi[useful])
        t_all.append(dist[useful] * (1.0 - SPAWN_EPSILON))
        c_all.append(contribution)
    if not vertex_all:
        return
    vertex = np.concatenate(vertex_all)
    blocked = tracer.occluded(np.concatenate(o_all).astype(np.float32),
                              np.concatenate(d_all).astype(np.float32),
                              np.concatenate(t_all).astype(np.float32))
    lit = ~blocked
    contribution = np.concatenate(c_all)[lit]
    target = path[vertex[lit]]
    for c in range(3):
        radiance[:, c] += np.bincount(target, weights=contribution[:, c], minlength=len(radiance))
