"""Where the nodes a coordinator starts on its own machine write their logs.

A node's log holds its own words: why it failed, and the messages and connections it refused.
Kept in a folder the user names (``--log-dir``, or beside ``--report``); otherwise in a
temporary folder removed when the render ends. A coordinator killed outright (SIGKILL) cannot
remove its temporary folder: the next coordinator of the same user removes those whose
coordinator is gone (their names carry its pid).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from vastray.processes import running

PREFIX = "vastray-nodes-"


class NodeLogs:
    """The log files of one render's local nodes, by rank and attempt.

    Parameters
    ----------
    keep : a folder to keep the logs in (made if missing); None: a temporary one.
    """

    def __init__(self, keep: str | os.PathLike | None = None):
        self.kept = keep is not None
        if keep is not None:
            self.folder = Path(keep)
            self.folder.mkdir(parents=True, exist_ok=True)
        else:
            sweep_stale()
            self.folder = Path(tempfile.mkdtemp(prefix=f"{PREFIX}{os.getpid()}-"))

    def path(self, rank: int, attempt: int = 0) -> Path:
        """Node ``rank``'s log of an attempt (attempts after a node loss start new nodes)."""
        return self.folder / (f"node{rank}.log" if attempt == 0
                              else f"node{rank}.attempt{attempt + 1}.log")

    def close(self) -> None:
        """Remove a temporary folder (a kept one stays)."""
        if not self.kept:
            shutil.rmtree(self.folder, ignore_errors=True)


def sweep_stale(root: str | os.PathLike | None = None) -> list[Path]:
    """Remove this user's temporary node-log folders whose coordinator is gone; returns them."""
    removed = []
    for folder in Path(root or tempfile.gettempdir()).glob(f"{PREFIX}*"):
        try:
            pid = int(folder.name[len(PREFIX):].split("-", 1)[0])
            if folder.stat().st_uid != os.getuid() or running(pid):
                continue
        except (ValueError, OSError):
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed
