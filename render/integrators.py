"""Ambient occlusion and path tracing with next-event estimation, as wavefront steps.

A render is a set of paths. Tracing is split into steps any scheduler can drive: radiance rays
(``RadianceRays``) meet their closest hits, ``shade`` turns hits into shadow rays (with the
contribution they carry if unoccluded) and continuation rays, and unoccluded shadow rays are
summed per path. The reference renderer (``trace_paths``) runs the steps in order; the
out-of-core and distributed schedulers run the very same steps in their own order, which is why
their images are identical. All randomness comes from ``render.rng`` keyed by (seed, pixel,
sample, bounce, purpose, index), never from processing order.

``shade`` and ``add_unoccluded`` run as fused numba kernels (``render.kernels``) over the batch.
The numpy chain they replaced is the tests' oracle (``tests/oracles.py``, the same rays and
sums bit for bit); it is not part of the package.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from vastray.render import kernels
from vastray.render.camera import start_distance
from vastray.render.lights import (
    AmbientLight,
    DirectionalLight,
    Light,
    PointLight,
    QuadLight,
    shadow_rays,
)
from vastray.render.materials import MaterialTable, blinn_phong_lobe_of_cos
from vastray.render.rng import Purpose
from vastray.render.tracer import DomainTracer, Hits

#: Shadow rays stop this fraction short of their light (see ``render.kernels.SPAWN_EPSILON``).
SPAWN_EPSILON = kernels.SPAWN_EPSILON


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
    colormap: str | None = None  # matplotlib colour map for scalars; None: built-in viridis
    #: The scalar range mapped to the colour map's ends (``--color-range LO HI``), the same
    #: for every frame and node; None: the store's own range.
    color_min: float | None = None
    color_max: float | None = None
    #: The pass: samples ``sample_start <= s < sample_stop`` of every pixel (None: up to
    #: ``spp``); its paths are numbered pixel-major within it (``driver.path_context``).
    sample_start: int = 0
    sample_stop: int | None = None
    #: The BVH Embree builds for every domain (``--bvh``, ``scene.bvh_choice``): auto, fast
    #: or quality; part of what the image is (the fast BVH finds other hits at a few rays).
    bvh: str = "auto"

    @property
    def color_range(self) -> tuple[float, float] | None:
        """The fixed scalar range of ``--color-range`` (None: the store's)."""
        if self.color_min is None or self.color_max is None:
            return None
        return float(self.color_min), float(self.color_max)

    @property
    def samples(self) -> tuple[int, int]:
        """(first, stop) sample numbers of the pass."""
        return self.sample_start, self.spp if self.sample_stop is None else self.sample_stop

    @property
    def paths(self) -> int:
        """Paths in the pass: one per pixel and sample."""
        first, stop = self.samples
        return self.width * self.height * (stop - first)

    def window(self, first: int, stop: int) -> RenderSettings:
        """These settings for the pass of samples ``first <= s < stop``."""
        if not 0 <= first < stop <= self.spp:
            raise ValueError(f"samples {first}:{stop} are not a pass of {self.spp} spp")
        return replace(self, sample_start=first, sample_stop=stop)


@dataclass(frozen=True)
class Shading:
    """Everything the integrators need besides geometry.

    ``clip`` ((2, 3) float64, the box of the scene and its area lights) and ``eye`` ((3,)
    float64, the camera's position), both in the store's frame, let camera rays from far away
    start near the scene (``camera.start_distance``); None: they start at the camera.
    ``seen_pixels`` ((width * height,) bool, ``render.seen_pixels``) names the pixels whose
    camera rays can meet something (with ``clip``); None: every pixel's can.
    """

    lights: list[Light]
    materials: MaterialTable
    has_color: bool
    clip: np.ndarray | None = None
    eye: np.ndarray | None = None
    seen_pixels: np.ndarray | None = None


class _RaySet:
    """Take and concatenate a structure-of-arrays dataclass row-wise, field by field."""

    def __len__(self) -> int:
        return len(self.path)

    def take(self, rows: np.ndarray):
        return type(self)(*(getattr(self, f.name)[rows] for f in fields(self)))

    @classmethod
    def concat(cls, parts: list):
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))


@dataclass
class RadianceRays(_RaySet):
    """Rays that look for a closest hit (camera rays and diffuse continuations).

    Attributes
    ----------
    path : (n,) int64 index of the ray's path in its batch
    depth : (n,) uint8 path vertex the ray will find (0 = camera ray)
    origin, direction : (n, 3) float32
    beta : (n, 3) float64 path throughput
    """

    path: np.ndarray
    depth: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    beta: np.ndarray


@dataclass
class ShadowRays(_RaySet):
    """Rays that test visibility; ``contribution`` reaches their path if nothing blocks them.

    Attributes
    ----------
    path : (n,) int64; depth : (n,) uint8 path vertex they leave from
    origin, direction : (n, 3) float32; t_max : (n,) float32 (inf = to infinity)
    contribution : (n, 3) float64
    """

    path: np.ndarray
    depth: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    t_max: np.ndarray
    contribution: np.ndarray


@dataclass(frozen=True)
class PathContext:
    """What shading needs to know about a batch of paths.

    Attributes
    ----------
    shading, settings : scene lights/materials and render settings
    pixel, sample : (P,) uint32 key of each path of the batch
    ao_distance : AO ray length
    """

    shading: Shading
    settings: RenderSettings
    pixel: np.ndarray
    sample: np.ndarray
    ao_distance: float


def hit_points(rays: RadianceRays, hits: Hits) -> tuple[np.ndarray, np.ndarray]:
    """The hits' points and error bounds ((k, 3) and (k,) float64): those the tracer rebuilt
    from barycentrics, or ``o + t d`` where the hit record has none."""
    if hits.point is not None:
        return _c(hits.point, np.float64), _c(hits.error, np.float64)
    k = len(rays)
    point, error = np.empty((k, 3)), np.empty(k)
    kernels.ray_points(_c(rays.origin, np.float32), _c(rays.direction, np.float32),
                       _c(hits.t, np.float64), point, error)
    return point, error


def camera_rays(camera, ctx: PathContext) -> RadianceRays:
    """One camera ray per path of the batch."""
    origin, direction = camera.generate32(ctx.pixel, ctx.sample, ctx.settings.seed,
                                          _camera_start(ctx))
    n = len(ctx.pixel)
    return RadianceRays(np.arange(n, dtype=np.int64), np.zeros(n, np.uint8), origin, direction,
                        np.ones((n, 3)))


def seen_camera_rays(camera, ctx: PathContext) -> RadianceRays:
    """The batch's camera rays that can see something: those entering ``Shading.clip``, the
    box of everything a ray can hit or see (the store and its quad lights), through a pixel of
    ``Shading.seen_pixels`` (the image of the occupied cells and quad lights), in path order,
    each bit for bit ``camera_rays``' ray. The others escape at once and are not made (an
    object that fills a quarter of the frame leaves three quarters of them: their query and
    their hit records are spared); ``launched_camera_rays`` gives their paths the sky.

    The box is grown by ``camera_pad``, far beyond float64's rounding in the test and
    float32's in the rays: a ray that Embree could find a hit for, or that meets a quad
    light, is always kept. Without ``Shading.clip``, every ray is kept.

    Returns
    -------
    the camera rays kept (``path`` their rows of the batch)
    """
    clip = ctx.shading.clip
    if clip is None:
        return camera_rays(camera, ctx)
    advance = _camera_start(ctx)
    lo, hi = np.asarray(clip, np.float64)
    pad = camera_pad(ctx.shading, advance)
    rows, origin, direction = camera.generate32_in_box(ctx.pixel, ctx.sample, ctx.settings.seed,
                                                       advance, lo - pad, hi + pad,
                                                       ctx.shading.seen_pixels)
    k = len(rows)
    return RadianceRays(rows, np.zeros(k, np.uint8), origin, direction, np.ones((k, 3)))


def launched_camera_rays(camera, ctx: PathContext, result: PathResult,
                         rows: np.ndarray | None = None) -> RadianceRays:
    """The camera rays a schedule queues for the paths ``rows`` of the batch ((m,) int64,
    ascending; None: every path): those ``seen_camera_rays`` keeps. The paths left out see
    the sky at once: ``escaped_emission`` is added to their rows of ``result.radiance``, as
    ``PathResult.record_camera_hits`` adds it for a camera ray that meets nothing (bit for
    bit: both sum the ambient lights, in order, onto zeros); their first-hit layers stay
    ``PathResult.empty``'s, a miss's. Paths outside ``rows`` are another node's: untouched.

    What it saves a schedule is the ray-domain enumeration of the rays left out
    (``ImageSchedule.start``: about half a microsecond a path), not only making them.
    """
    n = len(ctx.pixel)
    if rows is None:
        rays = seen_camera_rays(camera, ctx)
    else:  # the share's rays alone: a ray depends on its path's pixel and sample only
        rows = np.asarray(rows, np.int64)
        share = replace(ctx, pixel=ctx.pixel[rows], sample=ctx.sample[rows])
        rays = seen_camera_rays(camera, share)
        rays = replace(rays, path=rows[rays.path])
    sky = escaped_emission(ctx)
    if sky is not None:
        left_out = np.zeros(n, bool)
        left_out[slice(None) if rows is None else rows] = True
        left_out[rays.path] = False
        kernels.add_to_rows(result.radiance, left_out, sky)
    return rays


def camera_pad(shading: Shading, advance: float) -> float:
    """How far the boxes camera rays are tested against are grown (``seen_camera_rays``,
    ``render.seen_pixels``): ``2^-18`` of the largest coordinate involved (``Shading.clip``'s,
    the camera's and how far its rays start, ``advance``)."""
    lo, hi = np.asarray(shading.clip, np.float64)
    reach = max(np.abs(lo).max(), np.abs(hi).max()) + np.abs(shading.eye).max() + advance
    return 2.0 ** -18 * reach


def escaped_emission(ctx: PathContext) -> np.ndarray | None:
    """What a camera ray that meets nothing sees ((3,) float64: the ambient lights, summed in
    ``camera_emission``'s order), or None where that is nothing."""
    if ctx.settings.integrator != "pt":
        return None
    ambient = [light for light in ctx.shading.lights if isinstance(light, AmbientLight)]
    if not ambient:
        return None
    out = np.zeros(3)
    for light in ambient:
        out += light.radiance
    return out


def camera_emission(ctx: PathContext, rays: RadianceRays, t_hit: np.ndarray) -> np.ndarray:
    """Radiance camera rays see directly: quad lights in front of the first surface, and the
    environment where they escape (path tracing only).

    Parameters
    ----------
    rays : camera rays; t_hit : (n,) their final closest-hit distances (inf = miss).

    Returns
    -------
    (n, 3) float64
    """
    out = np.zeros((len(rays), 3))
    if ctx.settings.integrator != "pt":
        return out
    o = d = None
    for light in ctx.shading.lights:
        if isinstance(light, QuadLight):
            if o is None:
                o, d = rays.origin.astype(np.float64), rays.direction.astype(np.float64)
            out[light.intersect(o, d) < t_hit] += light.radiance
        elif isinstance(light, AmbientLight):
            out[~np.isfinite(t_hit)] += light.radiance
    return out


def shade(ctx: PathContext, rays: RadianceRays, hits: Hits, rows: np.ndarray | None = None
          ) -> tuple[ShadowRays, RadianceRays]:
    """Turn final closest hits into shadow rays and continuation rays, through the compiled
    kernels (``render.kernels``).

    Parameters
    ----------
    rays : n radiance rays; hits : their hits.
    rows : (k,) int64 the rows of ``rays`` and ``hits`` to shade, in order, all of them hits
        (None: every row, all of which hit). The same as shading ``rays.take(rows)`` and
        ``hits.take(rows)``, bit for bit, without the takes.

    Returns
    -------
    shadow : AO rays (contribution = surface colour / samples) or next-event rays to every
        light (contribution = throughput x BRDF x cos x incident radiance / samples)
    continuation : cosine-weighted diffuse bounces (path tracing, below ``bounces``)

    Raises
    ------
    TypeError
        Path tracing with a light of a kind the kernels do not know (not one of
        ``render.lights``' point, directional, quad and ambient lights).
    """
    return _shade_fused(ctx, rays, hits, rows)


_LIGHT_KINDS = {PointLight: kernels.POINT, DirectionalLight: kernels.DIRECTIONAL,
                QuadLight: kernels.QUAD, AmbientLight: kernels.AMBIENT}


def _light_table(lights: list[Light]) -> tuple[np.ndarray, np.ndarray]:
    """The lights as the kernels read them: (L,) int64 kinds and (L, ``LIGHT_PARAMS``)
    float64 parameters, with what the kernels derive from a light's fields (a directional
    light's unit direction, a quad's area normal and area) computed here in numpy, as the
    tests' oracle (``tests/oracles.py: sample_light``) computes them.

    Raises
    ------
    TypeError
        A light of another kind, naming it and the kinds supported.
    """
    kinds = np.zeros(len(lights), np.int64)
    params = np.zeros((len(lights), kernels.LIGHT_PARAMS))
    for i, light in enumerate(lights):
        kind = _LIGHT_KINDS.get(type(light))
        if kind is None:
            supported = ", ".join(k.__name__ for k in _LIGHT_KINDS)
            raise TypeError(f"light #{i + 1} is a {type(light).__name__}: the shading kernels "
                            f"know the lights {supported} only")
        kinds[i] = kind
        if kind == kernels.POINT:
            params[i, :6] = np.concatenate([light.position, light.intensity])
        elif kind == kernels.DIRECTIONAL:
            wi = -light.direction / np.linalg.norm(light.direction)
            params[i, :6] = np.concatenate([wi, light.irradiance])
        elif kind == kernels.QUAD:
            area_normal = light.area_normal
            params[i, :15] = np.concatenate([light.corner, light.edge1, light.edge2,
                                             light.radiance, area_normal])
            params[i, 15] = np.linalg.norm(area_normal)
        else:
            params[i, :3] = light.radiance
    return kinds, params


def _hemisphere_samples(ctx: PathContext, path: np.ndarray, bounce: np.ndarray, purpose: int,
                        m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u and the azimuth's cos, sin ((k * m,) float32 each) of ``m`` cosine-hemisphere
    samples per vertex (``kernels.hemisphere_uniforms``)."""
    u, v = kernels.hemisphere_uniforms(np.uint64(ctx.settings.seed), np.uint64(purpose),
                                       ctx.pixel, ctx.sample, path, bounce, m)
    return (u, *kernels.hemisphere_angles(v))


def _shade_fused(ctx: PathContext, rays: RadianceRays, hits: Hits,
                 rows: np.ndarray | None = None) -> tuple[ShadowRays, RadianceRays]:
    """``shade`` through ``render.kernels`` (the same rays as ``tests/oracles.py``'s numpy
    chain, bit for bit)."""
    settings, mats = ctx.settings, ctx.shading.materials
    rows = np.arange(len(rays), dtype=np.int64) if rows is None else _c(rows, np.int64)
    k = len(rows)
    path, depth = rays.path[rows], rays.depth[rows]  # of the shaded rows
    has_color = hits.color is not None
    color = hits.color if has_color else np.zeros((0, 3))
    dirs = _c(rays.direction, np.float32)
    point, error = hit_points(rays, hits)
    normal = _c(hits.normal, np.float64)
    if settings.integrator == "ao":
        m = settings.shadow_samples
        if m <= 0 or k == 0:
            return _no_shadow(), _no_rays()
        hu, hc, hs = _hemisphere_samples(ctx, path, np.ones(k, np.uint8),
                                         Purpose.AO_DIRECTION, m)
        s_org, s_dir = np.empty((k * m, 3), np.float32), np.empty((k * m, 3), np.float32)
        contribution = np.empty((k * m, 3))
        kernels.shade_ao(rows, dirs, point, error, normal, _c(color, np.float64), has_color, m,
                         hu, hc, hs, s_org, s_dir, contribution)
        return ShadowRays(np.repeat(path, m), np.zeros(k * m, np.uint8), s_org, s_dir,
                          np.full(k * m, ctx.ao_distance, np.float32), contribution), _no_rays()
    kinds, params = _light_table(ctx.shading.lights)
    counts = np.array([shadow_rays(light, settings.shadow_samples)
                       for light in ctx.shading.lights], np.int64)
    purposes = np.array([Purpose.LIGHT_SAMPLE + 16 * i for i in range(len(kinds))], np.uint64)
    # Hemisphere samples of ambient lights and of the bounce: drawn and turned into angles
    # before the kernel (numpy's float32 cos/sin; see render.kernels).
    ambient = np.nonzero((kinds == kernels.AMBIENT) & (counts > 0))[0]
    hem_slot = np.full(len(kinds), -1, np.int64)
    hem = np.zeros((3, len(ambient), k * settings.shadow_samples), np.float32)
    for slot, li in enumerate(ambient):
        hem_slot[li] = slot
        hem[:, slot] = _hemisphere_samples(ctx, path, depth, purposes[li], counts[li])
    more = depth < settings.bounces
    if more.any():
        bu, bc, bs = _hemisphere_samples(ctx, path, depth, Purpose.BOUNCE_DIRECTION, 1)
    else:
        bu = bc = bs = np.zeros(k, np.float32)
    n = k * int(counts.sum())
    ns = n if mats.has_specular else 0
    shadow = ShadowRays(np.empty(n, np.int64), np.empty(n, np.uint8),
                        np.empty((n, 3), np.float32), np.empty((n, 3), np.float32),
                        np.empty(n, np.float32), np.empty((n, 3)))
    s_vertex, s_weight, s_cos_h = np.empty(ns, np.int64), np.empty((ns, 3)), np.empty(ns)
    cont = RadianceRays(np.empty(k, np.int64), np.empty(k, np.uint8),
                        np.empty((k, 3), np.float32), np.empty((k, 3), np.float32),
                        np.empty((k, 3)))
    n_shadow, n_cont = kernels.shade_pt(
        rows, _c(rays.path, np.int64), _c(rays.depth, np.uint8), dirs, _c(rays.beta, np.float64),
        point, error, normal, _c(hits.material, np.int64), _c(color, np.float64), has_color,
        ctx.pixel, ctx.sample, np.uint64(settings.seed), settings.bounces, mats.diffuse,
        mats.has_specular, kinds, counts, purposes, params, hem_slot, hem[0], hem[1], hem[2],
        bu, bc, bs, shadow.path, shadow.depth, shadow.origin, shadow.direction, shadow.t_max,
        shadow.contribution, s_vertex, s_weight, s_cos_h,
        cont.path, cont.depth, cont.origin, cont.direction, cont.beta)
    shadow = shadow.take(slice(0, n_shadow))
    if mats.has_specular and n_shadow:
        vertex = rows[s_vertex[:n_shadow]]
        material = hits.material[vertex]
        lobe = blinn_phong_lobe_of_cos(mats.shininess[material], s_cos_h[:n_shadow])
        shadow.contribution += (rays.beta[vertex] * mats.specular[material]
                                * lobe[:, None] * s_weight[:n_shadow])
    return shadow, cont.take(slice(0, n_cont))


def _c(a: np.ndarray, dtype) -> np.ndarray:
    """``a`` as a C-contiguous array of ``dtype`` (a copy only where it is not one): one
    kernel signature per argument."""
    return np.ascontiguousarray(a, dtype=dtype)


def _no_shadow() -> ShadowRays:
    return ShadowRays(np.zeros(0, np.int64), np.zeros(0, np.uint8),
                      np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                      np.zeros(0, np.float32), np.zeros((0, 3)))


def _no_rays() -> RadianceRays:
    return RadianceRays(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros((0, 3), np.float32),
                        np.zeros((0, 3), np.float32), np.zeros((0, 3)))


def add_unoccluded(radiance: np.ndarray, shadow: ShadowRays, lit: np.ndarray) -> None:
    """Add the contribution of the shadow rays ``lit`` (bool (n,)) to ``radiance`` (P, 3).

    Per path, the contributions are summed in row order, then added, by
    ``kernels.add_unoccluded`` in one pass (``PathResult.radiance`` is always such an array).

    Raises
    ------
    TypeError
        ``radiance`` is not a C-contiguous float64 array: the kernel adds in place.
    """
    if radiance.dtype != np.float64 or not radiance.flags.c_contiguous:
        raise TypeError(f"add_unoccluded adds into a C-contiguous float64 (P, 3) array, not a "
                        f"{'' if radiance.flags.c_contiguous else 'non-contiguous '}"
                        f"{radiance.dtype} one")
    kernels.add_unoccluded(radiance, _c(shadow.path, np.int64),
                           _c(shadow.contribution, np.float64), _c(lit, np.bool_))


@dataclass
class PathResult:
    """Radiance of a batch of paths and what their camera rays saw first.

    Attributes
    ----------
    radiance : (P, 3) float64
    first_t : (P,) float32 camera-ray hit distance (inf for a miss)
    first_normal : (P, 3) float32 facing normal at the camera hit
    """

    radiance: np.ndarray
    first_t: np.ndarray
    first_normal: np.ndarray

    @staticmethod
    def empty(n: int) -> PathResult:
        return PathResult(np.zeros((n, 3)), np.full(n, np.inf, np.float32),
                          np.zeros((n, 3), np.float32))

    def record_camera_hits(self, ctx: PathContext, rays: RadianceRays, hits: Hits) -> None:
        """Camera emission and the first-hit layers, once camera hits are final."""
        if ctx.settings.integrator == "pt" and any(
                isinstance(light, QuadLight | AmbientLight) for light in ctx.shading.lights):
            # (nothing else is seen directly: point and directional lights have no area)
            self.radiance[rays.path] += camera_emission(ctx, rays, hits.t)
        # first_t = t + start and first_normal = facing(normal, direction), as float32, in
        # one compiled pass
        kernels.first_hits(_c(rays.path, np.int64), _c(hits.t, np.float64),
                           _c(hits.normal, np.float64), _c(rays.direction, np.float32),
                           float(_camera_start(ctx)), self.first_t, self.first_normal)


def _camera_start(ctx: PathContext) -> float:
    """How far from the camera its rays start (``camera.start_distance``; 0 without
    ``Shading.clip``)."""
    if ctx.shading.clip is None:
        return 0.0
    return start_distance(ctx.shading.eye, ctx.shading.clip)


def trace_paths(tracer: DomainTracer, camera, ctx: PathContext) -> PathResult:
    """The reference order: every wavefront to its closest hits, shade, test shadows, repeat."""
    result = PathResult.empty(len(ctx.pixel))
    n = len(ctx.pixel)
    rays = launched_camera_rays(camera, ctx, result)
    tracer.count_escaped(n - len(rays))
    while len(rays):
        first = rays.depth[0] == 0
        hits = tracer.intersect(rays.origin, rays.direction, kind="camera" if first else "bounce")
        if first:
            result.record_camera_hits(ctx, rays, hits)
        shadow, rays = shade(ctx, rays, hits, np.nonzero(hits.hit)[0])
        if len(shadow):
            blocked = tracer.occluded(shadow.origin, shadow.direction, shadow.t_max)
            add_unoccluded(result.radiance, shadow, ~blocked)
    return result
