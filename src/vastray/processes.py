"""Whether a process still runs: what files and folders named after their owner's pid (stale
temporary images, node logs, join secrets) are judged by."""

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
