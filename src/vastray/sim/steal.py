"""What else wants this machine's cores while a real run runs: the host's "steal" and other
processes.

On a virtual machine the host may run other guests on the cores ours wants: Linux counts that
time as ``steal`` in ``/proc/stat``. On the 2-core machine this project is measured on it goes
from nothing to a third of the time within minutes (2026-11-30: 0 % idle in one minute, 31 % of
the wanted CPU time in a 10-second window while a validation ran), and a real run under it is
slower by that share while the CPU seconds the simulator charges (a thread's own, which do not
count steal) are not: a validation that charges no steal under-predicts such a run, one taken in
a quiet minute over-predicts the next. ``StealMeter`` measures the share over a span, so a
validation can charge the cores the real run actually had (``CostModel.stolen``).

Other processes on this machine take cores too: a run beside one busy process (a CPU hog,
another test) got about two thirds of the 2 cores, and a validation that charged it both
under-predicted it by 23-32 %. From session 30 their CPU share over the run was charged like
the steal, as cores the run did not have; but that over-charges a run that leaves cores idle
part of the time (a node waiting on its peers): the other process took a core the run did not
want. Beside one busy process the validation's 2-node rows were then over-predicted by up to
28 % (2026-12-04). So other processes are counted as what they are, processes that want a
core (``others_running``), and the simulator runs that many busy processes beside the nodes
(``CostModel.beside``), sharing the cores as the operating system does. ``Contention``
measures both around a real run.
"""

from __future__ import annotations

import time
from pathlib import Path

#: /proc/stat's first line: "cpu  user nice system idle iowait irq softirq steal guest
#: guest_nice" (USER_HZ ticks summed over the cores).
PROC_STAT = Path("/proc/stat")
_BUSY_FIELDS = (0, 1, 2, 5, 6)  # user, nice, system, irq, softirq
_STEAL_FIELD = 7


def cpu_ticks(stat: Path = PROC_STAT) -> tuple[int, int] | None:
    """(busy, stolen) ticks so far, summed over the cores; None where the file is missing
    or unreadable (not Linux)."""
    try:
        first = stat.read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    if not first or first[0] != "cpu" or len(first) <= _STEAL_FIELD + 1:
        return None
    values = [int(v) for v in first[1:]]
    return sum(values[i] for i in _BUSY_FIELDS), values[_STEAL_FIELD]


def stolen_share(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float:
    """The share of the CPU time wanted between two ``cpu_ticks`` readings that the host gave
    to other machines: stolen / (busy + stolen), in [0, 1); 0 where either reading is missing
    or nothing ran."""
    if before is None or after is None:
        return 0.0
    busy, stolen = after[0] - before[0], after[1] - before[1]
    if busy + stolen <= 0 or stolen <= 0:
        return 0.0
    return min(stolen / (busy + stolen), 0.99)


#: How long ``others_running`` watches the machine, and how often it looks
OTHERS_WINDOW_S = 0.25
OTHERS_EVERY_S = 0.01


def running_now(stat: Path = PROC_STAT) -> int | None:
    """The machine's runnable tasks now (``procs_running`` in ``/proc/stat``; the caller
    counts as one); None where the file or the line is missing."""
    try:
        for line in stat.read_text().splitlines():
            if line.startswith("procs_running"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def others_running(seconds: float = OTHERS_WINDOW_S, stat: Path = PROC_STAT) -> float:
    """How many processes of others want a core, on average over ``seconds`` while this one
    waits: the machine's runnable tasks less this one, looked at every ``OTHERS_EVERY_S``
    (a spinner beside it: 1; three spinners on 2 cores: 3, where the cores they keep busy
    would say 2; a quiet machine: about 0). 0 where ``/proc/stat`` says nothing."""
    counts = []
    deadline = time.monotonic() + seconds
    while True:
        now = running_now(stat)
        if now is None:
            return 0.0
        counts.append(max(now - 1, 0))
        if time.monotonic() >= deadline:
            return sum(counts) / len(counts)
        time.sleep(OTHERS_EVERY_S)


class StealMeter:
    """The share of the CPU time wanted over a span that the host gave to other machines:
    ``with StealMeter() as meter: ...``, then ``meter.share`` (0 where ``/proc/stat`` is
    missing)."""

    def __init__(self, stat: Path = PROC_STAT):
        self.stat = stat
        self.share = 0.0
        self._before: tuple[int, int] | None = None

    def __enter__(self) -> StealMeter:
        self._before = cpu_ticks(self.stat)
        return self

    def __exit__(self, *exc) -> None:
        self.share = stolen_share(self._before, cpu_ticks(self.stat))


class Contention:
    """What else wanted this machine's cores around a span: ``with Contention() as seen:
    ...``, then ``seen.share`` (the host's steal during it, ``StealMeter.share``),
    ``seen.others`` (other processes wanting a core, ``others_running`` before and after
    it, averaged: during it the span's own processes would count) and ``seen.charged(costs)``
    (the costs a simulation of the span is charged)."""

    def __init__(self, stat: Path = PROC_STAT):
        self.stat = stat
        self._meter = StealMeter(stat)
        self._before = 0.0
        self.share = 0.0
        self.others = 0.0

    def __enter__(self) -> Contention:
        self._before = others_running(stat=self.stat)
        self._meter.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._meter.__exit__(*exc)
        self.share = self._meter.share
        self.others = (self._before + others_running(stat=self.stat)) / 2

    def charged(self, costs):
        """``costs`` (a ``CostModel``) with the steal as cores the span did not have and the
        others as busy processes beside its own (``CostModel.stolen``, ``beside``)."""
        return costs.stolen(self.share).beside(self.others)
