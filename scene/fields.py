"""Procedural scalar fields for synthetic scientific scenes, evaluated one brick at a time.

Each field is a callable ``field(x_range, y_range, z_range) -> (nx, ny, nz) float32 | None``
over voxel index ranges of an ``N**3`` grid spanning the unit cube (voxel ``i`` sits at
``i / (N - 1)``), as :class:`vastray.scene.isosurface.FieldVolume` expects. ``None`` means the
brick is known to hold no surface. Everything is a pure function of (seed, resolution), so
scenes are reproducible, and the heavy part of every evaluation is one matrix product.
"""

from __future__ import annotations

import numpy as np


def _coords(r: range, n: int) -> np.ndarray:
    return np.arange(r.start, r.stop, dtype=np.float64) / (n - 1)


class FourierNoise:
    """fBm-like 3-D noise: a sum of random plane waves with a power-law spectrum.

    ``noise(p) = sum_m a_m cos(k_m . p + phi_m)``. Split as ``cos(A + B)`` with ``A`` depending on
    (x, y) and ``B`` on z, a whole brick is ``[a cos A, -a sin A] @ [cos B, sin B].T``.

    Parameters
    ----------
    rng : source of the random modes.
    octaves : frequencies in cycles per unit length, one octave each.
    per_octave : plane waves per octave.
    amplitude : amplitude of the first octave's waves (before the 1/sqrt(per_octave) factor).
    hurst : amplitudes fall as ``(f / f0) ** -hurst``.
    """

    def __init__(self, rng: np.random.Generator, octaves, per_octave: int = 16,
                 amplitude: float = 1.0, hurst: float = 0.8):
        freqs = np.repeat(np.asarray(octaves, np.float64), per_octave)
        freqs *= rng.uniform(0.8, 1.25, freqs.size)
        direction = rng.standard_normal((freqs.size, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        self.k = 2 * np.pi * freqs[:, None] * direction  # (M, 3)
        self.phase = rng.uniform(0, 2 * np.pi, freqs.size)  # (M,)
        self.amp = amplitude * (freqs / freqs.min()) ** -hurst / np.sqrt(per_octave)  # (M,)
        self.sigma = float(np.sqrt(0.5 * np.sum(self.amp ** 2)))

    def __call__(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Noise on the grid x (nx,) by y (ny,) by z (nz,) -> (nx, ny, nz) float32."""
        f32 = np.float32
        ax = (x[:, None] * self.k[:, 0] + self.phase).astype(f32)  # (nx, M)
        ay = (y[:, None] * self.k[:, 1]).astype(f32)  # (ny, M)
        bz = (z[:, None] * self.k[:, 2]).astype(f32)  # (nz, M)
        cx, sx = np.cos(ax) * self.amp.astype(f32), np.sin(ax) * self.amp.astype(f32)
        cy, sy = np.cos(ay), np.sin(ay)
        # a cos(A), a sin(A) with A = kx x + ky y + phase, by the angle-sum identity
        cos_a = cx[:, None] * cy[None] - sx[:, None] * sy[None]  # (nx, ny, M)
        sin_a = sx[:, None] * cy[None] + cx[:, None] * sy[None]
        m = len(self.amp)
        lhs = np.concatenate([cos_a.reshape(-1, m), -sin_a.reshape(-1, m)], axis=1)
        rhs = np.concatenate([np.cos(bz), np.sin(bz)], axis=1)  # (nz, 2M)
        return (lhs @ rhs.T).reshape(len(x), len(y), len(z))


class RichtmyerMeshkov:
    """A Richtmyer-Meshkov-like mixing layer: heavy fluid above a perturbed, turbulent interface.

    The interface height is ``z0 + h(x, y) + n(x, y, z)``: ``h`` a few seeded long-wave
    sinusoidal modes (the initial perturbation), ``n`` fBm noise (the turbulent mixing, clipped
    at 4 sigma so the layer has a hard thickness). Density is ``rho = clip(0.5 + d / (2 w), 0,
    1)`` with ``d`` the signed height above the interface and ``w`` two voxels: a diffuse
    interface whose 0.5 isosurface is a folded sheet across the box.

    Parameters
    ----------
    seed : random seed.
    resolution : voxels per axis, N.
    """

    level = 0.5

    def __init__(self, seed: int, resolution: int):
        rng = np.random.default_rng([seed, 0x524D])
        self.n = int(resolution)
        self.z0 = 0.5
        modes = 6
        self.wave = rng.integers(1, 5, (modes, 2)) * rng.choice([-1, 1], (modes, 2))
        self.wave_amp = rng.uniform(0.01, 0.035, modes)
        self.wave_phase = rng.uniform(0, 2 * np.pi, modes)
        self.noise = FourierNoise(rng, octaves=[3, 6, 12, 24], per_octave=24, amplitude=0.09,
                                  hurst=0.5)
        self.clip = 4.0 * self.noise.sigma
        self.width = 2.0 / (self.n - 1)
        half = float(np.sum(self.wave_amp)) + self.clip + 2 * self.width
        self.layer = (self.z0 - half, self.z0 + half)

    #: name of the per-vertex scalar ``vertex_scalars`` gives (recorded in the store)
    scalar_name = "tanh(height above the unperturbed interface / 2 noise sigma)"

    def vertex_scalars(self, vertices: np.ndarray) -> np.ndarray:
        """(n,) float32 height of each vertex above the unperturbed interface plane, in units
        of twice the mixing noise's sigma and squashed into (-1, 1) by tanh: how far the
        mixing has carried the fluid, with spikes and bubbles at the ends of the colour map."""
        height = (vertices[:, 2] - self.z0) / (2.0 * self.noise.sigma)
        return np.tanh(height).astype(np.float32)

    def __call__(self, xr: range, yr: range, zr: range) -> np.ndarray | None:
        x, y, z = _coords(xr, self.n), _coords(yr, self.n), _coords(zr, self.n)
        if z[-1] < self.layer[0] or z[0] > self.layer[1]:
            return None  # rho is exactly 0 or 1 throughout
        phase = (2 * np.pi * (x[:, None, None] * self.wave[:, 0] + y[None, :, None]
                              * self.wave[:, 1]) + self.wave_phase)
        h = (self.wave_amp * np.sin(phase)).sum(axis=-1)  # (nx, ny)
        n = np.clip(self.noise(x, y, z), -self.clip, self.clip)
        d = (z[None, None, :] - self.z0 - h[:, :, None]).astype(np.float32) - n
        return np.clip(0.5 + d / np.float32(2 * self.width), 0.0, 1.0).astype(np.float32)


class CosmicWeb:
    """A cosmology-like density: Gaussian halos strung along filaments between cluster nodes.

    Cluster nodes are seeded at random; each is joined to its three nearest neighbours by a
    filament; halos are scattered along the filaments (plus big halos on the nodes and a few
    in the voids), with power-law masses and radii growing as mass**(1/3). Each halo is a
    separable Gaussian truncated at 3.5 sigma per axis, so a brick sums only the halos that
    reach it, as one matrix product. The isosurface at ``level`` wraps halos, and where they
    crowd, whole filaments.

    Parameters
    ----------
    seed : random seed.
    resolution : voxels per axis, N.
    """

    level = 0.35
    cutoff = 3.5
    chunk = 512  # halos per matrix product: (brick + 1)**2 x 512 float32 temporaries

    def __init__(self, seed: int, resolution: int):
        rng = np.random.default_rng([seed, 0xC05])
        self.n = int(resolution)
        nodes = rng.uniform(0.1, 0.9, (32, 3))
        dist = np.linalg.norm(nodes[:, None] - nodes[None], axis=-1)
        near = np.argsort(dist, axis=1)[:, 1:4]
        edges = np.unique(np.sort(np.stack([np.repeat(np.arange(len(nodes)), 3),
                                            near.ravel()], axis=1), axis=1), axis=0)
        length = dist[edges[:, 0], edges[:, 1]]
        per_edge = np.maximum(4, (length * 1600).astype(int))
        edge_of = np.repeat(np.arange(len(edges)), per_edge)
        t = rng.uniform(0, 1, edge_of.size)[:, None]
        along = nodes[edges[edge_of, 0]] * (1 - t) + nodes[edges[edge_of, 1]] * t
        fil = along + rng.normal(0, 0.012, along.shape)
        voids = rng.uniform(0, 1, (len(fil) // 20, 3))
        centers = np.concatenate([nodes, fil, voids])
        mass = np.concatenate([rng.uniform(40, 80, len(nodes)),
                               rng.pareto(1.6, len(fil)) + 1.0,
                               rng.pareto(1.6, len(voids)) + 1.0])
        mass = np.minimum(mass, 80.0)
        self.centers = centers  # (H, 3)
        self.sigma = 0.0045 * mass ** (1 / 3)  # (H,)
        self.peak = mass ** 0.25  # (H,)
        self.reach = self.cutoff * self.sigma

    def _gauss(self, coord: np.ndarray, axis: int, halos: np.ndarray) -> np.ndarray:
        """(len(coord), h) float32 truncated Gaussian factors along one axis."""
        d = coord[:, None] - self.centers[halos, axis]
        g = np.exp(-0.5 * (d / self.sigma[halos]) ** 2).astype(np.float32)
        g[np.abs(d) > self.reach[halos]] = 0.0
        return g

    def _reaching(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Halos whose truncated support contains at least one voxel of the brick."""
        ok = np.ones(len(self.centers), dtype=bool)
        for axis, c in enumerate((x, y, z)):
            # nearest brick coordinate to each centre, tested exactly as _gauss tests voxels
            i = np.clip(np.searchsorted(c, self.centers[:, axis]), 1, len(c) - 1)
            d = np.minimum(np.abs(c[i - 1] - self.centers[:, axis]),
                           np.abs(c[i] - self.centers[:, axis]))
            ok &= d <= self.reach
        return np.flatnonzero(ok)

    def __call__(self, xr: range, yr: range, zr: range) -> np.ndarray | None:
        x, y, z = _coords(xr, self.n), _coords(yr, self.n), _coords(zr, self.n)
        halos = self._reaching(x, y, z)
        if len(halos) == 0:
            return None  # density is exactly 0 throughout
        out = np.zeros((len(x) * len(y), len(z)), dtype=np.float32)
        for first in range(0, len(halos), self.chunk):  # bounded temporaries
            h = halos[first:first + self.chunk]
            gx, gy = self._gauss(x, 0, h), self._gauss(y, 1, h)
            gz = self._gauss(z, 2, h) * self.peak[h].astype(np.float32)
            out += (gx[:, None, :] * gy[None, :, :]).reshape(-1, len(h)) @ gz.T
        return out.reshape(len(x), len(y), len(z))


SCENES = {"rm": RichtmyerMeshkov, "cosmo": CosmicWeb}
