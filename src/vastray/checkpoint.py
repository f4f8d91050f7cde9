"""Checkpoints of a progressive render: the film after its last finished pass, written
atomically beside the image, and read back by ``vastray render --resume``.

A checkpoint is one ``.npz`` file (numpy's zip of arrays, read without pickle): the film's
arrays plus a JSON ``meta`` entry: format version, the passes done, the render seconds so far,
the error series, and ``identity``, everything that decides the image besides ``--spp`` (the
store's manifest digest, the scene, the resolved camera, the sampling settings, the pass
size). A resume must match it: then the passes it adds are those an uninterrupted run adds,
and, every sample being a pure function of (seed, pixel, sample), so is the image.

The zip's comment, its last bytes, is a seal: ``SEAL`` and the SHA-256 of every byte before
the digest. A truncated, emptied or bit-flipped file (any byte) fails the seal and is refused
in one line before anything is read from it. A checkpoint that cannot be written where asked
(a full or read-only disk) goes to the rescue folder (``vastray.outputs``) and the render goes
on; the temporary files of writes killed midway are removed when a render next uses the file.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import signal
import sys
import threading
import time
import zipfile
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np

from vastray.outputs import STORAGE_ERRNOS, OutputError, rescue_folders
from vastray.render.film import Film
from vastray.render.imageio import atomic_path, remove_orphans
from vastray.render.progressive import Progression, Snapshot
from vastray.scene.bvh_choice import resolve as resolve_bvh
from vastray.scene.errors import InputError
from vastray.scene.manifest import NPY_HEADERS

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = 4
#: Why a checkpoint of an older format cannot be resumed, by format.
_OLD_FORMATS = {3: "its film keeps the error estimate's batch sums in grey, format 4 per "
                   "colour channel",
                2: "its film keeps odd-sample sums, format 4 batch sums per colour channel"}
#: The zip comment's start; the hexadecimal SHA-256 of every byte before it follows.
SEAL = b"vastray checkpoint sha256 "
_DIGEST = 64  # hexadecimal characters
FILM_ARRAYS = ("sum", "batch", "count", "depth", "normal")

#: Settings that do not change the image: the spp bound (a resume may go further), the
#: pass window and the in-core batch size; and ``--bvh`` as given, since the BVH it resolves
#: to is what counts (the identity's ``bvh``: ``auto`` and the choice it makes are the same).
_FREE_SETTINGS = ("spp", "sample_start", "sample_stop", "batch_size", "bvh")


def default_path(output: str | Path) -> Path:
    """Where the checkpoints of a render writing ``output`` go: ``OUTPUT.checkpoint.npz``."""
    return Path(f"{output}.checkpoint.npz")


def render_identity(store, config, camera, settings, max_pass_spp: int) -> dict:
    """What a checkpoint must share with the render that resumes it (JSON-ready)."""
    manifest = Path(store.path) / "manifest.json"
    digest = hashlib.sha256(manifest.read_bytes()).hexdigest() if manifest.exists() else None
    scene = hashlib.sha256((config.text or "").encode()).hexdigest()
    cam = hashlib.sha256(repr(camera).encode()).hexdigest()
    return {"store_manifest_sha256": digest, "scene_sha256": scene, "camera_sha256": cam,
            "settings": {k: v for k, v in asdict(settings).items() if k not in _FREE_SETTINGS},
            "max_pass_spp": max_pass_spp, "bvh": resolve_bvh(settings.bvh, store.n_triangles)}


def write_checkpoint(path: str | Path, progression: Progression, identity: dict) -> Snapshot:
    """Write the progression's last finished pass to ``path`` atomically, sealed and synced
    to the disk; returns the snapshot written (taken once, so the arrays and meta agree)."""
    snap = progression.snapshot
    meta = {"format": CHECKPOINT_FORMAT, "identity": identity,
            "passes_done": snap.passes_done, "spp": int(snap.film.count.max()),
            "seconds": snap.seconds, "series": list(snap.series),
            "width": snap.film.width, "height": snap.film.height}
    arrays = {"meta": np.array(json.dumps(meta))}
    arrays.update((name, getattr(snap.film, name)) for name in FILM_ARRAYS)
    with atomic_path(path) as tmp, open(tmp, "w+b") as fh:
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
            for name, array in arrays.items():  # as np.savez writes them
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)
            archive.comment = SEAL + b"0" * _DIGEST
        fh.flush()
        digest = _digest(fh, fh.tell() - _DIGEST)
        fh.seek(-_DIGEST, os.SEEK_END)
        fh.write(digest)
        fh.flush()
        os.fsync(fh.fileno())  # a checkpoint outlives a crash of the machine too
    return snap


def _digest(fh, size: int) -> bytes:
    """The hexadecimal SHA-256 of the first ``size`` bytes of ``fh``."""
    fh.seek(0)
    sha = hashlib.sha256()
    while size > 0:
        chunk = fh.read(min(size, 1 << 22))
        if not chunk:
            break
        sha.update(chunk)
        size -= len(chunk)
    return sha.hexdigest().encode()


_NO_SEAL = ("has no intact checkpoint seal at its end: not a vastray checkpoint, or truncated "
            "(its write cut short, its copy incomplete) or damaged")


def _check_seal(path: Path) -> bool:
    """Whether the file at ``path`` ends in a seal (False: it has none, so it is no
    checkpoint of this format, or a truncated one).

    Raises
    ------
    InputError
        The file is missing, empty, unreadable, or sealed but damaged.
    """
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size == 0:
                raise InputError(path, "is empty (0 bytes), not a checkpoint (a write cut "
                                       "short?); resume from another checkpoint or render anew")
            fh.seek(max(size - len(SEAL) - _DIGEST, 0))
            tail = fh.read()
            if not tail.startswith(SEAL) or len(tail) != len(SEAL) + _DIGEST:
                return False
            if _digest(fh, size - _DIGEST) != tail[len(SEAL):]:
                raise InputError(path, "is damaged: its contents do not match its SHA-256 seal "
                                       "(a byte changed on the disk or in a copy); resume from "
                                       "another checkpoint or render anew")
    except FileNotFoundError:
        raise InputError(path, "checkpoint not found") from None
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a checkpoint file") from None
    except OSError as exc:
        raise InputError(path, f"cannot read the checkpoint ({exc.strerror or exc})") from None
    return True


def is_checkpoint(path: str | Path) -> bool:
    """Whether the file at ``path`` is an intact vastray checkpoint (its seal checks out)."""
    try:
        return _check_seal(Path(path))
    except InputError:
        return False


def read_checkpoint(path: str | Path, identity: dict) -> Snapshot:
    """The snapshot a checkpoint holds, checked against this render's ``identity``.

    Raises
    ------
    InputError
        Naming the file and what is wrong: missing, empty, truncated, damaged, not a
        checkpoint, or made for another render (naming the first setting that differs).
    """
    path = Path(path)
    remove_orphans(path)  # temporaries of writes to this file that were killed midway
    sealed = _check_seal(path)
    try:
        with NPY_HEADERS, np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {name: np.array(data[name]) for name in FILM_ARRAYS}
    except Exception as exc:  # zipfile, numpy and json raise many kinds on foreign bytes
        raise InputError(path, _NO_SEAL if not sealed else f"not a vastray checkpoint "
                                                             f"({exc})") from None
    found = meta.get("format") if isinstance(meta, dict) else None
    if found != CHECKPOINT_FORMAT:
        why = _OLD_FORMATS.get(found) if isinstance(found, int) else None
        why = f" ({why})" if why else ""
        raise InputError(path, f"checkpoint format {found!r}{why}; this vastray reads "
                               f"format {CHECKPOINT_FORMAT} only: render anew without --resume")
    if not sealed:
        raise InputError(path, _NO_SEAL)
    _check_identity(path, meta.get("identity") or {}, identity)
    film = Film(int(meta["width"]), int(meta["height"]))
    for name, array in arrays.items():
        want = getattr(film, name)
        if array.shape != want.shape or array.dtype != want.dtype:
            raise InputError(path, f"checkpoint array {name} is {array.dtype}{array.shape}, "
                                   f"expected {want.dtype}{want.shape}")
        setattr(film, name, array)
    return Snapshot(film, int(meta["passes_done"]), tuple(meta.get("series") or ()),
                    float(meta.get("seconds") or 0.0))


#: ``vastray render`` options whose values are paths: a checkpoint's command keeps them
#: absolute, so that ``--resume`` alone works from any folder.
PATH_OPTIONS = frozenset({"-o", "--output", "--png", "--scene", "--log-dir", "--rendezvous",
                          "--keys", "--report", "--reference", "--checkpoint"})


def saved_command(argv: list[str], store: str | None) -> list[str]:
    """The ``vastray render`` arguments ``argv`` as a checkpoint keeps them: paths made
    absolute (the positional ``store`` and the values of ``PATH_OPTIONS``), ``--resume``
    left out (a resume names its own)."""
    out, i, store_seen = [], 0, False
    while i < len(argv):
        token = argv[i]
        option, eq, value = token.partition("=")
        if option == "--resume":
            i += 1 if eq else 2
            continue
        if token.startswith("-") and eq and option in PATH_OPTIONS:
            out.append(f"{option}={os.path.abspath(value)}")
        elif token in PATH_OPTIONS and i + 1 < len(argv):
            out += [token, os.path.abspath(argv[i + 1])]
            i += 1
        elif store is not None and not store_seen and token == store:
            out.append(os.path.abspath(token))
            store_seen = True
        else:
            out.append(token)
        i += 1
    return out


def checkpoint_command(path: str | Path) -> list[str] | None:
    """The ``vastray render`` arguments of the run that wrote the checkpoint at ``path``
    (``saved_command``), or None: none kept, or a file that is not a sound checkpoint (which
    ``read_checkpoint`` then names)."""
    try:
        if not _check_seal(Path(path)):
            return None
        with NPY_HEADERS, np.load(path, allow_pickle=False) as data:
            command = json.loads(str(data["meta"]))["identity"].get("command")
    except Exception:  # noqa: BLE001 - read_checkpoint says what is wrong, in one line
        return None
    if isinstance(command, list) and all(isinstance(a, str) for a in command):
        return command
    return None


def why_no_command(path: str | Path) -> str:
    """Why ``vastray render --resume CHECKPOINT`` alone cannot go on from ``path``
    (``checkpoint_command`` found no command in it)."""
    try:
        sealed = _check_seal(Path(path))
    except InputError as exc:
        return exc.problem
    if not sealed:
        return _NO_SEAL
    return ("holds no command to go on with (written by an older vastray, or not readable): "
            "give the STORE and -o as in the first run, with --resume")


def _check_identity(path: Path, saved: dict, current: dict) -> None:
    names = {"store_manifest_sha256": "the store", "scene_sha256": "the scene file",
             "camera_sha256": "the camera", "max_pass_spp": "--max-pass-spp"}
    for key, what in names.items():
        if saved.get(key) != current.get(key):
            raise InputError(path, f"was written for another render: {what} differs; resume "
                                   "with the store, scene and options of the run that wrote it")
    # (a checkpoint written before --bvh was rendered with Embree's default BVH)
    if saved.get("bvh", "quality") != current.get("bvh", "quality"):
        raise InputError(path, f"was rendered with the {saved.get('bvh', 'quality')} BVH, this "
                               f"render builds the {current.get('bvh', 'quality')} one; resume "
                               f"with --bvh {saved.get('bvh', 'quality')}")
    theirs, ours = saved.get("settings") or {}, current["settings"]
    for key in ours:
        if theirs.get(key) != ours[key]:
            raise InputError(path, f"was written with --{key.replace('_', '-')} "
                                   f"{theirs.get(key)}, this render has {ours[key]}; resume "
                                   "with the options of the run that wrote it")


class Checkpointer:
    """Writes checkpoints of one render: every ``every`` seconds at a pass boundary, when
    asked (SIGUSR1: at once, from the last finished pass), and on Ctrl-C.

    Parameters
    ----------
    path : the checkpoint file.
    identity : ``render_identity`` of the render.
    every : seconds between checkpoints (None: only when asked or interrupted).
    write_image : ``write_image(progression)`` writes the partial image (the render's
        outputs), or None.
    """

    def __init__(self, path: str | Path, identity: dict, every: float | None = None,
                 write_image=None):
        self.path, self.identity, self.every = Path(path), identity, every
        self.write_image = write_image
        self._signal = None  # (pipe write end, thread) while SIGUSR1 writes checkpoints
        self.progression: Progression | None = None
        self.written: int | None = None  # passes done in the last checkpoint written
        self._last = time.monotonic()
        self._lock = threading.Lock()
        self._writer: ThreadPoolExecutor | None = None
        self._pending: Future | None = None
        self._warned = False  # the partial image could not be written (said once)
        self._rescued = False  # ``path`` is in a rescue folder
        remove_orphans(self.path)  # temporaries of earlier writes that were killed midway

    def after_pass(self, progression: Progression) -> None:
        """``Progression.on_pass``: a checkpoint when one is due, written on a thread of its
        own (on the coordinator, the event loop goes on with its heartbeats meanwhile); a
        write that failed raises here, at the next pass."""
        self.progression = progression
        self._raise_failed()
        if self.every is not None and time.monotonic() - self._last >= self.every:
            self._last = time.monotonic()
            if self._writer is None:
                self._writer = ThreadPoolExecutor(1, thread_name_prefix="checkpoint")
            self._pending = self._writer.submit(self.write)

    def _raise_failed(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None and pending.done() and pending.exception() is not None:
            raise InputError(self.path, f"cannot write the checkpoint: "
                                        f"{pending.exception()}") from None
        if pending is not None and not pending.done():
            self._pending = pending

    def drain(self) -> None:
        """Wait for the checkpoint being written, if any; raise if it failed."""
        if self._writer is not None:
            self._writer.shutdown(wait=True)
            self._writer = None
        self._raise_failed()

    def write(self) -> bool:
        """Write the last finished pass (nothing before the first pass, or while another
        write is under way). Returns whether one was written."""
        progression = self.progression
        if progression is None or progression.snapshot.passes_done == 0:
            return False
        if not self._lock.acquire(blocking=False):
            return False
        try:
            snap = self._write_checkpoint(progression)
            if self.write_image is not None:
                try:
                    self.write_image(progression)
                except OutputError as exc:  # the checkpoint holds the render: it goes on
                    if not self._warned:
                        print(f"warning: {exc}; the render goes on, and the checkpoint "
                              f"{self.path} holds it", file=sys.stderr)
                    self._warned = True
            self.written = snap.passes_done
            self._last = time.monotonic()
            log.info("checkpoint: %s (%d spp)", self.path, int(snap.film.count.max()))
            return True
        finally:
            self._lock.release()

    def _write_checkpoint(self, progression: Progression) -> Snapshot:
        """``write_checkpoint`` to ``path``, or, where its disk cannot take it (full,
        read-only, refused), to the rescue folder, which takes the checkpoints from then on
        (``path`` names it)."""
        try:
            return write_checkpoint(self.path, progression, self.identity)
        except OSError as exc:
            if exc.errno not in STORAGE_ERRNOS:
                raise
            for folder in rescue_folders():
                try:
                    snap = write_checkpoint(folder / self.path.name, progression,
                                            self.identity)
                except OSError:
                    continue
                print(f"warning: {self.path}: cannot be written ({exc.strerror}); the "
                      f"checkpoints go to {folder / self.path.name} instead", file=sys.stderr)
                self.path, self._rescued = folder / self.path.name, True
                return snap
            raise

    def install_signal(self) -> object:
        """SIGUSR1 writes a checkpoint now (main thread only); returns the handler it
        replaced (None where it could not install one; give it to ``uninstall_signal``).

        The write runs on a thread of its own, woken through a pipe: a signal handler runs
        between any two bytecodes of the main thread, in the middle of an import as well, and
        a write there (which imports and takes locks) once failed with "partially initialized
        module 'fractions'" and killed the render. The handler only writes a byte to the
        pipe, which takes no lock.
        """
        if threading.current_thread() is not threading.main_thread():
            return None
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)

        def serve() -> None:
            while os.read(read_fd, 64):  # b"" once the pipe is closed: the render is over
                self.write()
            os.close(read_fd)

        def request(signum, frame) -> None:
            with contextlib.suppress(OSError):  # full pipe: a write is requested already
                os.write(write_fd, b"w")

        thread = threading.Thread(target=serve, name="checkpoint-on-sigusr1", daemon=True)
        thread.start()
        self._signal = (write_fd, thread)
        return signal.signal(signal.SIGUSR1, request)

    def uninstall_signal(self, previous: object) -> None:
        """Put back the SIGUSR1 handler ``install_signal`` replaced and stop its thread (after
        a write under way, if any)."""
        if self._signal is None:
            return
        signal.signal(signal.SIGUSR1, signal.SIG_DFL if previous is None else previous)
        write_fd, thread = self._signal
        self._signal = None
        os.close(write_fd)
        thread.join(timeout=60)

    def finished(self) -> None:
        """The render is complete: its own checkpoint file is removed (a user's resumed
        file is left alone unless this render wrote over it)."""
        self.drain()
        if self.written is not None:
            self.path.unlink(missing_ok=True)
            if self._rescued:  # the rescue folder, unless something else is kept there
                with contextlib.suppress(OSError):
                    self.path.parent.rmdir()
