"""The film: per-pixel sums in float64, so accumulation order never shows in the image."""

from __future__ import annotations

import numpy as np

from vastray.render import kernels

#: Bytes of film state per pixel: sum and sum_odd (3 float64 each), count, depth, normal.
FILM_BYTES_PER_PIXEL = 24 + 24 + 8 + 4 + 12


class Film:
    """Accumulates path radiance per pixel.

    Besides the sum of every sample, the film keeps the sum of the odd-numbered samples
    (``sum_odd``): the means of the two halves (even and odd samples) differ by noise alone,
    which estimates each pixel's variance (``variance_of_mean``). Both sums are linear in the
    radiance, so they stay exact when the parts of one path are added on different nodes
    (a sum of squares would square the parts, not the path).

    Parameters
    ----------
    width, height : image size; pixel index = ``row * width + column``, row 0 at the top.
    """

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        n = width * height
        self.sum = np.zeros((n, 3))  # (P, 3) float64, sum of sample radiance
        self.sum_odd = np.zeros((n, 3))  # (P, 3) float64, sum over odd-numbered samples
        self.count = np.zeros(n, dtype=np.int64)  # (P,) samples added
        self.depth = np.full(n, np.inf, dtype=np.float32)  # (P,) first-hit distance, sample 0
        self.normal = np.zeros((n, 3), dtype=np.float32)  # (P, 3) first-hit facing normal

    def add(self, pixel: np.ndarray, radiance: np.ndarray,
            counted: np.ndarray | None = None, sample: np.ndarray | None = None) -> None:
        """Add one sample per row, in one compiled pass (``kernels.film_add``; the sums are
        those of ``np.bincount`` bit for bit, ``tests/test_kernels.py`` compares them).

        Parameters
        ----------
        pixel : (n,) pixel index of each sample.
        radiance : (n, 3) float64 radiance of each sample's whole path.
        counted : (n,) bool, the rows that count as samples (default: all). Under domain
            decomposition several nodes add parts of one path; exactly one counts it.
        sample : (n,) sample number of each row; the odd ones also add to ``sum_odd``
            (default: none are odd).
        """
        if len(pixel) == 0:
            return
        # Bins over the batch's pixel range only (a batch covers a run of pixels): the cost
        # follows the batch, not the film. Adding the zeros of other pixels changed nothing.
        lo = int(pixel.min())
        local = pixel - lo
        kernels.film_add(self.sum, self.sum_odd, self.count, lo,
                         np.ascontiguousarray(local, np.int64),
                         np.ascontiguousarray(radiance, np.float64),
                         np.ones(len(local), np.bool_) if counted is None
                         else np.ascontiguousarray(counted, np.bool_),
                         np.zeros(len(local), np.bool_) if sample is None
                         else np.ascontiguousarray(sample % 2 == 1, np.bool_))

    def add_paths(self, pixel: np.ndarray, sample: np.ndarray, paths,
                  counted: np.ndarray | None = None) -> None:
        """Add a batch of finished paths (a ``PathResult``) with keys (n,) pixel and sample;
        sample 0 of each pixel sets the depth and normal layers."""
        self.add(pixel.astype(np.int64), paths.radiance, counted, sample)
        zero = sample == 0
        self.depth[pixel[zero]] = paths.first_t[zero]
        self.normal[pixel[zero]] = paths.first_normal[zero]

    def count_samples(self, pixel: np.ndarray) -> None:
        """Count one sample per entry of ``pixel`` (n,) without adding radiance: a path is
        counted where it starts, its radiance may arrive later and in parts."""
        if len(pixel):
            lo, hi = int(pixel.min()), int(pixel.max()) + 1
            self.count[lo:hi] += np.bincount(pixel - lo, minlength=hi - lo)

    def add_partial(self, pixel: np.ndarray, sample: np.ndarray, paths) -> None:
        """Add what part of a batch of paths was gathered here (a ``PathResult``): radiance
        sums, and the first-hit layers of sample 0 where this part saw the camera hit. Parts
        of one path from elsewhere add up; samples are counted by ``count_samples``."""
        self.add(pixel.astype(np.int64), paths.radiance, counted=np.zeros(len(pixel), bool),
                 sample=sample)
        zero = np.nonzero(sample == 0)[0]
        np.minimum.at(self.depth, pixel[zero], paths.first_t[zero])
        self.normal[pixel[zero]] += paths.first_normal[zero]

    def merge(self, other: Film) -> None:
        """Add another node's partial film. Sums and counts add; each pixel's depth and normal
        come from the one film that traced its sample 0 (the others hold inf and zeros), so
        MIN and SUM merge them exactly."""
        self.sum += other.sum
        self.sum_odd += other.sum_odd
        self.count += other.count
        np.minimum(self.depth, other.depth, out=self.depth)
        self.normal += other.normal

    def _grid(self, a: np.ndarray) -> np.ndarray:
        return a.reshape(self.height, self.width, *a.shape[1:])

    def image(self) -> np.ndarray:
        """(H, W, 3) float32 mean radiance; a mean beyond float32's range becomes ``inf``
        (``report.count_overflow`` counts and reports those pixels)."""
        mean = self.sum / np.maximum(self.count, 1)[:, None]
        with np.errstate(over="ignore"):
            return self._grid(mean).astype(np.float32)

    def variance_of_mean(self) -> np.ndarray:
        """(H, W, 3) float64 estimated variance of each pixel's mean, from its two halves.

        With ``n`` samples, ``n_odd = n // 2`` of them odd-numbered: the mean of the odd
        samples ``b`` and of the even ones ``a`` differ by noise with variance
        ``s2 (1/n_even + 1/n_odd)``, so ``(a - b)**2 n_even n_odd / n**2`` is an unbiased
        estimate of ``s2 / n``, the variance of the pixel's mean. It has one degree of
        freedom per pixel: sound summed or averaged over many pixels (the image's estimated
        relative MSE, the confidence interval of its mean), not for one pixel or a small
        block that a few bright samples dominate (two of them, one in each half, make the
        halves agree). NaN where a pixel has fewer than 2 samples. Samples must be numbered
        from 0 without gaps (every render's are).
        """
        return self._grid(_half_variance(self.sum, self.sum_odd, self.count[:, None]))

    def variance_of_mean_radiance(self) -> float:
        """Estimated variance of the image's mean radiance (over pixels and channels): the
        per-pixel estimate of ``variance_of_mean`` on each pixel's channel mean (channels of
        one path are correlated), summed over independent pixels / P**2. NaN below 2 spp."""
        per_pixel = _half_variance(self.sum.mean(axis=1), self.sum_odd.mean(axis=1),
                                   self.count)
        return float(np.sum(per_pixel) / max(len(per_pixel), 1) ** 2)

    def depth_image(self) -> np.ndarray:
        return self._grid(self.depth)

    def normal_image(self) -> np.ndarray:
        return self._grid(self.normal)


def _half_variance(total: np.ndarray, odd: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Variance of the mean from the sums of all and of the odd-numbered samples (``count``
    broadcast against them); NaN below 2 samples. See ``Film.variance_of_mean``."""
    n = count.astype(np.float64)
    n_odd = np.floor(n / 2)
    n_even = n - n_odd
    with np.errstate(invalid="ignore", divide="ignore"):
        var = ((total - odd) / n_even - odd / n_odd) ** 2 * n_even * n_odd / n ** 2
    return np.where(n >= 2, var, np.nan)
