"""Pinhole camera: primary rays for (pixel, sample) pairs."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from vastray.render import kernels
from vastray.render.rng import Purpose, uniform2

#: ``camera_rays_in_box``'s ``seen`` for every pixel.
_NO_PIXELS = np.zeros(0, np.bool_)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes
    ----------
    position, look_at, up : (3,) float64
    fov : vertical field of view in degrees.
    width, height : image size in pixels; row 0 is the top of the image.
    """

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float
    width: int
    height: int

    @staticmethod
    def framing(lo: np.ndarray, hi: np.ndarray, width: int, height: int,
                fov: float = 35.0) -> Camera:
        """A camera that frames the box ``[lo, hi]`` from an oblique viewpoint."""
        center = (lo + hi) / 2.0
        radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-30)
        view = np.array([0.55, 0.45, 1.0])
        view /= np.linalg.norm(view)
        half = np.radians(fov) / 2.0
        half_min = min(half, np.arctan(np.tan(half) * width / height))
        distance = radius / np.sin(half_min) * 1.02
        return Camera(center + view * distance, center, np.array([0.0, 1.0, 0.0]), fov,
                      width, height)

    def in_frame(self, origin: np.ndarray) -> Camera:
        """This camera in a frame whose origin sits at ``origin`` ((3,) float64, world): its
        position and target minus ``origin`` (in float64, so a camera far from the world
        origin keeps its place relative to the data); itself when ``origin`` is zero."""
        origin = np.asarray(origin, np.float64)
        if not origin.any():
            return self
        return dataclasses.replace(self, position=self.position - origin,
                                   look_at=self.look_at - origin)

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit forward, right and up vectors (float64)."""
        forward = self.look_at - self.position
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        norm = np.linalg.norm(right)
        if norm < 1e-12:
            raise ValueError("camera up vector is parallel to the view direction")
        right /= norm
        return forward, right, np.cross(right, forward)

    def generate(self, pixel: np.ndarray, sample: np.ndarray, seed: int
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays with a box-filtered jitter inside each pixel.

        Parameters
        ----------
        pixel : (n,) uint32, ``row * width + column``.
        sample : (n,) uint32 sample index within the pixel.
        seed : render seed.

        Returns
        -------
        origins : (n, 3) float64
        directions : (n, 3) float64, unit length
        """
        forward, right, up = self.frame()
        jx, jy = uniform2(seed, pixel, sample, 0, Purpose.CAMERA_JITTER)
        column = (pixel % self.width).astype(np.float64) + jx
        row = (pixel // self.width).astype(np.float64) + jy
        tan_half = np.tan(np.radians(self.fov) / 2.0)
        aspect = self.width / self.height
        sx = (2.0 * column / self.width - 1.0) * tan_half * aspect
        sy = (1.0 - 2.0 * row / self.height) * tan_half
        d = forward[None, :] + sx[:, None] * right[None, :] + sy[:, None] * up[None, :]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.position, d.shape).copy(), d

    def generate32(self, pixel: np.ndarray, sample: np.ndarray, seed: int,
                   advance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``generate``'s rays cast to float32 ((n, 3) each), in one fused kernel
        (``kernels.camera_rays``; bit for bit the same, tested), each starting ``advance``
        along its direction (``start_distance``), computed in float64."""
        n = len(pixel)
        origin, direction = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        kernels.camera_rays(*self._kernel_inputs(pixel, sample, seed, advance), origin,
                            direction)
        return origin, direction

    def generate32_in_box(self, pixel: np.ndarray, sample: np.ndarray, seed: int,
                          advance: float, lo: np.ndarray, hi: np.ndarray,
                          seen: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``generate32``'s rays, bit for bit, of the samples whose ray enters the box
        ``[lo, hi]`` ((3,) float64 each; the caller grows it against rounding) through a pixel
        ``seen`` keeps ((width * height,) bool, ``render.seen_pixels``; None: every pixel), in
        one fused kernel (``kernels.camera_rays_in_box``).

        Returns
        -------
        rows : (k,) int64 the kept samples' rows of ``pixel``, ascending
        origins, directions : (k, 3) float32 their rays
        """
        n = len(pixel)
        rows = np.empty(n, np.int64)
        origin, direction = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        kept = kernels.camera_rays_in_box(
            *self._kernel_inputs(pixel, sample, seed, advance), np.asarray(lo, np.float64),
            np.asarray(hi, np.float64),
            _NO_PIXELS if seen is None else np.ascontiguousarray(seen, np.bool_), rows, origin,
            direction)
        return rows[:kept], origin[:kept], direction[:kept]

    def _kernel_inputs(self, pixel: np.ndarray, sample: np.ndarray, seed: int,
                       advance: float) -> tuple:
        """The camera kernels' inputs before their outputs (``kernels.camera_rays``' pixel
        .. advance), as ``generate`` computes them."""
        forward, right, up = self.frame()
        return (np.ascontiguousarray(pixel, np.uint32), np.ascontiguousarray(sample, np.uint32),
                np.uint64(seed), np.uint64(Purpose.CAMERA_JITTER), self.width, self.height,
                float(np.tan(np.radians(self.fov) / 2.0)), self.width / self.height,
                np.asarray(self.position, np.float64), forward, right, up, float(advance))


def start_distance(eye: np.ndarray, clip: np.ndarray) -> float:
    """How far from the camera at ``eye`` ((3,)) its rays may start: 0, unless the box
    ``clip`` ((2, 3): the scene and its area lights) is more than 16 box diagonals away; then
    the distance to the box less one diagonal, where nothing can be hit yet.

    From that far, float32's rounding of the camera's coordinates and of the directions
    (2^-24 of the distance each) would move every sample by up to a pixel; a ray that starts
    near the box, placed in float64 along its float64 direction, is off by 2^-24 of a few
    diagonals instead. Nearer cameras keep their rays exactly as ``Camera.generate`` makes
    them.
    """
    lo, hi = np.asarray(clip, np.float64)
    diagonal = float(np.linalg.norm(hi - lo))
    gap = float(np.linalg.norm(np.maximum(np.maximum(lo - eye, eye - hi), 0.0)))
    return gap - diagonal if gap > 16.0 * diagonal else 0.0
