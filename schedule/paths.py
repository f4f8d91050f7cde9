"""Ray sets as schedulers carry them: the integrator's rays plus per-ray scheduling state."""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from vastray.render.integrators import RadianceRays, ShadowRays
from vastray.render.tracer import ClosestHits
from vastray.schedule.soa import SoA

RADIANCE_FIELDS = tuple(f.name for f in fields(RadianceRays))
SHADOW_FIELDS = tuple(f.name for f in fields(ShadowRays))


def radiance_soa(rays: RadianceRays, with_color: bool, **extra: np.ndarray) -> SoA:
    """Radiance rays with an empty closest-hit record (``hit_*`` fields) and ``extra`` fields."""
    n = len(rays)
    hits = ClosestHits.empty(n, with_color)
    fields = {f: getattr(rays, f) for f in RADIANCE_FIELDS}
    fields.update(hit_t=hits.t, hit_domain=hits.domain, hit_ng=hits.ng,
                  hit_material=hits.material, hit_point=hits.point, hit_error=hits.error)
    if with_color:
        fields["hit_color"] = hits.color
    fields.update(extra)
    return SoA(**fields)


def closest_hits(rays: SoA) -> ClosestHits:
    """The ``hit_*`` fields of ``rays`` as a ClosestHits view (offers write into ``rays``)."""
    return ClosestHits(rays["hit_t"], rays["hit_domain"], rays["hit_ng"], rays["hit_material"],
                       rays.fields.get("hit_color"), rays["hit_point"], rays["hit_error"])


def as_radiance(rays: SoA) -> RadianceRays:
    return RadianceRays(*(rays[f] for f in RADIANCE_FIELDS))


def shadow_soa(rays: ShadowRays, **extra: np.ndarray) -> SoA:
    fields = {f: getattr(rays, f) for f in SHADOW_FIELDS}
    fields.update(extra)
    return SoA(**fields)


def as_shadow(rays: SoA) -> ShadowRays:
    return ShadowRays(*(rays[f] for f in SHADOW_FIELDS))


def start_cursor(n: int) -> dict[str, np.ndarray]:
    """Cursor fields of rays that have visited no domain yet."""
    return {"at_t": np.full(n, -np.inf, np.float32), "at_d": np.full(n, -1, np.int32)}
