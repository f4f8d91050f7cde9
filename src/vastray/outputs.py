"""A render's output files, written so that a full disk or a folder that refuses them never
loses the render.

Each file goes to a temporary name beside its target (``imageio.atomic_path``) and the files
are renamed into place together, so a failure leaves no partial or half-set output. When a
file cannot be written (no space, no permission, a read-only or failing disk), every file is
written instead to a rescue folder (``vastray-rescued-*`` in the temp folder, else in the home
folder) and the error names the file, the reason and that folder, on one line.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

from vastray.render.imageio import atomic_path, os_error
from vastray.scene.errors import InputError

#: ``write(path)``: writes one output file at ``path``.
Writer = Callable[[str], None]

#: The errors of a place that cannot take a file (not of a wrong path): a checkpoint that
#: meets one goes to the rescue folder and the render goes on.
STORAGE_ERRNOS = frozenset(getattr(errno, name) for name in (
    "ENOSPC", "EDQUOT", "EFBIG", "EROFS", "EACCES", "EPERM", "EIO") if hasattr(errno, name))

_rescue_folders: dict[Path, Path] = {}  # one rescue folder per place, per process


class OutputError(InputError):
    """An output that could not be written.

    Attributes
    ----------
    path : the file that could not be written.
    reason : the ``OSError``.
    kept : the rescue folder that holds the outputs instead (None: none could).
    """

    def __init__(self, path: str | os.PathLike, reason: OSError, kept: Path | None,
                 names: list[str]):
        self.reason, self.kept = reason, kept
        why = reason.strerror or str(reason)
        if kept is None:
            where = "and no rescue folder (temp or home folder) could take them either"
        else:
            where = f"written to {kept} instead: {_listing(names)}"
        super().__init__(path, f"cannot be written ({why}); the outputs are {where}")


def rescue_folders() -> Iterator[Path]:
    """The folders a file that cannot be written goes to, best first: this process's
    ``vastray-rescued-*`` folder in the temp folder, then in the home folder (each made on
    first use; a place where none can be made is skipped)."""
    for base in (Path(tempfile.gettempdir()), Path.home()):
        try:
            if base not in _rescue_folders or not _rescue_folders[base].is_dir():
                _rescue_folders[base] = Path(tempfile.mkdtemp(prefix="vastray-rescued-",
                                                              dir=base))
        except OSError:
            continue
        yield _rescue_folders[base]


class StagedOutputs:
    """Output files staged beside their targets and renamed into place together when the
    ``with`` block ends without an error (removed when it ends with one): all or none.

    ``add`` writes a group of files (one image's -o, --png and --report); when one cannot be
    written, the group and the files staged before it go to a rescue folder and ``add``
    raises ``OutputError`` naming the file, the reason and the folder.
    """

    def __init__(self):
        self._stack = ExitStack()
        self.staged: dict[Path, str] = {}  # target -> its written temporary

    def __enter__(self) -> StagedOutputs:
        return self

    def __exit__(self, *exc_info) -> bool:
        return self._stack.__exit__(*exc_info)

    def add(self, files: dict[Path, Writer]) -> None:
        """Write ``files`` (target -> writer) to their temporaries.

        Raises
        ------
        OutputError
            A file could not be written; every output is in the rescue folder it names.
        """
        for target, write in files.items():
            target = Path(target)
            try:
                tmp = self._stack.enter_context(atomic_path(target))
                write(tmp)
            except OSError as exc:
                before = {t: tmp for t, tmp in self.staged.items() if t not in files}
                kept, names = rescue(files, before)
                raise OutputError(target, os_error(exc, target), kept, names) from None
            self.staged[target] = tmp


def rescue(files: dict[Path, Writer], staged: dict[Path, str] | None = None
           ) -> tuple[Path | None, list[str]]:
    """Write ``files`` (target -> writer), and copy the ``staged`` temporaries already written
    (target -> temporary), into the first rescue folder that takes them all.

    Returns
    -------
    The folder (None: none could) and the names written there.
    """
    staged = staged or {}
    for folder in rescue_folders():
        names = _names([*staged, *files])
        try:
            for tmp, name in zip(staged.values(), names, strict=False):
                with atomic_path(folder / name) as out:
                    shutil.copyfile(tmp, out)
            for write, name in zip(files.values(), names[len(staged):], strict=True):
                with atomic_path(folder / name) as out:
                    write(out)
        except OSError:
            continue
        return folder, names
    return None, []


def _names(targets: list[Path]) -> list[str]:
    """Each target's file name, numbered where two targets share one."""
    names: list[str] = []
    for target in targets:
        name = Path(target).name
        names.append(name if name not in names else f"{len(names)}-{name}")
    return names


def _listing(names: list[str]) -> str:
    """The rescued files, shortened for one line."""
    if len(names) <= 4:
        return ", ".join(names)
    return f"{len(names)} files, {names[0]} ... {names[-1]}"
