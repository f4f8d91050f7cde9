"""The values of a render's options: how each is read and checked, and the defaults."""

from __future__ import annotations

import argparse
import math

from vastray.preflight import parse_size
from vastray.schedule import portals

#: Defaults for a user's store, and for the built-in scene (a first picture in a few seconds:
#: larger, smoother, one bounce and two shadow rays toward the sky).
STORE_DEFAULTS = {"width": 320, "height": 240, "spp": 4, "bounces": 3, "shadow_samples": 16}
BUILTIN_DEFAULTS = {"width": 640, "height": 480, "spp": 8, "bounces": 1, "shadow_samples": 2}


def _size(text: str) -> int:
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _portal_resolution(text: str) -> int:
    value = _positive(text)
    if value > portals.MAX_RESOLUTION:
        raise argparse.ArgumentTypeError(f"at most {portals.MAX_RESOLUTION} (the paper's "
                                         f"largest), got {value}")
    return value


def _cache_size(text: str) -> int | str:
    """``N`` domains or ``P%`` of the domains (resolved once the store is open)."""
    if text.endswith("%"):
        value = float(text[:-1])
        if not 0 < value <= 100:
            raise argparse.ArgumentTypeError(f"percentage must be in (0, 100], got {text}")
        return text
    return _positive(text)


def resolve_cache(cache: int | str | None, n_domains: int) -> int | None:
    """The cache size in domains: ``P%`` of ``n_domains`` rounded up (at least 1)."""
    if isinstance(cache, str):
        return max(1, math.ceil(float(cache[:-1]) / 100.0 * n_domains))
    return cache


def _bandwidths(text: str) -> float | list[float]:
    """``MB/s`` or a comma-separated list of them (one per rank, cycled)."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MB/s numbers like 200 or 200,100; got "
                                         f"{text!r}") from None
    if not all(0 < v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"bandwidths must be positive, got {text!r}")
    return values[0] if len(values) == 1 else values


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _non_negative(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {value}")
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value
