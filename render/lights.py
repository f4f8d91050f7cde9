"""The lights of a scene: point, directional, quad (area) and ambient (environment).

They are data: the fused shading kernels (``render.kernels``, through
``integrators._light_table``) sample them for next-event estimation: a direction toward the
light, the distance a shadow ray must stay clear, and the incident radiance divided by the
sampling pdf. Lights with one fixed direction (point, directional) need one shadow ray; area
and environment lights need ``--shadow-samples`` of them. The same sampling in numpy is the
tests' oracle (``tests/oracles.py: sample_light``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np


def shadow_rays(light, samples: int) -> int:
    """Shadow rays per hit that ``light`` takes: ``samples`` (``--shadow-samples``) for an
    area or sky light, sampled stochastically; one for a point or directional light."""
    return samples if light.stochastic else 1


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light; ``intensity`` (3,) in W/sr."""

    position: np.ndarray
    intensity: np.ndarray
    stochastic = False


@dataclass(frozen=True)
class DirectionalLight:
    """Light from infinitely far away travelling along ``direction``; ``irradiance`` (3,)."""

    direction: np.ndarray
    irradiance: np.ndarray
    stochastic = False


@dataclass(frozen=True)
class QuadLight:
    """One-sided parallelogram area light ``corner + s*edge1 + t*edge2`` (s, t in [0, 1]).

    Emits ``radiance`` (3,) on the side of ``cross(edge1, edge2)``; sampled by area for
    next-event estimation, seen by camera rays, and it casts no shadow itself.
    """

    corner: np.ndarray
    edge1: np.ndarray
    edge2: np.ndarray
    radiance: np.ndarray
    stochastic = True

    @property
    def area_normal(self) -> np.ndarray:
        return np.cross(self.edge1, self.edge2)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance along each ray to the emitting side of the quad, ``inf`` where missed.

        Parameters
        ----------
        origins, directions : (n, 3)

        Returns
        -------
        (n,) float64
        """
        nrm = self.area_normal
        denom = directions @ nrm
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.corner - origins) @ nrm) / denom
            hit = origins + t[:, None] * directions - self.corner
            # Solve hit = s*e1 + t*e2 in the plane via the dual basis.
            e11, e12, e22 = self.edge1 @ self.edge1, self.edge1 @ self.edge2, self.edge2 @ self.edge2
            det = e11 * e22 - e12 * e12
            h1, h2 = hit @ self.edge1, hit @ self.edge2
            s = (e22 * h1 - e12 * h2) / det
            u = (e11 * h2 - e12 * h1) / det
        ok = (denom < 0) & (t > 0) & (s >= 0) & (s <= 1) & (u >= 0) & (u <= 1)
        return np.where(ok, t, np.inf)


@dataclass(frozen=True)
class AmbientLight:
    """Uniform environment radiance ``radiance`` (3,) from every direction (with occlusion)."""

    radiance: np.ndarray
    stochastic = True


Light = PointLight | DirectionalLight | QuadLight | AmbientLight


def in_frame(lights: list[Light], origin: np.ndarray) -> list[Light]:
    """``lights`` moved into a frame whose origin sits at ``origin`` ((3,) float64, world):
    point positions and quad corners minus ``origin`` (in float64); directions, edges and
    powers unchanged. The same list when ``origin`` is zero."""
    origin = np.asarray(origin, np.float64)
    if not origin.any():
        return lights
    moved = []
    for light in lights:
        if isinstance(light, PointLight):
            light = dataclasses.replace(light, position=light.position - origin)
        elif isinstance(light, QuadLight):
            light = dataclasses.replace(light, corner=light.corner - origin)
        moved.append(light)
    return moved


#: The largest power a light may have: float32's largest value. Images are written in float32
#: (EXR, PFM, HDR), so a light beyond it could only make infinite pixels.
MAX_POWER = float(np.finfo(np.float32).max)
_POWER = {PointLight: "intensity", DirectionalLight: "irradiance", QuadLight: "radiance",
          AmbientLight: "radiance"}


def check_power(lights: list[Light], where) -> None:
    """Refuse a light whose power is not a finite number within float32's range.

    Raises
    ------
    InputError
        Naming ``where`` (the scene file), the light (1-based) and its value.
    """
    from vastray.scene.errors import InputError

    for index, light in enumerate(lights):
        name = _POWER.get(type(light))
        if name is None:
            continue
        value = np.asarray(getattr(light, name), np.float64)
        if not np.all(np.isfinite(value)) or np.any(np.abs(value) > MAX_POWER):
            raise InputError(where, f"[[light]] #{index + 1}: {name} {value.tolist()} is beyond "
                                    f"float32's range ({MAX_POWER:.3g}); the image would be "
                                    "infinite. Give it in other units (scale every light alike)")
