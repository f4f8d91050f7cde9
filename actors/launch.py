"""``vastray launch``: run a render on SSH hosts against a STORE path they all share.

HOSTFILE, one node per line (``#`` starts a comment)::

    gpu01                                   # uses `python3` on gpu01
    gpu02 python=/opt/venvs/vastray/bin/python
    gpu03 python=/usr/bin/python3.11 slots=2   # two nodes on gpu03

Each node is started as ``ssh HOST PYTHON -m vastray.cli node --coordinator tcp://ME:PORT
--bind 0.0.0.0 --keys BUNDLE --key-name HOST``: BUNDLE is the host's own bundle (``vastray
keys -o KEYS --node HOST`` writes it to KEYS/bundles/HOST), at ``--node-keys`` on every host
where each was given its own, else at KEYS/bundles/HOST on a shared file system (where every
host can read every bundle). Its output is collected in ``--logs``. The STORE must be at the
same path on every host. When the render ends, fails or is interrupted (Ctrl-C), every ssh
session is closed.
"""

from __future__ import annotations

import shlex
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

from vastray.scene.errors import InputError


@dataclass(frozen=True)
class Host:
    name: str
    python: str = "python3"
    slots: int = 1


def read_hostfile(path: str | Path) -> list[Host]:
    """Hosts of a HOSTFILE, one entry per node slot."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "host file not found")
    hosts = []
    for number, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].split()
        if not line:
            continue
        options = {}
        for item in line[1:]:
            key, sep, value = item.partition("=")
            if not sep or key not in ("python", "slots"):
                raise InputError(path, f"line {number}: unknown option {item!r} "
                                       "(expected python=PATH or slots=N)")
            options[key] = value
        try:
            slots = int(options.get("slots", 1))
        except ValueError:
            raise InputError(path, f"line {number}: slots must be a number") from None
        if slots < 1:
            raise InputError(path, f"line {number}: slots must be at least 1")
        hosts += [Host(line[0], options.get("python", "python3"), slots)] * slots
    if not hosts:
        raise InputError(path, "no hosts listed")
    return hosts


#: How ``vastray launch`` runs a command on a host: no password prompt, and a host that does not
#: answer is given up after 15 s (an unreachable one once held the launch for 122 s).
DEFAULT_SSH = "ssh -o BatchMode=yes -o ConnectTimeout=15 -tt"


def start_nodes(hosts: list[Host], coordinator: str, bundles: dict[str, str], logs: Path,
                ssh: str = DEFAULT_SSH, timeout: float = 120.0
                ) -> dict[str, tuple[subprocess.Popen, Path]]:
    """Start one node per host entry over ssh, with ``bundles[HOST]``, the path of that host's
    key bundle on it; returns name -> (process, log file)."""
    logs.mkdir(parents=True, exist_ok=True)
    started = {}
    for i, host in enumerate(hosts):
        remote = shlex.join([host.python, "-m", "vastray.cli", "node", "--coordinator",
                             coordinator, "--bind", "0.0.0.0", "--keys", bundles[host.name],
                             "--key-name", host_key_name(host.name), "--timeout", str(timeout)])
        log = logs / f"node{i}-{host.name}.log"
        with open(log, "wb") as out:
            proc = subprocess.Popen([*shlex.split(ssh), host.name, remote], stdout=out,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        started[f"{host.name} (node {i})"] = (proc, log)
    return started


def host_key_name(host: str) -> str:
    """The node key a HOSTFILE host uses: its name, user@ and :port left out."""
    return host.rpartition("@")[2].split(":")[0]


def stop_nodes(started: dict[str, tuple[subprocess.Popen, Path]]) -> None:
    """Close every ssh session (the remote node gets a hang-up) and reap them."""
    for proc, _ in started.values():
        if proc.poll() is None:
            proc.terminate()
    for proc, _ in started.values():
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def this_host() -> str:
    """An address the hosts can reach this coordinator at (best guess; see --advertise)."""
    return socket.getfqdn()
