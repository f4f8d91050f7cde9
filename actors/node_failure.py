"""How a node is lost to a render: the errors the coordinator raises for a node that died,
stalled or failed, and the word or two that says how."""

from __future__ import annotations

import signal

from vastray.scene.errors import VastrayError


class NodeFailure(VastrayError, RuntimeError):
    """A node died or went silent; the message names it."""


class NodeLost(NodeFailure):
    """A node that had joined died or stalled mid-frame (a frame on the others can replace
    it, unlike a node that never joined or a protocol failure).

    ``rank`` is the lost node's, or None where only its launcher (an ssh session) is known;
    ``cause`` says how it was lost in a word or two: the signal that killed it (``"SIGSEGV"``,
    ``"SIGKILL"``), ``"exit code N"``, ``"stalled"`` or ``"failed"``.
    """

    def __init__(self, message: str, rank: int | None = None, cause: str = "lost"):
        super().__init__(message)
        self.rank = rank
        self.cause = cause


def exit_cause(code: int) -> str:
    """How a process with exit status ``code`` (``Popen.returncode``) ended, in a word or two:
    the signal's name for a negative code (killed by it), else ``"exit code N"``."""
    if code < 0:
        try:
            return signal.Signals(-code).name
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"
