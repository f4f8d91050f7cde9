"""The film: per-pixel sums in float64, so accumulation order never shows in the image."""

from __future__ import annotations

import numpy as np

from vastray.render import kernels

#: Batches of the error estimate: sample ``s`` of a pixel adds its radiance (each colour
#: channel apart) to batch ``s mod BATCHES``. 8 batches give each pixel's variance 7
#: degrees of freedom (a t quantile 2.36, not 12.7 as with 2 halves), at 192 bytes a pixel
#: (8 batches x 3 channels, float64); 16 would cost 384 for 15 (2.13). Even, so the even and
#: odd batches are the even and odd samples (the two independent halves of the relMSE
#: denominator). DESIGN.md: "Error estimates".
BATCHES = 8

#: Colour channels of each batch sum: the estimate is of the per-channel relMSE, the metric
#: ``imageio.relative_mse`` measures (a grey estimate is optimistic on coloured pixels).
CHANNELS = 3

#: Bytes of film state per pixel: sum (3 float64), the batches' colour sums (BATCHES x
#: CHANNELS float64), count, depth, normal.
FILM_BYTES_PER_PIXEL = 24 + 8 * BATCHES * CHANNELS + 8 + 4 + 12


#: ``kernels.film_add``'s "not given" (every row counted; every row in batch 0)
_NONE_BOOL = np.zeros(0, np.bool_)
_NONE_INT = np.zeros(0, np.uint32)


def _integers(keys) -> np.ndarray:
    """(n,) pixel or sample keys as the kernels take them: contiguous uint32, the path
    contexts' own type (no copy from those; one kernel signature, so that a node's warm-up
    compiles the one its schedulers use)."""
    return np.ascontiguousarray(keys, np.uint32)


def changing_rows(sample: np.ndarray, paths) -> np.ndarray:
    """(k,) the rows of a batch of partial paths (a ``PathResult``; ``sample`` (n,)) that
    change a film: some radiance (NaN included), or sample 0's first hit (a distance other
    than inf, or a normal). Every other row adds +-0.0 to sums that start at +0.0, and inf and
    zero normals to the first-hit layers: nothing."""
    first_hit = (sample == 0) & ((paths.first_t != np.inf)
                                 | np.any(paths.first_normal != 0, axis=1))
    return np.flatnonzero(np.any(paths.radiance != 0, axis=1) | first_hit)


class Film:
    """Accumulates path radiance per pixel.

    Besides the sum of every sample, the film keeps per pixel ``BATCHES`` sums of radiance
    per colour channel, batch ``b`` over the samples numbered ``s`` with ``s mod BATCHES ==
    b`` (``batch``): the batch means differ by noise alone, which estimates each pixel's and
    channel's variance (``variance_of_mean``) with ``BATCHES - 1`` degrees of freedom, and the
    even and odd batches are two independent halves (``rel_mse_terms``). The sums are linear
    in the radiance, so they stay exact when the parts of one path are added on different
    nodes (a sum of squares would square the parts, not the path).

    Parameters
    ----------
    width, height : image size; pixel index = ``row * width + column``, row 0 at the top.
    """

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        n = width * height
        self.sum = np.zeros((n, 3))  # (P, 3) float64, sum of sample radiance
        # (P, B, 3) float64, colour sums by sample mod B
        self.batch = np.zeros((n, BATCHES, CHANNELS))
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
        sample : (n,) sample number of each row: its radiance adds to batch ``sample mod
            BATCHES`` (default: batch 0).
        """
        if len(pixel) == 0:
            return
        # Bins over the batch's pixel run only (a batch covers a run of pixels): the cost
        # follows the batch, not the film. Adding the zeros of other pixels changed nothing.
        kernels.film_add(self.sum, self.batch, self.count, _integers(pixel),
                         np.ascontiguousarray(radiance, np.float64),
                         _NONE_BOOL if counted is None else np.ascontiguousarray(counted, np.bool_),
                         _NONE_INT if sample is None else _integers(sample))

    def add_paths(self, pixel: np.ndarray, sample: np.ndarray, paths,
                  counted: np.ndarray | None = None) -> None:
        """Add a batch of finished paths (a ``PathResult``) with keys (n,) pixel and sample;
        sample 0 of each pixel sets the depth and normal layers."""
        pixel, sample = _integers(pixel), _integers(sample)  # once, for both kernels
        self.add(pixel, paths.radiance, counted, sample)
        kernels.film_first_hits(self.depth, self.normal, pixel, sample,
                                np.ascontiguousarray(paths.first_t, np.float32),
                                np.ascontiguousarray(paths.first_normal, np.float32))

    def count_samples(self, pixel: np.ndarray) -> None:
        """Count one sample per entry of ``pixel`` (n,) without adding radiance: a path is
        counted where it starts, its radiance may arrive later and in parts."""
        if len(pixel):
            lo, hi = int(pixel.min()), int(pixel.max()) + 1
            self.count[lo:hi] += np.bincount(pixel - lo, minlength=hi - lo)

    def add_partial(self, pixel: np.ndarray, sample: np.ndarray, paths) -> None:
        """Add what part of a batch of paths was gathered here (a ``PathResult``): radiance
        sums, and the first-hit layers of sample 0 where this part saw the camera hit. Parts
        of one path from elsewhere add up; samples are counted by ``count_samples``.

        Only the rows that change the film are folded in (``changing_rows``): under domain
        decomposition each node holds every path of a tile it took part in, most of them
        traced elsewhere (on 8 nodes a node folded all 49,152 paths of each tile, 1.6 ms a
        tile on its event loop); the others add zeros, which change no sum's bits."""
        rows = changing_rows(sample, paths)
        pixel, sample = pixel[rows], sample[rows]
        self.add(pixel, paths.radiance[rows], counted=np.zeros(len(rows), bool), sample=sample)
        zero = np.nonzero(sample == 0)[0]
        np.minimum.at(self.depth, pixel[zero], paths.first_t[rows][zero])
        self.normal[pixel[zero]] += paths.first_normal[rows][zero]

    def merge(self, other: Film) -> None:
        """Add another node's partial film. Sums and counts add; each pixel's depth and normal
        come from the one film that traced its sample 0 (the others hold inf and zeros), so
        MIN and SUM merge them exactly."""
        self.sum += other.sum
        self.batch += other.batch
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
        """(H, W, 3) float64 estimated variance of each pixel's mean per colour channel, from
        its batch means.

        With ``n`` samples in ``k = min(n, BATCHES)`` non-empty batches of ``n_b`` samples
        and means ``m_b``, ``sum_b n_b (m_b - m)**2 / ((k - 1) n)`` is an unbiased estimate
        of ``s2 / n``, the variance of the pixel's mean (one-way ANOVA's between-batch
        square sum has expectation ``(k - 1) s2``), with ``k - 1`` degrees of freedom. NaN
        where a pixel has fewer than 2 samples. Samples must be numbered from 0 without gaps
        (every render's are): the batch sizes follow from ``count``.
        """
        return self._grid(batch_estimates(self.batch, self.count)[1])

    def variance_of_mean_radiance(self) -> float:
        """Estimated variance of the image's mean radiance (over pixels and channels): the
        variance of each pixel's channel mean (channels of one path are correlated: from the
        batches' channel means) summed over independent pixels / P**2. NaN below 2 spp."""
        grey = self.batch.sum(axis=2) / CHANNELS
        per_pixel = batch_estimates(grey, self.count)[1]
        return float(np.sum(per_pixel) / max(len(per_pixel), 1) ** 2)

    def rel_mse_terms(self, epsilon: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Two estimates per pixel and channel (P, 3) of the relMSE of the pixel's mean that
        bracket it, and per pixel (P,) the degrees of freedom of its variance; NaN below 2
        samples. Their means over pixels and channels estimate ``imageio.relative_mse``,
        term for term.

        Both divide the variance of the mean, a sum over the batches ``var = sum_b v_b``,
        ``v_b = n_b (m_b - m)**2 / ((k - 1) n)`` (``variance_of_mean``), by an estimate of
        ``r**2 + ε`` from the means of the even and of the odd batches (independent halves):
        ``inclusive`` = ``var / (a o + ε)``, the halves whole; ``exclusive`` = ``sum_b v_b /
        (a_b o_b + ε)``, batch ``b`` left out of its half, so that each ``v_b`` is divided by
        a denominator independent of it. Where a rare bright sample is a firefly (the mean
        carried by the other samples), it makes one ``v_b`` large and the inclusive
        denominator grows with it: that term grows as the outlier, not as its square, and
        ``inclusive`` is optimistic (3-4x on ``bench/convergence.py``'s hidden lamp), while
        ``exclusive`` is right. Where rare bright samples carry the mean (a light seen only
        through rare paths), the exclusive denominator misses them and ``exclusive`` is
        pessimistic (10-20x in ``tests/test_error_estimates.py``'s heavy-tailed case), while
        ``inclusive`` is right. Without heavy tails the two agree to order ``m``."""
        return rel_mse_terms(self.batch, self.count, epsilon)

    def depth_image(self) -> np.ndarray:
        return self._grid(self.depth)

    def normal_image(self) -> np.ndarray:
        return self._grid(self.normal)


def batch_sizes(count: np.ndarray, batches: int = BATCHES) -> np.ndarray:
    """(P, B) samples in each batch of pixels with ``count`` (P,) samples numbered from 0."""
    b = np.arange(batches)
    return np.maximum((count[:, None] + batches - 1 - b) // batches, 0)


def batch_estimates(batch: np.ndarray, count: np.ndarray, halves: bool = False) -> tuple:
    """From the batch sums (P, B) or (P, B, C) (C channels) and sample counts (P,): per
    pixel (and channel) the mean, the estimated variance of the mean
    (``Film.variance_of_mean``; NaN below 2 samples) and, with ``halves``, the means of the
    even and of the odd batches and per pixel (P,) the number of non-empty batches."""
    n = count.astype(np.float64)
    sizes = batch_sizes(count, batch.shape[1]).astype(np.float64)
    k = np.minimum(n, batch.shape[1])
    # per-pixel figures broadcast over the channels, if any; one batch at a time, so the
    # temporaries are of one batch's size, not of all of them (preflight counts film copies)
    extra = (None,) * (batch.ndim - 2)
    n_, k_ = n[(slice(None), *extra)], k[(slice(None), *extra)]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = batch.sum(axis=1) / n_
        square = np.zeros_like(mean)
        for b in range(batch.shape[1]):
            size = sizes[(slice(None), b, *extra)]
            square += size * (np.where(size > 0, batch[:, b] / np.maximum(size, 1), 0.0)
                              - mean) ** 2
        var = np.where(n_ >= 2, square / ((k_ - 1) * n_), np.nan)
        if not halves:
            return mean, var
        even = batch[:, 0::2].sum(axis=1) / sizes[:, 0::2].sum(axis=1)[(slice(None), *extra)]
        odd = batch[:, 1::2].sum(axis=1) / sizes[:, 1::2].sum(axis=1)[(slice(None), *extra)]
    return mean, var, np.where(n_ >= 2, even, np.nan), np.where(n_ >= 2, odd, np.nan), k


def rel_mse_terms(batch: np.ndarray, count: np.ndarray, epsilon: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Film.rel_mse_terms`` of the batch sums (P, B, C) (or (P, B)) and counts (P,):
    (inclusive, exclusive, degrees of freedom)."""
    n = count.astype(np.float64)
    nb = batch.shape[1]
    sizes = batch_sizes(count, nb).astype(np.float64)
    k = np.minimum(n, nb)
    extra = (None,) * (batch.ndim - 2)
    n_, k_ = n[(slice(None), *extra)], k[(slice(None), *extra)]
    var = np.zeros(batch.shape[:1] + batch.shape[2:])
    exclusive = np.zeros_like(var)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = batch.sum(axis=1) / n_
        halves = [(batch[:, h::2].sum(axis=1), sizes[:, h::2].sum(axis=1)[(slice(None), *extra)])
                  for h in (0, 1)]
        full = [total / size for total, size in halves]
        for b in range(nb):  # one batch at a time: temporaries of (P, C)
            size = sizes[(slice(None), b, *extra)]
            v = size * (np.where(size > 0, batch[:, b] / np.maximum(size, 1), 0.0)
                        - mean) ** 2 / ((k_ - 1) * n_)
            var += np.where(size > 0, v, 0.0)
            total, rest = halves[b % 2]
            # batch b's half without it (the whole half where b is all of it: below 3 spp)
            own = np.where(rest > size, (total - batch[:, b]) / (rest - size), full[b % 2])
            # a product of two independent means estimates r**2 without bias but may be
            # negative where r is near 0 and the samples signed: taken as 0 there
            exclusive += np.where(size > 0, v / (np.maximum(own * full[1 - b % 2], 0.0)
                                                 + epsilon), 0.0)
        inclusive = var / (np.maximum(full[0] * full[1], 0.0) + epsilon)
    ok = n_ >= 2
    return np.where(ok, inclusive, np.nan), np.where(ok, exclusive, np.nan), k - 1.0
