"""Telling a slow process from a lost one on a starved machine.

On a machine kept busy by other jobs (a load average of 8 on 2 cores), an event loop can be
held up for seconds: heartbeats are late although their sender is alive and working. Silence
alone is no verdict when the silent process runs here: a process that keeps using CPU is slow,
one that uses none is stopped or hung. ``CpuWitness`` judges that from ``/proc``.
"""

from __future__ import annotations

from pathlib import Path

#: A node that is not waiting for others and, by the CPU time its heartbeats give, uses less
#: than this share of one core is not working: its render thread hangs while its event loop
#: still beats (a heartbeat costs about a millisecond a second).
HUNG_CPU_SHARE = 0.05

#: A silent process on this machine that still uses CPU is given this many silence limits
#: before it counts as lost (a node judging its coordinator, the coordinator its nodes).
BUSY_GRACE = 10


def cpu_ticks(pid: int) -> int | None:
    """CPU time (user + system, in clock ticks) process ``pid`` has used; None where /proc
    cannot tell (not Linux, or the process is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15)
    except (OSError, IndexError, ValueError):
        return None


class CpuWitness:
    """Whether a silent process on this machine is still working.

    CPU time is compared over windows of ``window`` seconds: a window still open is no verdict
    yet (busy), a closed one in which the process used no CPU time means it stopped.

    Parameters
    ----------
    window : seconds per comparison window.
    """

    def __init__(self, window: float):
        self.window = window
        self._seen: dict[int, tuple[float, int]] = {}

    def forget(self, pid: int) -> None:
        """Start afresh for ``pid`` (it was heard from)."""
        self._seen.pop(pid, None)

    def busy(self, pid: int, now: float) -> bool:
        """True while process ``pid`` keeps using CPU (False: gone, or idle for a window)."""
        ticks = cpu_ticks(pid)
        if ticks is None:
            return False
        since, before = self._seen.setdefault(pid, (now, ticks))
        if now - since < self.window:
            return True
        self._seen[pid] = (now, ticks)
        return ticks > before
