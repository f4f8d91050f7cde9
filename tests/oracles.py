"""Test oracles: the numpy chain the fused shading kernels (``render.kernels``) replace.

``shade_numpy`` turns closest hits into shadow and continuation rays, ``sample_light`` samples
one light, ``add_unoccluded_numpy`` sums unoccluded shadow rays per path: one numpy operation
at a time, in the order the kernels follow. The kernels must give the same rays and sums bit
for bit (``tests/test_kernels.py``). None of this runs in a render: ``integrators.shade`` and
``integrators.add_unoccluded`` call the kernels only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vastray.render.integrators import (
    SPAWN_EPSILON,
    PathContext,
    RadianceRays,
    ShadowRays,
    hit_points,
)
from vastray.render.lights import (
    AmbientLight,
    DirectionalLight,
    PointLight,
    QuadLight,
    shadow_rays,
)
from vastray.render.materials import blinn_phong_lobe_of_cos
from vastray.render.rng import Purpose, uniform2
from vastray.render.tracer import Hits, facing


@dataclass(frozen=True)
class SampleKeys:
    """Random-number keys of a set of path vertices: (n,) pixel, sample and bounce; seed."""

    seed: int
    pixel: np.ndarray
    sample: np.ndarray
    bounce: np.ndarray


# ---------------------------------------------------------------------------------------------
# Directions and the specular lobe
# ---------------------------------------------------------------------------------------------

def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents completing each unit normal to a frame (Duff et al. 2017).

    Parameters
    ----------
    n : (k, 3) unit vectors.

    Returns
    -------
    t, b : (k, 3) each, with ``t, b, n`` orthonormal.
    """
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(nz >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + nz)
    b_ = nx * ny * a
    t = np.empty_like(n)
    b = np.empty_like(n)
    t[:, 0] = 1.0 + sign * nx * nx * a
    t[:, 1] = sign * b_
    t[:, 2] = -sign * nx
    b[:, 0] = b_
    b[:, 1] = sign + ny * ny * a
    b[:, 2] = -ny
    return t, b


def cosine_hemisphere(n: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions about each normal (pdf = cos(theta) / pi); the kernels'
    ``_hemisphere`` row by row.

    Parameters
    ----------
    n : (k, 3) unit normals.
    u, v : (k,) uniforms in [0, 1).

    Returns
    -------
    (k, 3) unit directions with ``dot(d, n) >= 0``.
    """
    r = np.sqrt(u)
    phi = 2.0 * np.pi * v
    x, y = r * np.cos(phi), r * np.sin(phi)
    z = np.sqrt(np.maximum(0.0, 1.0 - u))
    t, b = orthonormal_basis(n)
    # Unit length already (x^2 + y^2 + z^2 = 1 in an orthonormal frame): no renormalising.
    return t * x[:, None] + b * y[:, None] + n * z[:, None]


def blinn_phong_lobe(shininess: np.ndarray, n: np.ndarray, wo: np.ndarray, wi: np.ndarray
                     ) -> np.ndarray:
    """Energy-normalised Blinn-Phong lobe ``(s + 2) / (2 pi) * cos(theta_h)^s`` from the
    directions (``materials.blinn_phong_lobe_of_cos`` of the half vector's cosine).

    Parameters
    ----------
    shininess : (k,); n, wo, wi : (k, 3) unit facing normal, directions to viewer and light.

    Returns
    -------
    (k,)
    """
    h = wo + wi
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-300)
    cos_h = np.maximum(0.0, np.einsum("ij,ij->i", n, h))
    return blinn_phong_lobe_of_cos(shininess, cos_h)


# ---------------------------------------------------------------------------------------------
# Light sampling
# ---------------------------------------------------------------------------------------------

def sample_light(light, p, n, keys: SampleKeys, light_index: int, j):
    """Sample ``light`` from points ``p`` with facing normals ``n`` ((k, 3) each).

    Returns
    -------
    wi : (k, 3) unit direction toward the light; dist : (k,) how far a shadow ray must stay
    clear (inf for lights at infinity); incident : (k, 3) incident radiance divided by the
    sampling pdf.
    """
    if isinstance(light, PointLight):
        return _sample_point(light, p)
    if isinstance(light, DirectionalLight):
        return _sample_directional(light, p)
    if isinstance(light, QuadLight):
        return _sample_quad(light, p, keys, light_index, j)
    if isinstance(light, AmbientLight):
        return _sample_ambient(light, p, n, keys, light_index, j)
    raise TypeError(f"no numpy sampling for a {type(light).__name__}")


def _sample_point(light: PointLight, p):
    to_light = light.position[None, :] - p
    dist = np.linalg.norm(to_light, axis=1)
    wi = to_light / np.maximum(dist, 1e-300)[:, None]
    return wi, dist, light.intensity[None, :] / np.maximum(dist * dist, 1e-300)[:, None]


def _sample_directional(light: DirectionalLight, p):
    wi = np.broadcast_to(-light.direction / np.linalg.norm(light.direction), p.shape)
    return wi, np.full(len(p), np.inf), np.broadcast_to(light.irradiance, p.shape)


def _sample_quad(light: QuadLight, p, keys: SampleKeys, light_index: int, j):
    s, t = uniform2(keys.seed, keys.pixel, keys.sample, keys.bounce,
                    Purpose.LIGHT_SAMPLE + 16 * light_index, j)
    q = light.corner + s[:, None] * light.edge1 + t[:, None] * light.edge2
    to_light = q - p
    dist2 = np.einsum("ij,ij->i", to_light, to_light)
    dist = np.sqrt(dist2)
    wi = to_light / np.maximum(dist, 1e-300)[:, None]
    area_normal = light.area_normal
    area = np.linalg.norm(area_normal)
    cos_light = np.maximum(0.0, -_facing(wi, area_normal) / area)
    weight = light.radiance[None, :] * (cos_light * area / np.maximum(dist2, 1e-300))[:, None]
    return wi, dist, weight


def _facing(wi: np.ndarray, area_normal: np.ndarray) -> np.ndarray:
    """``wi @ area_normal`` summed in a fixed order (BLAS's order varies by machine and uses
    FMA; ``render.kernels`` sums the same way)."""
    return (wi[:, 0] * area_normal[0] + wi[:, 1] * area_normal[1]) + wi[:, 2] * area_normal[2]


def _sample_ambient(light: AmbientLight, p, n, keys: SampleKeys, light_index: int, j):
    u, v = uniform2(keys.seed, keys.pixel, keys.sample, keys.bounce,
                    Purpose.LIGHT_SAMPLE + 16 * light_index, j)
    wi = cosine_hemisphere(n, u, v)
    cos = np.maximum(np.einsum("ij,ij->i", wi, n), 1e-12)
    # radiance / pdf with pdf = cos / pi; the integrator multiplies by cos again.
    return wi, np.full(len(p), np.inf), light.radiance[None, :] * (np.pi / cos)[:, None]


# ---------------------------------------------------------------------------------------------
# Shading and the radiance sum
# ---------------------------------------------------------------------------------------------

def spawn(points: np.ndarray, normals: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Ray origins just off a surface, on the side of ``normals`` (pbrt-v4's
    ``OffsetRayOrigin``; the kernels' ``_shade_row``).

    Parameters
    ----------
    points : (k, 3) float64 hit points; normals : (k, 3) unit normals of the side to leave by;
    error : (k,) bound on how far a float32 query may misplace the surface near each point
        (``kernels.hit_points``): the origin moves that far, whatever the ray's length.

    Returns
    -------
    (k, 3) float64
    """
    return points + normals * error[:, None]


def shade_numpy(ctx: PathContext, rays: RadianceRays, hits: Hits
                ) -> tuple[ShadowRays, RadianceRays]:
    """``integrators.shade`` as a chain of numpy operations (the same rays, bit for bit)."""
    settings = ctx.settings
    d = rays.direction.astype(np.float64)
    p, error = hit_points(rays, hits)
    nf = facing(hits.normal, d)
    origin = spawn(p, nf, error)
    if settings.integrator == "ao":
        return _ambient_occlusion_rays(ctx, rays, hits, origin, nf), _no_rays()
    albedo = ctx.shading.materials.diffuse[hits.material]
    if hits.color is not None:
        albedo = albedo * hits.color
    shadow = _next_event_rays(ctx, rays, p, origin, nf, -d, albedo, hits.material)
    more = rays.depth < settings.bounces
    if not more.any():
        return shadow, _no_rays()
    # Continue the path: one cosine-weighted diffuse bounce (weight = albedo).
    path, depth = rays.path[more], rays.depth[more]
    u, v = uniform2(settings.seed, ctx.pixel[path], ctx.sample[path], depth,
                    Purpose.BOUNCE_DIRECTION)
    beta = rays.beta[more] * albedo[more]
    keep = np.any(beta > 0, axis=1)
    direction = cosine_hemisphere(nf[more], u, v)
    continuation = RadianceRays(path[keep], depth[keep] + 1,
                                origin[more][keep].astype(np.float32),
                                direction[keep].astype(np.float32), beta[keep])
    return shadow, continuation


def _no_shadow() -> ShadowRays:
    return ShadowRays(np.zeros(0, np.int64), np.zeros(0, np.uint8),
                      np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                      np.zeros(0, np.float32), np.zeros((0, 3)))


def _no_rays() -> RadianceRays:
    return RadianceRays(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros((0, 3), np.float32),
                        np.zeros((0, 3), np.float32), np.zeros((0, 3)))


def _ambient_occlusion_rays(ctx, rays, hits, origin, nf) -> ShadowRays:
    """``shadow_samples`` cosine-weighted rays of length ``ao_distance`` per hit."""
    m = ctx.settings.shadow_samples
    k = len(rays)
    j = np.tile(np.arange(m, dtype=np.uint64), k)
    path = np.repeat(rays.path, m)
    u, v = uniform2(ctx.settings.seed, ctx.pixel[path], ctx.sample[path], 1,
                    Purpose.AO_DIRECTION, j)
    direction = cosine_hemisphere(np.repeat(nf, m, axis=0), u, v)
    color = hits.color if hits.color is not None else np.ones((k, 3))
    return ShadowRays(path, np.zeros(k * m, np.uint8), np.repeat(origin, m, axis=0).astype(np.float32),
                      direction.astype(np.float32), np.full(k * m, ctx.ao_distance, np.float32),
                      np.repeat(color / max(m, 1), m, axis=0))


def _next_event_rays(ctx, rays, point, origin, nf, wo, albedo, material) -> ShadowRays:
    """Shadow rays from ``k`` path vertices to every light, with the light they would bring.

    Lights are sampled from the hit point (distance, direction and cosines); the rays leave
    from the spawned origin.

    Parameters
    ----------
    rays : the k radiance rays whose hits these are (path, depth, beta).
    point, origin, nf, wo : (k, 3) hit point, spawned origin, facing normal, direction to the
        viewer.
    albedo : (k, 3); material : (k,) slots.
    """
    settings, mats = ctx.settings, ctx.shading.materials
    throughput_diffuse = rays.beta * albedo / np.pi  # (k, 3) throughput times Lambertian BRDF
    pixel, sample = ctx.pixel[rays.path], ctx.sample[rays.path]
    parts = []
    for index, light in enumerate(ctx.shading.lights):
        m = shadow_rays(light, settings.shadow_samples)
        if m == 0:
            continue
        # One row per (vertex, shadow sample j), vertex-major.
        if m == 1:
            p_rep, o_rep, n_rep, j = point, origin, nf, 0
            keys = SampleKeys(settings.seed, pixel, sample, rays.depth)
        else:
            p_rep, o_rep = np.repeat(point, m, axis=0), np.repeat(origin, m, axis=0)
            n_rep = np.repeat(nf, m, axis=0)
            keys = SampleKeys(settings.seed, np.repeat(pixel, m), np.repeat(sample, m),
                              np.repeat(rays.depth, m))
            j = np.tile(np.arange(m, dtype=np.uint64), len(rays))
        wi, dist, incident = sample_light(light, p_rep, n_rep, keys, index, j)
        cos_i = np.einsum("ij,ij->i", n_rep, wi)
        lit = incident[:, 0] + incident[:, 1] + incident[:, 2] > 0
        useful = np.nonzero((cos_i > 0) & lit)[0]
        if len(useful) == 0:
            continue
        vertex = useful // m
        weight = (cos_i[useful] / m)[:, None] * incident[useful]
        contribution = throughput_diffuse[vertex] * weight
        if mats.has_specular:
            lobe = blinn_phong_lobe(mats.shininess[material[vertex]], nf[vertex], wo[vertex],
                                    wi[useful])
            contribution += (rays.beta[vertex] * mats.specular[material[vertex]]
                             * lobe[:, None] * weight)
        parts.append(ShadowRays(rays.path[vertex], rays.depth[vertex],
                                o_rep[useful].astype(np.float32),
                                wi[useful].astype(np.float32),
                                (dist[useful] * (1.0 - SPAWN_EPSILON)).astype(np.float32),
                                contribution))
    if not parts:
        return _no_shadow()
    return ShadowRays.concat(parts)


def add_unoccluded_numpy(radiance: np.ndarray, shadow: ShadowRays, lit: np.ndarray) -> None:
    """``integrators.add_unoccluded`` with ``np.bincount`` (its rounding is the kernel's
    reference); any dtype and layout of ``radiance``."""
    path = shadow.path[lit]
    contribution = shadow.contribution[lit]
    for c in range(3):
        radiance[:, c] += np.bincount(path, weights=contribution[:, c], minlength=len(radiance))
