"""Counter-based random numbers: every sample is a pure hash of where it is used.

A value depends only on ``(seed, pixel, sample, bounce, purpose, index)`` and never on the order
in which rays are processed, so every scheduler, batch size and domain split draws exactly the
same numbers (DESIGN.md, "The invariant that makes everything testable").
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)
_TOP24, _MID24 = np.uint64(40), np.uint64(16)
_MASK24 = np.uint64(0xFFFFFF)
_INV24 = np.float32(1.0 / (1 << 24))


class Purpose(IntEnum):
    """Why a random number is drawn; part of the hash key so uses never correlate."""

    CAMERA_JITTER = 1
    AO_DIRECTION = 2
    LIGHT_SAMPLE = 3  # + light index * 16
    BOUNCE_DIRECTION = 4


def _mix(h: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser, in place on a uint64 array."""
    h ^= h >> _S30
    h *= _M1
    h ^= h >> _S27
    h *= _M2
    h ^= h >> _S31
    return h


def frame_seed(seed: int, frame: int) -> int:
    """The seed of frame ``frame`` of an animation rendered with ``seed``.

    A 63-bit hash of ``(seed, frame)`` through the same splitmix64 mixer as ``hash_keys``, so
    the frames of an animation are independent Monte Carlo samples (no frame repeats another's
    noise pattern) while each frame stays a pure function of the run's seed and its index:
    a frame renders the same alone, in a sequence, or on any scheduler.

    Parameters
    ----------
    seed : the run's seed (``--seed``), 0 <= seed < 2**64.
    frame : the frame index, >= 0.

    Returns
    -------
    int
        In [0, 2**63): fits a signed 64-bit integer (msgpack, JSON readers).
    """
    if frame < 0 or seed < 0:
        raise ValueError(f"frame and seed must not be negative, got frame {frame}, seed {seed}")
    with np.errstate(over="ignore"):
        h = np.array([np.uint64(seed) * _GOLDEN], dtype=np.uint64)
        h = _mix(h + _GOLDEN)
        h ^= np.uint64(frame)
        h = _mix(h + _GOLDEN)
    return int(h[0] >> np.uint64(1))


def hash_keys(seed: int, pixel: np.ndarray, sample: np.ndarray, bounce: int | np.ndarray,
              purpose: int, index: int | np.ndarray = 0) -> np.ndarray:
    """Hash the key tuple of each ray into 64 random bits.

    Parameters
    ----------
    seed : render seed.
    pixel, sample : (n,) integer arrays.
    bounce : int or (n,) ints, the path vertex index (0 = camera ray).
    purpose : a ``Purpose`` value (plus a light offset where relevant).
    index : int or (n,) ints, the sample index within one purpose (e.g. shadow ray j).

    Returns
    -------
    (n,) uint64
    """
    with np.errstate(over="ignore"):
        h = np.full(pixel.shape, np.uint64(seed) * _GOLDEN + np.uint64(purpose), dtype=np.uint64)
        h = _mix(h)
        for part in (pixel, sample):
            h ^= part.astype(np.uint64)
            h = _mix(h + _GOLDEN)
        h ^= np.asarray(bounce, dtype=np.uint64) | (np.asarray(index, dtype=np.uint64) << np.uint64(8))
        return _mix(h + _GOLDEN)


def uniform2(seed: int, pixel: np.ndarray, sample: np.ndarray, bounce: int | np.ndarray,
             purpose: int,
             index: int | np.ndarray = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two independent uniforms in [0, 1) per ray, from one hash.

    Returns
    -------
    u, v : (n,) float32 each
    """
    h = hash_keys(seed, pixel, sample, bounce, purpose, index)
    u = (h >> _TOP24).astype(np.float32) * _INV24
    v = ((h >> _MID24) & _MASK24).astype(np.float32) * _INV24
    return u, v
