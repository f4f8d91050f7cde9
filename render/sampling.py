"""Direction sampling and orthonormal frames, vectorised over rays."""

from __future__ import annotations

import numpy as np


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
    """Cosine-weighted directions about each normal (pdf = cos(theta) / pi).

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
