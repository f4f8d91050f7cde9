"""Finding each other under the engines clusters already run (Slurm, MPI launchers).

A node started by ``srun`` or ``mpirun`` takes its rank from the launcher's environment, and
finds the coordinator either from ``--coordinator ADDR`` or from a *rendezvous file* on a
shared file system: the coordinator, once listening, writes its address there; the nodes
wait for the file to appear.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from vastray.scene.errors import InputError

#: Rank variables of the launchers, in the order they are trusted: Slurm, PMI (MPICH, Intel
#: MPI, Slurm's PMI), PMIx, Open MPI.
RANK_VARIABLES = ("SLURM_PROCID", "PMI_RANK", "PMIX_RANK", "OMPI_COMM_WORLD_RANK")
SIZE_VARIABLES = ("SLURM_NTASKS", "PMI_SIZE", "PMIX_SIZE", "OMPI_COMM_WORLD_SIZE")


def _first_int(names: tuple[str, ...]) -> int | None:
    for name in names:
        value = os.environ.get(name, "").strip()
        if value.isdigit():
            return int(value)
    return None


def launcher_rank() -> int | None:
    """This process's rank as the launcher (Slurm, PMI, PMIx, Open MPI) numbered it."""
    return _first_int(RANK_VARIABLES)


def launcher_size() -> int | None:
    """How many processes the launcher started."""
    return _first_int(SIZE_VARIABLES)


def write_address(path: str | os.PathLike, address: str) -> None:
    """Publish the coordinator's address: written beside, then renamed, so a node never reads
    half a file."""
    path = Path(path)  # its folder was checked before the render (never created here)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(address + "\n")
    os.replace(tmp, path)


def read_address(path: str | os.PathLike, timeout: float) -> str:
    """Wait up to ``timeout`` seconds for the rendezvous file and return the address in it.

    Raises
    ------
    InputError
        When no file appears in time, or it holds no ``tcp://HOST:PORT`` address.
    """
    path = Path(path)
    deadline = time.monotonic() + timeout
    while not path.is_file():
        if time.monotonic() > deadline:
            raise InputError(path, f"no coordinator address appeared within {timeout:.0f} s "
                                   "(start the coordinator with --rendezvous on the same path)")
        time.sleep(0.1)
    try:
        address = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot be read as a coordinator's address ({exc})") from None
    if not address.startswith("tcp://") or ":" not in address[6:]:
        raise InputError(path, f"holds {address[:80]!r}, not a tcp://HOST:PORT address")
    return address


#: Seconds a node retries resolving the coordinator's host name before it gives up: a name
#: service (a compose cluster's) may register the coordinator's container a moment late.
RESOLVE_WAIT_S = 10.0


def coordinator_address(address: str, wait: float = 0.0) -> str:
    """``tcp://HOST:PORT`` from what a user gave (``HOST:PORT`` too), checked before any
    socket is made: a bad form or a host name that does not resolve is named, where ZeroMQ
    would say "Invalid argument" or the node would wait out its timeout. A name that does not
    resolve is tried again for ``wait`` seconds.

    Raises
    ------
    InputError
        When ``address`` is not ``[tcp://]HOST:PORT`` or HOST does not resolve.
    """
    import socket

    full = address if "://" in address else f"tcp://{address}"
    host, _, port = full.removeprefix("tcp://").rpartition(":")
    host = host.strip("[]")  # an IPv6 literal, [::1]
    if not full.startswith("tcp://") or not host or not port.isdigit() \
            or not 0 < int(port) < 65536:
        raise InputError(None, f"--coordinator {address!r} is not tcp://HOST:PORT "
                               "(the address the coordinator prints)")
    deadline = time.monotonic() + wait
    while True:
        try:
            socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
            return full
        except (socket.gaierror, UnicodeError) as exc:
            if time.monotonic() >= deadline:
                waited = f" after {wait:.0f} s" if wait > 0 else ""
                raise InputError(None, f"--coordinator {address!r}: host {host!r} not found "
                                       f"({exc.args[-1]}){waited}: check the name, and that "
                                       "the coordinator is running (in a compose cluster a "
                                       "coordinator that has exited, for example refusing its "
                                       "options, has no host name left: see its output)"
                                 ) from None
            time.sleep(0.5)
