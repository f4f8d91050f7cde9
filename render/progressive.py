"""Progressive rendering: sample-major passes, the error after each, and when to stop.

A render of ``spp`` samples per pixel runs as passes: pass k adds samples ``b_k <= s <
b_{k+1}`` to every pixel, with bounds 0, 1, 2, 4, 8, ... (doubling, so a log-log plot of error
against time gets evenly spaced points) and then steps of at most ``max_pass_spp``. The bounds
depend only on the sample numbers, never on time or on the machine, so a run that stops and
resumes adds exactly the passes an uninterrupted run adds. Each pass renders into a film of
its own, merged into the image's afterwards: the film after pass k is the same whatever the
scheduler, node count, cache or threads (DESIGN.md's invariance rule, at every pass).

Nothing here does I/O: the runtimes (``render.driver``, ``actors.local``, the coordinator) ask
``Progression.next_pass`` what to render and hand back each pass's film.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from vastray.render.film import Film
from vastray.render.imageio import REL_MSE_EPSILON, image_error

#: The most samples one pass adds per pixel (once the doubling passes reach it).
DEFAULT_MAX_PASS_SPP = 16

#: Two-sided 95 % quantile of the normal distribution.
Z95 = 1.959963984540054

#: One-sided risk of ``--target-error`` without a reference stopping above its target, over
#: all the looks of one render (split evenly over its passes: Bonferroni).
STOP_ALPHA = 0.05

#: Why a render stopped (the report's ``stopped_by``).
STOP_REASONS = ("spp", "time-limit", "target-error", "interrupted")


def pass_bounds(spp: int, max_pass_spp: int = DEFAULT_MAX_PASS_SPP) -> list[tuple[int, int]]:
    """The passes of ``spp`` samples: [(0, 1), (1, 2), (2, 4), (4, 8), ...], each at most
    ``max_pass_spp`` samples, the last cut at ``spp``."""
    if spp < 1 or max_pass_spp < 1:
        raise ValueError("spp and max_pass_spp must be at least 1")
    bounds, first = [], 0
    while first < spp:
        stop = min(first + min(max(first, 1), max_pass_spp), spp)
        bounds.append((first, stop))
        first = stop
    return bounds


@dataclass(frozen=True)
class StopRules:
    """When a progressive render stops: at ``spp`` samples per pixel at most; before a pass
    that would end after ``time_limit`` seconds (predicted from the last pass's time per
    sample; the first pass always runs); after the pass whose relative MSE is at most
    ``target_error`` (against the reference, or estimated from the film without one)."""

    spp: int
    time_limit: float | None = None
    target_error: float | None = None
    max_pass_spp: int = DEFAULT_MAX_PASS_SPP
    #: every sample in one pass (no series to speak of): what runtimes do when asked for
    #: no passes, e.g. ``render_distributed`` called without progressions.
    one_pass: bool = False

    @property
    def paced(self) -> bool:
        """Whether each pass must wait for the verdict on the one before (a rule that may
        stop the render early)."""
        return self.time_limit is not None or self.target_error is not None


def normal_quantile(p: float) -> float:
    """The standard normal's ``p`` quantile (``statistics.NormalDist``)."""
    from statistics import NormalDist
    return NormalDist().inv_cdf(p)


def rel_mse_estimate(film: Film, epsilon: float = REL_MSE_EPSILON) -> dict | None:
    """The film's estimate of its own per-pixel relative MSE, without a reference (None
    below 2 spp): of ``imageio.relative_mse``, the mean over pixels and colour channels of
    ``(x - r)**2 / (r**2 + ε)``, ε = ``REL_MSE_EPSILON``. DESIGN.md, "Error estimates",
    derives it.

    Per pixel and channel two estimates bracket the term (``Film.rel_mse_terms``): ``t``
    (``exclusive``: each batch's share of the variance of the mean over a product of even and
    odd batches' means without that batch; right with fireflies, pessimistic where rare
    bright paths carry the mean) and ``u`` (``inclusive``: the variance over the product of
    the whole halves' means; right where rare paths carry the mean, optimistic with
    fireflies). The denominators' inverses overestimate ``1/r**2`` by about ``4 m``
    relative (``m``: the term's relMSE; each half's mean has relative variance ``2 m``), so
    both lean pessimistic; ``c = (sqrt(1 + 16 u) - 1) / 8`` inverts ``u = m (1 + 4 m)``
    (the delta method's correction, optimistic where ``m`` is not small). Keys:
    ``estimate`` (mean of ``t`` over pixels and channels: not optimistic; the stop rule's),
    ``se`` (its standard error against the realised error: per pixel ``(2 + 2 / dof)
    T**2``, ``T`` the pixel's mean of ``t`` over its channels, the chi-square spread of the
    realised error and of the batch variance with the channels' noise taken as fully
    correlated (an upper bound: one path carries every channel), over independent pixels),
    ``ci95`` = [mean c - z se_c, mean t + z se] (from the optimistic end of the one to the
    pessimistic end of the other) and ``inclusive`` (mean of ``u``).
    """
    inclusive, exclusive, dof = film.rel_mse_terms(epsilon)  # (P, 3), (P, 3), (P,)
    ok = np.isfinite(exclusive) & np.isfinite(inclusive)
    if not ok.any():
        return None
    t = np.where(ok, exclusive, 0.0)
    u = np.where(ok, inclusive, 0.0)
    d = np.where(ok.all(axis=1), dof, 1.0)
    corrected = (np.sqrt(1.0 + 16.0 * u) - 1.0) / 8.0
    pixels = len(t)
    # per pixel, the channels' mean: their noise comes from the same paths
    pixel_t, pixel_c = t.mean(axis=1), corrected.mean(axis=1)
    se = float(np.sqrt(np.sum((2.0 + 2.0 / d) * pixel_t ** 2)) / pixels)
    se_c = float(np.sqrt(np.sum((2.0 + 2.0 / d) * pixel_c ** 2)) / pixels)
    raw, low = float(np.mean(pixel_t)), float(np.mean(pixel_c))
    return {"estimate": raw, "se": se, "inclusive": float(np.mean(u)),
            "ci95": [max(min(low, raw) - Z95 * se_c, 0.0), raw + Z95 * se]}


def stop_bound(point: dict, looks: int, alpha: float = STOP_ALPHA) -> float | None:
    """The upper confidence bound the target-error rule compares with (no reference): the
    raw estimate plus ``z(1 - alpha / looks)`` standard errors, one-sided, ``looks`` the
    render's passes (Bonferroni: the chance that any look's bound is below the truth is at
    most ``alpha``)."""
    raw, se = point.get("estimated_rel_mse"), point.get("estimated_rel_mse_se")
    if raw is None or se is None:
        return None
    return raw + normal_quantile(1.0 - alpha / max(looks, 1)) * se


def pass_point(film: Film, index: int, seconds: float,
               reference: np.ndarray | None = None) -> dict:
    """One entry of the report's ``passes``: the film after pass ``index`` at ``seconds``.

    Keys: ``pass``, ``seconds``, ``spp`` (samples per pixel so far); against ``reference``
    ((H, W, 3), else None) ``mse``, ``rel_mse`` (per pixel, ``imageio.relative_mse``),
    ``rel_mse_global`` (``mse / mean(r**2)``, energy-normalised: another metric),
    ``psnr_db``; from the film alone ``variance_of_mean`` (the image's mean over pixels and
    channels of the estimated variance of each pixel's mean), ``estimated_rel_mse``
    (``rel_mse_estimate``: the per-pixel relative MSE ``rel_mse`` is, same ε and channels,
    that the noise alone gives) with ``estimated_rel_mse_ci95`` and
    ``estimated_rel_mse_se``, and ``mean_radiance`` with
    ``ci95``, its 95 % confidence interval. Estimates need 2 samples per pixel (None before).
    """
    image = film.image()
    spp = int(film.count.max()) if film.count.size else 0
    point = {"pass": int(index), "seconds": round(float(seconds), 4), "spp": spp}
    error = image_error(image, reference) if reference is not None else {}
    for key in ("mse", "rel_mse", "rel_mse_global", "psnr_db"):
        point[key] = error.get(key)
    x = image.astype(np.float64)
    mean = float(np.mean(x)) if x.size else 0.0
    var = film.variance_of_mean() if spp >= 2 else None
    point["variance_of_mean"] = None if var is None else float(np.nanmean(var))
    estimate = rel_mse_estimate(film) if spp >= 2 else None
    point["estimated_rel_mse"] = None if estimate is None else estimate["estimate"]
    point["estimated_rel_mse_ci95"] = None if estimate is None else estimate["ci95"]
    point["estimated_rel_mse_se"] = None if estimate is None else estimate["se"]
    point["mean_radiance"] = mean
    spread = film.variance_of_mean_radiance() if spp >= 2 else None
    point["ci95"] = (None if spread is None else
                     [mean - Z95 * float(np.sqrt(spread)), mean + Z95 * float(np.sqrt(spread))])
    return point


def passes_in_time(budget_s: float | None, running_s: float, per_sample_s: float | None,
                   spp: list[int], ahead_s: float = 0.0, traced: list[float] = ()) -> int:
    """How many of the passes after the current one the time rule may still grant, by its
    own prediction (the rule: ``Progression.next_pass``).

    Passes may be traced partly ahead of their turn (``SortFirstTiles.render_ahead``), so
    the rule predicts from a pass's work as if swept alone (``pass_work``: its seconds less
    those spent on later passes, plus those its own rays took before it led), and takes off
    a pass's prediction what was traced of it ahead. Here the current pass (``spp[0]``
    samples a pixel, granted with ``budget_s`` seconds of the limit left) has run
    ``running_s`` seconds, ``ahead_s`` of them on later passes. Its own work left takes
    ``own = max(running_s - ahead_s, per_sample_s * spp[0] - traced[0])`` (at least what it
    has run; the last pass's seconds a sample of work, ``per_sample_s``, where there is
    one), it ends after ``own + ahead_s``, its work a sample is ``(own + traced[0]) /
    spp[0]``, and pass i after it takes ``max(that * spp[i] - traced[i], 0)``: it is granted
    if the passes up to it end within ``budget_s``. Without anything traced ahead this is
    the rule for passes swept alone: each pass at the last one's seconds a sample. In the
    first pass (no ``per_sample_s``) only the next pass is predicted.

    Parameters
    ----------
    budget_s : seconds left of the time limit when the current pass was granted (None: no
        limit, every pass may be granted).
    running_s : seconds the current pass has run.
    per_sample_s : the last pass's seconds of work a sample (None: no pass done yet).
    spp : (K,) samples a pixel of the current pass and of each after it.
    ahead_s : of ``running_s``, the seconds spent tracing later passes ahead.
    traced : (<= K,) seconds each of those passes' rays were traced before it led (none:
        0; the current pass's before it was granted, the later ones' so far).
    """
    if budget_s is None:
        return len(spp) - 1
    if per_sample_s is None:
        # the first pass: its time so far says little of its work yet, so no pass beyond
        # the next is predicted (riders of later passes would delay the first pass's end
        # past the point where the rule grants the next)
        spp = spp[:2]
    traced = (list(traced) + [0.0] * len(spp))[:len(spp)]
    own = max(running_s - ahead_s, (per_sample_s or 0.0) * spp[0] - traced[0])
    per_sample = (own + traced[0]) / max(spp[0], 1)
    total, count = own + ahead_s, 0
    for samples, done in zip(spp[1:], traced[1:], strict=True):
        total += max(per_sample * samples - done, 0.0)
        if total > budget_s:
            break
        count += 1
    return count


def pass_work(point: dict) -> float:
    """A pass's work as if swept alone: its seconds less those spent tracing later passes
    ahead (``ahead_seconds``) plus those its own rays took before it led
    (``rode_seconds``); a point written before those keys, its seconds. What the time rule
    predicts the next pass's seconds a sample from."""
    return max((point.get("pass_seconds") or 0.0) - (point.get("ahead_seconds") or 0.0)
               + (point.get("rode_seconds") or 0.0), 0.0)


@dataclass(frozen=True)
class Snapshot:
    """The image after the passes done so far, replaced whole after each pass (so a signal
    handler that reads it never sees a half-merged film)."""

    film: Film
    passes_done: int
    series: tuple = ()  # pass_point dicts
    seconds: float = 0.0  # render time up to the end of the last pass


@dataclass
class Progression:
    """The passes of one image: which to render next, the film so far and its error series.

    Parameters
    ----------
    width, height : image size.
    rules : when to stop.
    reference : (H, W, 3) image to measure against (also what ``target_error`` compares
        with), or None.
    resumed : a checkpoint's snapshot to go on from (None: from the first pass).
    on_pass : called as ``on_pass(progression)`` after each pass is merged (checkpoints).
    """

    width: int
    height: int
    rules: StopRules
    reference: np.ndarray | None = None
    resumed: Snapshot | None = None
    on_pass: Callable[[Progression], None] | None = None
    snapshot: Snapshot = field(init=False)
    stopped_by: str | None = field(init=False, default=None)
    #: what the target-error rule compared with ``target_error`` when it stopped the render
    #: (the relMSE against the reference, or the estimate's upper bound ``stop_bound``)
    stopped_at: float | None = field(init=False, default=None)
    passes: list = field(init=False)

    def __post_init__(self):
        self.passes = ([(0, self.rules.spp)] if self.rules.one_pass
                       else pass_bounds(self.rules.spp, self.rules.max_pass_spp))
        self.snapshot = self.resumed or Snapshot(Film(self.width, self.height), 0)
        done = self.snapshot.passes_done
        if done and (done > len(self.passes)
                     or int(self.snapshot.film.count.max()) != self.passes[done - 1][1]):
            raise ValueError(f"the checkpoint holds {int(self.snapshot.film.count.max())} spp "
                             f"in {done} passes, which are not the first passes of "
                             f"--spp {self.rules.spp}")
        self._started = None  # the first next_pass starts the clock
        self._pass_started = None
        self._granted = None  # the pass next_pass gave, until its film is merged
        self._next_traced = 0.0  # seconds the next pass's rays were traced ahead of it

    @property
    def film(self) -> Film:
        return self.snapshot.film

    @property
    def series(self) -> list[dict]:
        return list(self.snapshot.series)

    def elapsed(self) -> float:
        """Render seconds so far (from the first ``next_pass``), those of the runs this one
        resumed included."""
        before = self.resumed.seconds if self.resumed is not None else 0.0
        if self._started is None:
            return before
        return before + time.perf_counter() - self._started

    def start(self) -> None:
        """Start the clock (the first ``next_pass`` does, if nothing did before)."""
        if self._started is None:
            self._started = self._pass_started = time.perf_counter()

    def remaining(self) -> list[tuple[int, int]]:
        """The passes not rendered yet (none once a rule stopped the render)."""
        return [] if self.stopped_by is not None else self.passes[self.snapshot.passes_done:]

    def next_pass(self) -> tuple[int, int, int] | None:
        """The next pass to render as (index, first sample, stop sample), or None once a
        rule says stop (``stopped_by`` names it). The rules rule once per pass: asked again
        before that pass's film is merged, it gives the same pass (``retake`` asks anew)."""
        done = self.snapshot.passes_done
        self.start()
        if self.stopped_by is not None:
            return None
        if self._granted is not None:
            return self._granted
        if done == len(self.passes):
            return self._stop("spp")
        last = self.snapshot.series[-1] if self.snapshot.series else None
        if self.rules.target_error is not None and last is not None:
            error = last.get("stop_bound")
            if error is not None and error <= self.rules.target_error:
                self.stopped_at = error
                return self._stop("target-error")
        if self.rules.time_limit is not None and last is not None:
            first, stop = self.passes[done]
            per_sample = pass_work(last) / max(last["pass_spp"], 1)
            # what was traced of the pass ahead of its turn is done (``passes_in_time``)
            predicted = max(per_sample * (stop - first) - self._next_traced, 0.0)
            if self.elapsed() + predicted > self.rules.time_limit:
                return self._stop("time-limit")
        self._pass_started = time.perf_counter()
        self._granted = (done, *self.passes[done])
        return self._granted

    def pass_clock(self) -> tuple[float | None, float | None]:
        """What the time rule knows of the pass granted now: (seconds left of the limit when
        it was granted, or None without a limit; the last pass's seconds a sample, or None
        before any): the arguments ``passes_in_time`` predicts with, which a coordinator
        sends its nodes with each grant."""
        if self.rules.time_limit is None:
            return None, None
        last = self.snapshot.series[-1] if self.snapshot.series else None
        per_sample = (None if last is None or not last.get("pass_seconds") else
                      pass_work(last) / max(last["pass_spp"], 1))
        started = self._pass_started or time.perf_counter()
        budget = self.rules.time_limit - (self.elapsed() - (time.perf_counter() - started))
        return budget, per_sample

    def may_grant(self, index: int, ahead_seconds: float = 0.0,
                  traced_ahead: list[float] = ()) -> bool:
        """Whether the rules may still grant pass ``index`` (after the current one), by the
        time rule's own prediction (``passes_in_time``; always, without a time limit): what
        a runtime asks before it traces that pass ahead of its turn. ``ahead_seconds``: of
        the current pass's time so far, the seconds spent tracing later passes;
        ``traced_ahead``: the seconds the current pass's and each later one's rays were
        traced before they led."""
        done = self.snapshot.passes_done
        if self.stopped_by is not None or index >= len(self.passes):
            return False
        if index <= done or self.rules.time_limit is None:
            return True
        budget, per_sample = self.pass_clock()
        running = time.perf_counter() - (self._pass_started or time.perf_counter())
        spp = [stop - first for first, stop in self.passes[done:index + 1]]
        return (passes_in_time(budget, running, per_sample, spp, ahead_seconds, traced_ahead)
                >= index - done)

    def retake(self) -> None:
        """Before a runtime (re)starts mid-way: after a node loss, the pass granted and lost
        with it unmerged, or a checkpoint's passes done. The rules rule on the next pass
        anew (time went by meanwhile): it is granted, or ``stopped_by`` says which rule
        stopped, and the image is that of the passes done. A progression with no pass done
        or granted is left as it is (its first ``next_pass`` starts the clock)."""
        if self.stopped_by is None and (self._granted or self.snapshot.passes_done):
            self._granted = None
            self._next_traced = 0.0  # what was traced ahead went with the runtime
            self.next_pass()

    def _stop(self, reason: str) -> None:
        self.stopped_by = reason
        return None

    def add_pass(self, index: int, pass_film: Film, ahead_seconds: float = 0.0,
                 traced_ahead: list[float] = ()) -> dict:
        """Merge the film of pass ``index`` (the next one) into the image; returns its
        ``pass_point`` (with the pass's seconds and samples, for the time rule).

        Where the runtime traced passes ahead of their turn (``SortFirstTiles.render_ahead``)
        the time rule predicts each pass as if swept alone (``pass_work``) less what was
        traced of it ahead: ``ahead_seconds`` are the pass's seconds spent tracing later
        passes, and ``traced_ahead`` the seconds this pass's rays ([0]) and each later
        one's ([1], ...) were traced before they led, so far."""
        done = self.snapshot.passes_done
        if index != done:
            raise ValueError(f"pass {index} arrived where pass {done} was due")
        self._granted = None
        film = Film(self.width, self.height)
        film.merge(self.snapshot.film)
        film.merge(pass_film)
        seconds = self.elapsed()
        point = pass_point(film, index, seconds, self.reference)
        first, stop = self.passes[index]
        point["pass_spp"] = stop - first
        point["stop_bound"] = (point["rel_mse"] if self.reference is not None
                               else stop_bound(point, len(self.passes)))
        point["pass_seconds"] = round(time.perf_counter() - (self._pass_started or 0.0), 4)
        point["ahead_seconds"] = round(max(float(ahead_seconds), 0.0), 4)
        traced = [max(float(t), 0.0) for t in traced_ahead]
        point["rode_seconds"] = round(traced[0], 4) if traced else 0.0
        self._next_traced = traced[1] if len(traced) > 1 else 0.0
        self.snapshot = Snapshot(film, done + 1, self.snapshot.series + (point,), seconds)
        if self.on_pass is not None:
            self.on_pass(self)
        return point

    def interrupted(self) -> None:
        """Mark the render as stopped by the user (Ctrl-C)."""
        self.stopped_by = "interrupted"

    def report(self) -> dict:
        """What the report gets: ``stopped_by`` and the ``passes`` series."""
        return {"stopped_by": self.stopped_by, "max_pass_spp": self.rules.max_pass_spp,
                "time_limit_s": self.rules.time_limit, "target_error": self.rules.target_error,
                "target_error_against": (None if self.rules.target_error is None else
                                         "reference" if self.reference is not None
                                         else "estimate"),
                "stop_rule": self.stop_rule(), "stop_bound": self.stopped_at,
                "rel_mse_epsilon": REL_MSE_EPSILON, "passes": self.series}

    def stop_rule(self) -> str | None:
        """The target-error rule in words (None without a target)."""
        if self.rules.target_error is None:
            return None
        if self.reference is not None:
            return "rel_mse against the reference <= target_error"
        return (f"upper {100 * (1 - STOP_ALPHA):g} % bound of the estimated relMSE "
                f"(estimated_rel_mse + z(1 - {STOP_ALPHA:g}/{len(self.passes)}) x "
                f"estimated_rel_mse_se: Bonferroni over the {len(self.passes)} passes) "
                f"<= target_error")
