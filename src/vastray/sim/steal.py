"""The share of this machine's CPU time its hypervisor gave to other machines ("steal").

On a virtual machine the host may run other guests on the cores ours wants: Linux counts that
time as ``steal`` in ``/proc/stat``. On the 2-core machine this project is measured on it goes
from nothing to a third of the time within minutes (2026-11-30: 0 % idle in one minute, 31 % of
the wanted CPU time in a 10-second window while a validation ran), and a real run under it is
slower by that share while the CPU seconds the simulator charges (a thread's own, which do not
count steal) are not: a validation that charges no steal under-predicts such a run, one taken in
a quiet minute over-predicts the next. ``StealMeter`` measures the share over a span, so a
validation can charge the cores the real run actually had (``CostModel.stolen``).
"""

from __future__ import annotations

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


class StealMeter:
    """The stolen share over a span: ``with StealMeter() as meter: ...``, then
    ``meter.share`` (0 where ``/proc/stat`` is missing)."""

    def __init__(self, stat: Path = PROC_STAT):
        self.stat = stat
        self.share = 0.0
        self._before: tuple[int, int] | None = None

    def __enter__(self) -> StealMeter:
        self._before = cpu_ticks(self.stat)
        return self

    def __exit__(self, *exc) -> None:
        self.share = stolen_share(self._before, cpu_ticks(self.stat))
