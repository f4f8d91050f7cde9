"""Facts about processes: whether one still runs (what files and folders named after their
owner's pid, such as stale temporary images, node logs and join secrets, are judged by), and
this process's peak resident memory."""

from __future__ import annotations

import os


def running(pid: int) -> bool:
    """Whether process ``pid`` exists (ours or another user's)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def peak_rss_bytes() -> int:
    """This process's peak resident memory since it started its program.

    ``VmHWM``, the peak of its own address space: ``getrusage``'s ``ru_maxrss`` also keeps the
    peak of the process it was forked from (Linux carries it across ``exec``), so a node
    started by a 250 MB coordinator would report at least 250 MB. ``ru_maxrss`` where there
    is no ``/proc``.
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
