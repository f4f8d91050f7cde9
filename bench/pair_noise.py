"""How much of a validation's worst row is the machine's noise (``bench/simulate.py``).

Each validation point is judged by the median of its pairs' errors (a real run and the
simulation right after it), and ``sim_error_oos_max=`` is the worst point's. A pair's error
moves with this machine's moment: the same real render takes up to a fifth longer within a
minute, and the simulation, a few seconds later, does not follow it. So the worst of 14
points is partly the largest of 14 draws of that noise, whatever the simulator charges.

Two figures tell the two apart:

- ``pooled_sd``: the spread of a pair's error about its own point's mean, pooled over the
  points (each point's mean taken out, so a point's bias does not count as noise);
- ``chance_within``: the chance that a simulator with no bias at all would still print a worst
  point within the goal, given that noise and the pairs each point took (normal noise,
  Monte Carlo).

Sessions 73-74 (12 ``--quick`` runs, 178 pairs on the 14 out-of-sample points): a pair's
error spread 0.122 about its point's mean; at that noise an unbiased simulator would print
``sim_error_oos_max`` <= 0.20 in 75 % of runs with 2 pairs a point, 81 % with 3 and 96 %
with 4.
"""

from __future__ import annotations

import numpy as np

#: Monte Carlo draws of a whole validation (``chance_within``).
DRAWS = 20_000


def pooled_sd(errors_per_point: list[list[float]]) -> float | None:
    """The pooled standard deviation of a pair's error about its point's mean.

    Parameters
    ----------
    errors_per_point : each point's pair errors (simulated / real - 1), K lists.

    Returns
    -------
    sqrt(sum of squared deviations from each point's mean / (N - K)) over the N pairs of
    the K points; None where no point has two pairs (no spread to measure).
    """
    squares, freedom = 0.0, 0
    for errors in errors_per_point:
        errors = np.asarray(errors, float)
        if len(errors) > 1:
            squares += float(((errors - errors.mean()) ** 2).sum())
            freedom += len(errors) - 1
    return float(np.sqrt(squares / freedom)) if freedom else None


def chance_within(goal: float, sd: float, pairs: list[int], draws: int = DRAWS,
                  seed: int = 0) -> float:
    """The chance that the worst of the points' medians stays within ``goal`` when every
    pair's error is normal noise of ``sd`` about 0 (a simulator without bias).

    Parameters
    ----------
    goal : the bound on the worst |median| (``sim_error_oos_max=``'s goal, 0.20).
    sd : a pair's noise (``pooled_sd``).
    pairs : (K,) the pairs each point takes (its median is over them).
    draws : whole validations drawn.
    seed : the draws' seed (the figure is the same from run to run for the same inputs).

    Returns
    -------
    The share of the drawn validations whose worst point is within ``goal``.
    """
    if sd <= 0:
        return 1.0
    rng = np.random.default_rng(seed)
    worst = np.zeros(draws)
    for count in pairs:
        medians = np.median(rng.normal(0.0, sd, (draws, max(int(count), 1))), axis=1)
        worst = np.maximum(worst, np.abs(medians))
    return float(np.mean(worst <= goal))
