"""Checkpoints of a progressive render: the film after its last finished pass, written
atomically beside the image, and read back by ``vastray render --resume``.

A checkpoint is one ``.npz`` file (numpy's zip of arrays, read without pickle): the film's
arrays plus a JSON ``meta`` entry: format version, the passes done, the render seconds so far,
the error series, and ``identity``, everything that decides the image besides ``--spp`` (the
store's manifest digest, the scene, the resolved camera, the sampling settings, the pass
size). A resume must match it: then the passes it adds are those an uninterrupted run adds,
and, every sample being a pure function of (seed, pixel, sample), so is the image.
"""

from __future__ import annotations

import hashlib
import json
import logging
import signal
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np

from vastray.render.film import Film
from vastray.render.imageio import atomic_path
from vastray.render.progressive import Progression, Snapshot
from vastray.scene.errors import InputError

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = 1
FILM_ARRAYS = ("sum", "sum_odd", "count", "depth", "normal")

#: Settings that do not change the image: the spp bound (a resume may go further), the
#: pass window and the in-core batch size.
_FREE_SETTINGS = ("spp", "sample_start", "sample_stop", "batch_size")


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
            "max_pass_spp": max_pass_spp}


def write_checkpoint(path: str | Path, progression: Progression, identity: dict) -> Snapshot:
    """Write the progression's last finished pass to ``path`` atomically; returns the
    snapshot written (taken once, so the arrays and meta agree)."""
    snap = progression.snapshot
    meta = {"format": CHECKPOINT_FORMAT, "identity": identity,
            "passes_done": snap.passes_done, "spp": int(snap.film.count.max()),
            "seconds": snap.seconds, "series": list(snap.series),
            "width": snap.film.width, "height": snap.film.height}
    arrays = {name: getattr(snap.film, name) for name in FILM_ARRAYS}
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, meta=np.array(json.dumps(meta)), **arrays)
    return snap


def read_checkpoint(path: str | Path, identity: dict) -> Snapshot:
    """The snapshot a checkpoint holds, checked against this render's ``identity``.

    Raises
    ------
    InputError
        Naming the file and what is wrong: missing, not a checkpoint, or made for another
        render (naming the first setting that differs).
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {name: np.array(data[name]) for name in FILM_ARRAYS}
    except FileNotFoundError:
        raise InputError(path, "checkpoint not found") from None
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as exc:
        raise InputError(path, f"not a vastray checkpoint ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        raise InputError(path, f"checkpoint format {meta.get('format')!r}; this vastray reads "
                               f"format {CHECKPOINT_FORMAT}")
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


def _check_identity(path: Path, saved: dict, current: dict) -> None:
    names = {"store_manifest_sha256": "the store", "scene_sha256": "the scene file",
             "camera_sha256": "the camera", "max_pass_spp": "--max-pass-spp"}
    for key, what in names.items():
        if saved.get(key) != current.get(key):
            raise InputError(path, f"was written for another render: {what} differs; resume "
                                   "with the store, scene and options of the run that wrote it")
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
        self.progression: Progression | None = None
        self.written: int | None = None  # passes done in the last checkpoint written
        self._last = time.monotonic()
        self._lock = threading.Lock()
        self._writer: ThreadPoolExecutor | None = None
        self._pending: Future | None = None

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
            snap = write_checkpoint(self.path, progression, self.identity)
            if self.write_image is not None:
                self.write_image(progression)
            self.written = snap.passes_done
            self._last = time.monotonic()
            log.info("checkpoint: %s (%d spp)", self.path, int(snap.film.count.max()))
            return True
        finally:
            self._lock.release()

    def install_signal(self) -> object:
        """SIGUSR1 writes a checkpoint now (main thread only); returns the handler it
        replaced (None where it could not install one)."""
        if threading.current_thread() is not threading.main_thread():
            return None
        return signal.signal(signal.SIGUSR1, lambda signum, frame: self.write())

    def finished(self) -> None:
        """The render is complete: its own checkpoint file is removed (a user's resumed
        file is left alone unless this render wrote over it)."""
        self.drain()
        if self.written is not None:
            self.path.unlink(missing_ok=True)
