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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
    address = path.read_text().strip()
    if not address.startswith("tcp://") or ":" not in address[6:]:
        raise InputError(path, f"holds {address[:80]!r}, not a tcp://HOST:PORT address")
    return address
