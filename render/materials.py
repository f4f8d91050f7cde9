"""Blinn-Phong materials (diffuse bounces) and the colour map for scalar fields."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class Material:
    """Diffuse albedo (3,), Blinn-Phong specular colour (3,) and exponent."""

    diffuse: np.ndarray
    specular: np.ndarray
    shininess: float

    @staticmethod
    def default() -> Material:
        return Material(np.full(3, 0.7), np.zeros(3), 32.0)


class MaterialTable:
    """Materials as arrays indexed per hit, so shading never loops over rays.

    Parameters
    ----------
    materials : one per object (material slot) of the store, in store order.
    """

    def __init__(self, materials: list[Material]):
        self.diffuse = np.stack([m.diffuse for m in materials]).astype(np.float64)  # (M, 3)
        self.specular = np.stack([m.specular for m in materials]).astype(np.float64)  # (M, 3)
        self.shininess = np.array([m.shininess for m in materials], dtype=np.float64)  # (M,)
        self.has_specular = bool(np.any(self.specular > 0))

    def __len__(self) -> int:
        return len(self.diffuse)


# Viridis sampled at 9 points (matplotlib's table), linearly interpolated.
_VIRIDIS = np.array([
    [0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530],
    [0.207, 0.372, 0.553], [0.164, 0.471, 0.558], [0.128, 0.567, 0.551],
    [0.135, 0.659, 0.518], [0.267, 0.749, 0.441], [0.993, 0.906, 0.144],
])


class ScalarMap(NamedTuple):
    """How scalars become colours: the range mapped to the ends of the colour table, and the
    table ((n, 3) float64; None: the built-in viridis). Unpacks as ``colormap``'s arguments."""

    lo: float
    hi: float
    lut: np.ndarray | None = None


def colormap(values: np.ndarray, lo: float, hi: float, lut: np.ndarray | None = None
             ) -> np.ndarray:
    """Map scalars to colours, interpolating a colour table linearly.

    Parameters
    ----------
    values : (n,) scalars; lo, hi : the range mapped to the ends of the map.
    lut : (k, 3) colour table, k >= 2 (e.g. ``render.colormaps.colormap_lut``); None: viridis
        sampled at 9 points.

    Returns
    -------
    (n, 3) float64 linear-ish RGB in [0, 1]; ``NAN_COLOR`` where a value is NaN.
    """
    table = color_table(lut)
    span = hi - lo if hi > lo else 1.0
    x = np.clip((np.asarray(values, np.float64) - lo) / span, 0.0, 1.0) * (len(table) - 1)
    nan = np.isnan(x)
    if nan.any():  # a NaN has no place on the map (it made an index out of bounds before)
        x = np.where(nan, 0.0, x)
    i = np.minimum(x.astype(np.int64), len(table) - 2)
    f = (x - i)[:, None]
    out = table[i] * (1.0 - f) + table[i + 1] * f
    out[nan] = NAN_COLOR
    return out


#: The colour of a NaN scalar (a volume's missing values, a simulation's undefined cells), as
#: ParaView shows NaNs in a colour of their own: mid grey (the built-in viridis has none; under
#: a grey colour map a NaN looks like a mid value).
NAN_COLOR = np.array([0.5, 0.5, 0.5])


def color_table(lut: np.ndarray | None) -> np.ndarray:
    """``colormap``'s table: ``lut`` ((k, 3), k >= 2), or viridis sampled at 9 points."""
    return _VIRIDIS if lut is None else lut


def blinn_phong_lobe_of_cos(shininess: np.ndarray, cos_h: np.ndarray) -> np.ndarray:
    """Energy-normalised Blinn-Phong lobe ``(s + 2) / (2 pi) * cos(theta_h)^s`` from the
    half vector's ``cos(theta_h)`` ((k,) each; numpy's ``pow``, which the fused kernels leave
    to numpy: see ``render.kernels``).

    The BRDF is ``diffuse / pi + specular * lobe``; bounces sample the diffuse part only.
    """
    return (shininess + 2.0) / (2.0 * np.pi) * cos_h ** shininess
