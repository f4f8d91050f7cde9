"""The join secret of a render without keys: who may join is whoever holds it.

The coordinator hands it to the nodes it starts through an inherited pipe (never argv or the
environment), and for nodes of the same user on the same machine (``--listen`` on loopback)
writes it to a file only that user can read, named by the port it listens on.
"""

from __future__ import annotations

import os
import re
import secrets
import socket
import stat
import time
from pathlib import Path

from vastray.processes import running
from vastray.scene.errors import InputError


def new_secret() -> bytes:
    """A fresh join secret (hex text: it travels in PLAIN's password field)."""
    return secrets.token_hex(16).encode()


def runtime_dir() -> Path:
    """Where a coordinator without keys leaves its join secret: ``$VASTRAY_RUNTIME_DIR``, else
    ``~/.vastray/run`` (created owner-only)."""
    return Path(os.environ.get("VASTRAY_RUNTIME_DIR") or Path.home() / ".vastray" / "run")


def join_secret_path(port: int) -> Path:
    return runtime_dir() / f"{socket.gethostname()}-{int(port)}.join"


def _private_dir() -> Path:
    """``runtime_dir()``, made owner-only; refused if another user could read or replace it."""
    folder = runtime_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        info = folder.stat()
    except OSError as exc:
        raise InputError(folder, f"cannot keep the join secret here ({exc.strerror}); set "
                                 "VASTRAY_RUNTIME_DIR to a folder only you can read") from None
    if info.st_uid != os.getuid() or stat.S_IMODE(info.st_mode) & 0o077:
        raise InputError(folder, "must be a folder only you can read (owner "
                                 f"{info.st_uid}, mode {stat.S_IMODE(info.st_mode):o}); fix it "
                                 "with chmod 700 or set VASTRAY_RUNTIME_DIR")
    return folder


def write_join_secret(port: int, secret: bytes) -> Path:
    """Leave ``secret`` for nodes of this user on this machine (mode 0600, beside any left by
    coordinators that are gone, which are removed)."""
    folder = _private_dir()
    for old in folder.glob("*.join"):
        if not _holder_alive(old):
            old.unlink(missing_ok=True)
    path = join_secret_path(port)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"{os.getpid()} {secret.decode()}\n")
    os.replace(tmp, path)
    return path


def _holder_alive(path: Path) -> bool:
    try:
        return running(int(path.read_text().split()[0]))
    except (OSError, ValueError, IndexError):
        return False


def read_join_secret(port: int, timeout: float) -> bytes:
    """The join secret of this user's coordinator listening on ``port`` on this machine,
    waiting up to ``timeout`` seconds for it to start.

    Raises
    ------
    InputError
        When none appears: no coordinator of this user listens there (without keys, only the
        coordinator's own user on its own machine may join).
    """
    deadline = time.monotonic() + timeout
    while (secret := _current_secret(port)) is None:
        _check_deadline(port, deadline, timeout)
        time.sleep(0.1)
    return secret


async def wait_for_join_secret(port: int, timeout: float) -> bytes:
    """``read_join_secret`` for a node's event loop: it waits there, not on a thread, so a
    Ctrl-C or SIGTERM ends the wait at once (a thread blocked the loop's shutdown until the
    timeout: a node waiting for its coordinator ignored both for minutes)."""
    import asyncio

    deadline = time.monotonic() + timeout
    while (secret := _current_secret(port)) is None:
        _check_deadline(port, deadline, timeout)
        await asyncio.sleep(0.1)
    return secret


def _current_secret(port: int) -> bytes | None:
    """The secret in ``port``'s file if a running process of this user left it, else None."""
    path = join_secret_path(port)
    try:
        pid, secret = path.read_text().split()
        if running(int(pid)) and path.stat().st_uid == os.getuid():
            return secret.encode()
    except (OSError, ValueError):
        pass
    return None


def _check_deadline(port: int, deadline: float, timeout: float) -> None:
    if time.monotonic() > deadline:
        raise InputError(join_secret_path(port),
                         f"no join secret of a running coordinator appeared within "
                         f"{timeout:.0f} s: without --keys, a node joins only a coordinator of "
                         "its own user on its own machine (give both --keys to join from "
                         "elsewhere)")


def read_secret_fd(fd: int) -> bytes:
    """The join secret a coordinator wrote into the pipe it handed this node (then closed)."""
    with os.fdopen(fd, "rb") as pipe:
        secret = pipe.read(256).strip()
    if not re.fullmatch(rb"[0-9a-f]{32}", secret):
        raise InputError(None, f"--secret-fd {fd} gave no join secret")
    return secret
