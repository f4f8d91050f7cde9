"""Errors raised for bad input: each names the offending file and the problem."""

from __future__ import annotations

import os


class VastrayError(Exception):
    """Every refusal and failure vastray reports to its user: the CLI prints the message on
    one line, and the Python API (``vastray.render``) raises it. Catch this one type."""


class InputError(VastrayError, ValueError):
    """Bad user input: a missing, malformed or unsupported file or setting.

    The message always reads ``"<path>: <problem>"`` so the CLI can print it on one line.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(problem if self.path is None else f"{self.path}: {problem}")
