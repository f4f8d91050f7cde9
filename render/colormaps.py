"""Named colour maps for scalar colouring (``--colormap``) and the colour bar drawn into PNGs
(``--legend``, on by default with ``--colormap``).

A named map is sampled once from matplotlib into a 256-entry table (``ScalarMap.lut``) when
the render starts; tracing only interpolates that table, so matplotlib is imported only when
``--colormap`` is given (it comes with ``pip install 'vastray[plot]'`` and with the vtk
extra). Without ``--colormap`` the built-in viridis table is used and matplotlib is not needed.
The table's values are used as the surface's albedo, as the built-in table's are, so the bar
shows each colour as a surface lit at unit radiance appears in the PNG.
"""

from __future__ import annotations

import difflib
import functools
from dataclasses import dataclass

import numpy as np

from vastray.render.materials import ScalarMap, colormap
from vastray.scene.errors import InputError

LUT_SIZE = 256


def colormap_names() -> list[str]:
    """Every colour-map name matplotlib knows (its ``_r`` reversed forms included)."""
    import matplotlib

    return sorted(matplotlib.colormaps)


@functools.lru_cache(maxsize=8)
def colormap_lut(name: str) -> np.ndarray:
    """The matplotlib colour map ``name`` sampled at ``LUT_SIZE`` points: (256, 3) float64,
    read-only (sampled once per process: the checks, the legend and every frame share it).

    Raises
    ------
    InputError : matplotlib is not installed, or ``name`` is not a colour map (the message
        lists the closest names).
    """
    try:
        import matplotlib
    except ImportError:
        raise InputError(None, f"--colormap {name} needs matplotlib: pip install "
                               "'vastray[plot]' (without --colormap the built-in viridis is "
                               "used)") from None
    if name not in matplotlib.colormaps:
        close = difflib.get_close_matches(name, colormap_names(), n=6, cutoff=0.5)
        hint = (f"closest: {', '.join(close)}" if close
                else "e.g. viridis, plasma, inferno, magma, cividis, coolwarm, turbo, gray")
        raise InputError(None, f"--colormap: unknown colour map {name!r}; {hint}")
    cmap = matplotlib.colormaps[name].resampled(LUT_SIZE)
    lut = np.array(cmap(np.arange(LUT_SIZE))[:, :3], dtype=np.float64)
    lut.flags.writeable = False
    return lut


def scalar_map(scalar_range: tuple[float, float] | None, name: str | None,
               fixed: tuple[float, float] | None = None) -> ScalarMap:
    """The store's scalar range, or the ``fixed`` one (``--color-range``) when given, with the
    colour table of ``name`` (None: the built-in one)."""
    lo, hi = fixed or scalar_range or (0.0, 1.0)
    return ScalarMap(float(lo), float(hi), None if name is None else colormap_lut(name))


@dataclass(frozen=True)
class Legend:
    """A colour bar: the map, the range it spans and the scalar's name."""

    scalars: ScalarMap
    name: str


def coloured_by_scalars(store) -> bool:
    """Whether ``store``'s surfaces take their colour from its scalar field (a store with
    per-vertex colours uses those instead)."""
    return store.has_scalars and not store.has_colors


def legend_for(store, colormap_name: str | None,
               fixed: tuple[float, float] | None = None) -> Legend | None:
    """The colour bar of a render of ``store`` (over the ``fixed`` range when given): None
    unless ``coloured_by_scalars``."""
    if not coloured_by_scalars(store):
        return None
    return Legend(scalar_map(store.scalar_range, colormap_name, fixed),
                  store.scalar_name or "scalar")


def draw_legend(image: np.ndarray, legend: Legend) -> np.ndarray:
    """``image`` ((H, W, 3) uint8 sRGB) with the colour bar drawn over its bottom.

    The bar spans most of the width on a dark band, the scalar's name above it, the range's
    ends below. Images too small for text (under 96 x 48 pixels) get the bar alone.
    """
    from PIL import Image, ImageDraw, ImageFont

    from vastray.render.imageio import to_srgb8

    h, w = image.shape[:2]
    if w < 16 or h < 8:
        return image
    text = w >= 96 and h >= 48
    font = ImageFont.load_default()
    line = (font.getbbox("Ag")[3] + 2) if text else 0
    bar_h = max(3, h // 24)
    pad = max(2, w // 40)
    band_h = bar_h + 2 * pad + (2 * line if text else 0)
    top = h - band_h
    pil = Image.fromarray(image, mode="RGB")
    draw = ImageDraw.Draw(pil)
    draw.rectangle([0, top, w - 1, h - 1], fill=(24, 24, 24))
    x0, x1 = pad, w - pad
    lo, hi, _ = legend.scalars
    ramp = colormap(np.linspace(lo, hi, x1 - x0), *legend.scalars)
    colors = to_srgb8(ramp[None, :, :])[0]
    bar_top = top + pad + line
    for i, c in enumerate(colors):
        draw.line([(x0 + i, bar_top), (x0 + i, bar_top + bar_h - 1)], fill=tuple(int(v) for v in c))
    if text:
        white = (235, 235, 235)
        below = bar_top + bar_h + 1
        draw.text(((w - draw.textlength(legend.name, font=font)) / 2, top + pad), legend.name,
                  fill=white, font=font)
        draw.text((x0, below), f"{lo:.4g}", fill=white, font=font)
        high = f"{hi:.4g}"
        draw.text((x1 - draw.textlength(high, font=font), below), high, fill=white, font=font)
    return np.asarray(pil)
