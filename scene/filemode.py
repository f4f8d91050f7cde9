"""File modes that respect the user's umask.

``tempfile.mkstemp`` and ``mkdtemp`` create files 0600 and folders 0700 whatever the umask, so
outputs written through a temporary name and renamed into place would be private to their
owner. Every file and folder vastray publishes gets the mode a plain ``open`` or ``mkdir``
would have given it.
"""

from __future__ import annotations

import os


def _read_umask() -> int:
    mask = os.umask(0o022)  # the only portable way to read it is to set it and put it back
    os.umask(mask)
    return mask


#: The process's umask, read once at import (reading it briefly changes it, which is not safe
#: once worker threads are creating files).
UMASK = _read_umask()


def publish_mode(path: str | os.PathLike, directory: bool = False) -> None:
    """Give ``path`` the mode ``open``/``mkdir`` would have: 0666 or 0777 less the umask."""
    os.chmod(path, (0o777 if directory else 0o666) & ~UMASK)
