"""Local nodes bound to their own CPUs.

``vastray render --nodes N`` starts N node processes on this machine, each running
``available_cpus() // N`` threads. Left to the operating system, two nodes that wake each
other every round (an all-reduction, a ray swap) are often placed on one core: Linux runs a
woken task on its waker's core (wake-affine placement) and moves it only later, so both run
at half speed while the other core idles (session 54 found both nodes of a 2-node `dynamic`
render on one core in 70-83 % of the samples where both were runnable). Bound, each node
keeps a share of the CPUs of its own: on this 2-core machine, 2 nodes of rm 128³ in 128
domains rendered `dynamic` in 1.10 s against 1.24 s unbound (means of 8 interleaved runs),
`spec-ooc` 0.70 against 0.75 s and `image` 0.74 against 0.82 s, the spread between runs
about halved; the turbine-blade scan's `dynamic`, whose rounds are few and short, 0.296 against
0.281 s (session 75, ``bench/README.md``).

Where the nodes outnumber the CPUs they must share cores, and binding would only keep the
operating system from balancing them: they run unbound, as a lone node does.
``VASTRAY_BIND_NODES=0`` leaves every node unbound.
"""

from __future__ import annotations

import os

from vastray.scene.cpus import available_cpus

#: ``VASTRAY_BIND_NODES=0`` leaves local nodes unbound.
BIND_ENV = "VASTRAY_BIND_NODES"


def node_cpu_blocks(nodes: int, mask: list[int] | None = None, cpus: int | None = None,
                    threads: int | None = None) -> list[list[int]] | None:
    """The CPUs each of ``nodes`` local nodes is bound to, or None where they run unbound.

    Parameters
    ----------
    nodes : the node processes started on this machine.
    mask : the CPUs this process may use, ascending (default: its affinity mask).
    cpus : the CPUs worth a thread (default: ``available_cpus()``, the mask lowered to the
        cgroup quota).
    threads : the threads each node runs where the render sets them (``--threads``; None:
        ``cpus // nodes``, the default).

    Returns
    -------
    ``nodes`` disjoint blocks of ``cpus // nodes`` CPUs of ``mask`` each, in order (node i
    the i-th), as each node runs ``cpus // nodes`` threads; None for one node, for more
    nodes than ``cpus``, for more threads a node than its block (the render asked for more
    threads than the CPUs: the operating system shares them out), off Linux, or with
    ``VASTRAY_BIND_NODES=0``.
    """
    if os.environ.get(BIND_ENV, "1").strip() == "0" or nodes < 2:
        return None
    if mask is None:
        try:
            mask = sorted(os.sched_getaffinity(0))
        except (AttributeError, OSError):  # not on Linux: no affinity to set
            return None
    share = min(available_cpus() if cpus is None else cpus, len(mask)) // nodes
    if share < 1 or (threads or 0) > share:
        return None
    return [list(mask[i * share:(i + 1) * share]) for i in range(nodes)]


def parse_cpus(text: str) -> list[int]:
    """``--cpus``: a comma-separated list of CPU numbers and ranges (``0-3,8``), ascending.

    Raises
    ------
    ValueError
        A part that is not a CPU number or a range of them, or an empty list.
    """
    cpus: set[int] = set()
    for part in text.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            low, high = int(first), int(last if dash else first)
        except ValueError:
            raise ValueError(f"CPU numbers and ranges such as 0-3,8 expected, got "
                             f"{part.strip()!r}") from None
        if low < 0 or high < low:
            raise ValueError(f"{part.strip()!r} is not a range of CPU numbers")
        cpus.update(range(low, high + 1))
    if not cpus:
        raise ValueError("no CPU given")
    return sorted(cpus)


def bind_process(cpus: list[int]) -> list[int]:
    """Bind every thread of this process (and the threads it starts later, which inherit
    it) to ``cpus``; the affinity mask it then has.

    Raises
    ------
    OSError
        None of ``cpus`` is a CPU this process may use (the kernel refuses the mask).
    """
    threads = [int(t) for t in os.listdir("/proc/self/task")] if os.path.isdir(
        "/proc/self/task") else [0]
    for thread in threads:
        try:
            os.sched_setaffinity(thread, cpus)
        except ProcessLookupError:  # the thread ended meanwhile
            pass
    return sorted(os.sched_getaffinity(0))
