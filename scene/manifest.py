"""Reading a store's ``manifest.json`` without trusting it.

A manifest is a file anyone can edit, so every value in it is checked before it is used:

* its size, before it is parsed (:data:`MAX_MANIFEST_BYTES`, :data:`MAX_DOMAINS`);
* every file it names stays inside the store folder: relative, no ``..``, no symlink leading
  out, and named ``<kind>.npy`` for one of the known kinds (:func:`domain_file`);
* counts are whole numbers >= 0, boxes are finite with lo <= hi, ids are 0..N-1 in order, and
  the totals add up;
* the ``.npy`` header of every file (read without touching the data) has the shape and dtype
  the counts promise (:func:`read_npy_header`).

The checks that need the data itself (index ranges, checksums) run when a domain is loaded
(``Store.load_domain``: the CRC-32, or the SHA-256 of older stores) and in ``vastray verify``
(every checksum; see :mod:`vastray.scene.checksums`).

The optional ``"simplified"`` entry (the simplified whole-scene model) gets the same checks as
a domain entry (:func:`simplified_entry`); a manifest without it is as valid as before.

Every problem is an :class:`~vastray.scene.errors.InputError` naming the file to fix
(``manifest.json`` or the ``.npy``) and what is wrong with it.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vastray.scene import occupancy
from vastray.scene.checksums import CRC32, DIGITS, PATTERNS, SHA256
from vastray.scene.errors import InputError

FORMAT = "vastray-store"
#: Version written. 2 added a SHA-256 checksum of every array file (``"sha256"`` in each
#: domain entry); 3 added ``"origin"``, the world position of the store's frame: vertices and
#: every box of the manifest are relative to it, so float32 vertices keep their precision
#: wherever the data sits; 4 added a CRC-32 of every array file (``"crc32"``), which every
#: load checks (SHA-256 costs 3 to 10 times as much); 5 added each domain's occupancy mask
#: (``"occupancy"``, :mod:`vastray.scene.occupancy`), so rays skip a domain's empty cells.
#: Version 1 and 2 stores (frame at the world origin), 3 (loads check the SHA-256) and 4 (no
#: masks: every cell counts as occupied) still open.
VERSION = 5
READABLE_VERSIONS = (1, 2, 3, 4, 5)
#: The first version whose domain entries carry an occupancy mask.
OCCUPANCY_VERSION = 5
MANIFEST = "manifest.json"
#: The manifest key, and the store folder, of the simplified whole-scene model (optional).
SIMPLIFIED = "simplified"
ATTRIBUTES = ("objects", "scalars", "colors")
ARRAYS = ("vertices", "indices", *ATTRIBUTES)

#: Most domains a store may have (a folder each; far beyond any useful partition).
MAX_DOMAINS = 100_000
#: Largest manifest read; checked on the file's size before parsing. About 2 KB per domain
#: at :data:`MAX_DOMAINS` (a written entry is under 1 KB), plus the partition cells.
MAX_MANIFEST_BYTES = 256 * 2**20

REWRITE = "rewrite the store with `vastray partition` or `vastray generate`"
RESIMPLIFY = "rebuild it with `vastray simplify STORE --ratio R --force`"

_DRIVE = re.compile(r"[A-Za-z]:")  # C:... is absolute on Windows


@dataclass(frozen=True)
class DomainInfo:
    """A domain's manifest entry, checked: id, box (may overlap neighbours), counts, files.

    Attributes
    ----------
    files : kind (``"vertices"``, ``"indices"``, ...) -> path relative to the store, as written
        in the manifest (already checked to stay inside the store).
    sha256 : kind -> hex SHA-256 of the file; empty for version 1 stores.
    crc32 : kind -> hex CRC-32 of the file; empty before version 4.
    occupancy : (a, b, c) bool occupancy mask over the box (:mod:`vastray.scene.occupancy`);
        None before version 5 (every cell occupied).
    """

    id: int
    lo: np.ndarray  # (3,) float64
    hi: np.ndarray  # (3,) float64
    n_triangles: int
    n_vertices: int
    nbytes: int
    files: dict = field(hash=False)
    sha256: dict = field(default_factory=dict, hash=False)
    crc32: dict = field(default_factory=dict, hash=False)
    occupancy: np.ndarray | None = field(default=None, hash=False, compare=False)

    @property
    def label(self) -> str:
        """How messages name it: ``"domain N"``."""
        return f"domain {self.id}"

    def read_bytes(self, attributes=None) -> int:
        """Bytes a load reading the vertices, indices and ``attributes`` (None: every file)
        reads: ``nbytes`` less the arrays of the attributes left unread."""
        if attributes is None:
            return self.nbytes
        unread = 0
        for kind in set(self.files) & set(ATTRIBUTES) - set(attributes):
            shape, dtype = expected_array(kind, self.n_triangles, self.n_vertices)
            unread += int(np.prod(shape)) * dtype.itemsize
        return max(0, self.nbytes - unread)


@dataclass(frozen=True)
class SimplifiedInfo(DomainInfo):
    """The manifest's ``"simplified"`` entry, checked: the decimated whole-scene model.

    The inherited fields mean what they mean for a domain (``id`` is -1; ``lo``/``hi`` the box
    of its triangles, inside the scene bounds). Besides them:

    Attributes
    ----------
    ratio : the triangle fraction asked for, in (0, 1].
    rate : the fraction achieved, simplified triangles / the domains' triangles.
    memory_rate : ``nbytes`` / the domains' bytes (arrays only; BVHs are built on loading).
    min_faces : object pieces with fewer triangles were kept whole.
    """

    ratio: float = 1.0
    rate: float = 1.0
    memory_rate: float = 1.0
    min_faces: int = 0

    @property
    def label(self) -> str:
        return "simplified model"


@dataclass(frozen=True)
class NpyHeader:
    """What a ``.npy`` header promises: shape, dtype, order, and where the data starts."""

    shape: tuple
    dtype: np.dtype
    fortran_order: bool
    offset: int

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


@dataclass(frozen=True)
class StoreRoot:
    """A store folder: ``path`` as the user gave it (for messages), ``real`` resolved."""

    path: Path
    real: Path

    @staticmethod
    def of(path: str | os.PathLike) -> StoreRoot:
        path = Path(path)
        return StoreRoot(path, Path(os.path.realpath(path)))

    @property
    def manifest(self) -> Path:
        return self.path / MANIFEST


def one_line(text: object, limit: int = 200) -> str:
    """``text`` on one line, at most ``limit`` characters (for values quoted in errors)."""
    flat = " ".join(str(text).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


# --- the manifest file -------------------------------------------------------------------------


def read_manifest(root: StoreRoot) -> dict:
    """Parse ``root``'s manifest after checking where it is and how big it is.

    Returns
    -------
    The manifest, a dict whose format and version are readable.

    Raises
    ------
    InputError
        No such store, no manifest, a manifest outside the store or not a regular file, too
        large, not JSON, or not a readable vastray store version.
    """
    where = root.manifest
    if not root.path.exists():
        raise InputError(root.path, "no such store (run `vastray partition` or `vastray generate`)")
    if not root.path.is_dir():
        raise InputError(root.path, "is not a folder; a store is a folder holding manifest.json")
    size = _manifest_size(root)
    if size > MAX_MANIFEST_BYTES:
        raise InputError(where, f"is {size:,} bytes, more than the {MAX_MANIFEST_BYTES:,} a store "
                                f"manifest may have (at most {MAX_DOMAINS:,} domains); not read")
    try:
        manifest = json.loads(where.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(where, f"not valid JSON ({one_line(exc)})") from None
    except RecursionError:
        raise InputError(where, "not a store manifest (JSON nested too deeply)") from None
    except OSError as exc:
        raise InputError(where, f"cannot be read ({exc.strerror})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise InputError(where, f"not a {FORMAT} manifest")
    version = manifest.get("version")
    if isinstance(version, bool) or version not in READABLE_VERSIONS:
        raise InputError(where, f"store format version {one_line(repr(version), 40)} is not "
                                f"supported (this vastray reads versions "
                                f"{', '.join(map(str, READABLE_VERSIONS))}); re-run `vastray partition`")
    return manifest


def _manifest_size(root: StoreRoot) -> int:
    """Size of the manifest, refused unless it is a regular file inside the store."""
    where = root.manifest
    real = Path(os.path.realpath(where))
    if not where.exists():
        raise InputError(where, "missing manifest; is this a vastray store?")
    if not real.is_relative_to(root.real):
        raise InputError(where, f"resolves to {real}, outside the store (a symlink?); "
                                "the manifest must be a file inside the store folder")
    try:
        st = os.stat(real)
    except OSError as exc:
        raise InputError(where, f"cannot be read ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(where, "is not a regular file; is this a vastray store?")
    return st.st_size


def manifest_size_ok(path: str | os.PathLike) -> bool:
    """Whether ``path`` (a manifest file) is small enough to parse; False when unreadable."""
    try:
        return os.stat(path).st_size <= MAX_MANIFEST_BYTES
    except OSError:
        return False


# --- whole-store fields ------------------------------------------------------------------------


def scene_fields(manifest: dict, where: Path) -> np.ndarray:
    """Check the store-wide fields (bounds, objects, attributes, scalar range, domains list).

    Returns
    -------
    (2, 3) float64 scene bounds.

    Raises
    ------
    InputError
        Naming ``where`` (the manifest) and the field at fault.
    """
    domains = manifest.get("domains")
    if not isinstance(domains, list):
        raise InputError(where, f"'domains' must be a list of domain entries; {REWRITE}")
    if len(domains) > MAX_DOMAINS:
        raise InputError(where, f"lists {len(domains):,} domains, more than the {MAX_DOMAINS:,} a "
                                "store may have")
    objects = manifest.get("objects", [])
    if not isinstance(objects, list) or not all(isinstance(o, dict) for o in objects):
        raise InputError(where, "'objects' must be a list of {\"name\": ...} entries")
    attributes = manifest.get("attributes", {})
    if not isinstance(attributes, dict) or set(attributes) - set(ATTRIBUTES):
        raise InputError(where, f"'attributes' must map some of {', '.join(ATTRIBUTES)} to "
                                f"true/false, found {one_line(repr(attributes), 80)}")
    if manifest.get("scalar_range") is not None:
        _interval(manifest["scalar_range"], where, "'scalar_range'")
    _count(manifest.get("triangles"), where, "'triangles' (the total)")
    lo, hi = box(manifest.get("bounds"), where, "scene 'bounds'")
    return np.stack([lo, hi])


def frame_origin(manifest: dict, where: Path) -> np.ndarray:
    """The store frame's origin in world coordinates ((3,) float64): ``"origin"`` of a
    version 3 manifest, zero for older ones.

    Raises
    ------
    InputError
        A version 3 manifest without a finite 3-vector ``"origin"``.
    """
    if manifest["version"] < 3:
        return np.zeros(3)
    value = manifest.get("origin")
    if not (isinstance(value, list) and len(value) == 3 and all(map(_is_number, value))
            and all(map(math.isfinite, value))):
        raise InputError(where, f"'origin' must be a finite [x, y, z], found "
                                f"{one_line(repr(value), 80)}; {REWRITE}")
    return np.asarray(value, np.float64)


def _interval(value, where: Path, what: str) -> None:
    if not (isinstance(value, list) and len(value) == 2 and all(map(_is_number, value))):
        raise InputError(where, f"{what} must be [lo, hi], found {one_line(repr(value), 80)}")
    if not all(map(math.isfinite, value)) or value[0] > value[1]:
        raise InputError(where, f"{what} must be finite with lo <= hi, found {value}; {REWRITE}")


def totals(manifest: dict, domains: list[DomainInfo], bounds: np.ndarray, where: Path) -> None:
    """Check that the total triangle count and the scene box agree with the domains.

    Raises
    ------
    InputError
        The sum of the domains' triangles differs from ``"triangles"``, or a non-empty
        domain's box sticks out of the scene ``"bounds"``.
    """
    total = sum(d.n_triangles for d in domains)
    if manifest["triangles"] != total:
        raise InputError(where, f"'triangles' says {manifest['triangles']:,} but the domains hold "
                                f"{total:,}; {REWRITE}")
    for d in domains:
        if d.n_triangles and not _inside(d.lo, d.hi, bounds[0], bounds[1]):
            raise InputError(where, f"domain {d.id} bounds stick out of the scene 'bounds' "
                                    f"(a domain would be left out of the picture); {REWRITE}")


def _inside(lo, hi, outer_lo, outer_hi) -> bool:
    slack = 1e-6 * max(1.0, float(np.abs(np.concatenate([outer_lo, outer_hi])).max()))
    return bool((lo >= outer_lo - slack).all() and (hi <= outer_hi + slack).all())


# --- one domain entry --------------------------------------------------------------------------


@dataclass
class DomainParser:
    """Checks domain entries in manifest order, remembering the ids seen (for duplicates).

    Parameters
    ----------
    root : the store.
    manifest : the parsed manifest (format and version already checked).
    check_headers : read each file's ``.npy`` header and compare it with the counts.
    """

    root: StoreRoot
    manifest: dict
    check_headers: bool = True
    _first_at: dict = field(default_factory=dict)

    def __iter__(self) -> Iterator[DomainInfo | InputError]:
        """Each entry in order: its :class:`DomainInfo`, or the first problem found in it."""
        for position, entry in enumerate(self.manifest["domains"]):
            try:
                yield self.parse(entry, position)
            except InputError as exc:
                yield exc

    def parse(self, entry, position: int) -> DomainInfo:
        """Check one domain entry (the ``position``-th) and the headers of its files.

        Raises
        ------
        InputError
            Naming the manifest, or the ``.npy`` file whose header disagrees with it.
        """
        where = self.root.manifest
        label = f"domain {position}"
        if not isinstance(entry, dict):
            raise InputError(where, f"{label}: entry must be an object, found "
                                    f"{one_line(repr(entry), 60)}")
        self._check_id(entry.get("id"), position)
        n_tri = _count(entry.get("triangles"), where, f"{label} 'triangles'")
        n_vert = _count(entry.get("vertices"), where, f"{label} 'vertices'")
        nbytes = _count(entry.get("bytes"), where, f"{label} 'bytes'")
        if n_tri and not n_vert:
            raise InputError(where, f"{label} has {n_tri:,} triangles but 0 vertices; {REWRITE}")
        lo, hi = box(entry.get("bounds"), where, f"{label} bounds")
        files = self._files(entry.get("files"), label, n_tri)
        sha = self._checksums(entry.get("sha256"), files, label)
        crc = self._crc32(entry.get(CRC32), files, label)
        mask = self._occupancy(entry.get("occupancy"), label)
        if self.check_headers:
            check_headers(self.root, files, n_tri, n_vert, nbytes, label)
        return DomainInfo(position, lo, hi, n_tri, n_vert, nbytes, files, sha, crc, mask)

    def _check_id(self, value, position: int) -> None:
        where = self.root.manifest
        if not _is_int(value):
            raise InputError(where, f"domain {position}: 'id' must be a whole number, found "
                                    f"{one_line(repr(value), 40)}")
        first = self._first_at.setdefault(value, position)
        if first != position:
            raise InputError(where, f"duplicate domain id {value} (entries {first} and {position}); "
                                    f"ids must be 0..N-1 in order; {REWRITE}")
        if value != position:
            raise InputError(where, f"domain ids must be 0..N-1 in order: entry {position} has id "
                                    f"{value}; {REWRITE}")

    def _files(self, files, label: str, n_tri: int) -> dict:
        where = self.root.manifest
        if not isinstance(files, dict):
            raise InputError(where, f"{label} 'files' must map kinds to paths, found "
                                    f"{one_line(repr(files), 60)}")
        unknown = sorted(set(files) - set(ARRAYS))
        if unknown:
            raise InputError(where, f"{label} lists unknown file kind(s) {unknown}; expected some "
                                    f"of {', '.join(ARRAYS)}")
        for kind in ("vertices", "indices"):
            if kind not in files:
                raise InputError(where, f"{label} lists no {kind} file; {REWRITE}")
        for kind, rel in files.items():
            domain_file(self.root, rel, kind, label)
        declared = self.manifest.get("attributes")
        declared = declared if isinstance(declared, dict) else {}
        for kind in ATTRIBUTES:
            if declared.get(kind) and n_tri and kind not in files:
                raise InputError(where, f"{label} has no {kind} file, but the manifest's "
                                        f"'attributes' say the scene has {kind}; {REWRITE}")
        return dict(files)

    def _checksums(self, sha, files: dict, label: str) -> dict:
        if self.manifest["version"] < 2:
            return {}
        return checked_checksums(sha, files, label, self.root.manifest)

    def _occupancy(self, value, label: str) -> np.ndarray | None:
        """The entry's occupancy mask (version 5 on), None before."""
        if self.manifest["version"] < OCCUPANCY_VERSION:
            return None
        try:
            return occupancy.decode(value)
        except ValueError as exc:
            raise InputError(self.root.manifest, f"{label} 'occupancy' {exc}, found "
                                                 f"{one_line(repr(value), 60)}; {REWRITE}") from None

    def _crc32(self, crc, files: dict, label: str) -> dict:
        if self.manifest["version"] < 4:
            return {}
        return checked_checksums(crc, files, label, self.root.manifest, CRC32)


def checked_checksums(sums, files: dict, label: str, where, algorithm: str = SHA256) -> dict:
    """``sums`` ({kind: hex digest} for each of ``files``) if well formed, else InputError
    naming the manifest ``where``.

    Parameters
    ----------
    algorithm : the manifest key, ``"sha256"`` (64 hex digits) or ``"crc32"`` (8).
    """
    if not isinstance(sums, dict) or set(sums) != set(files):
        raise InputError(where, f"{label} '{algorithm}' must give a checksum for each of its "
                                f"files ({', '.join(files)}), found {one_line(repr(sums), 80)}")
    for kind, digest in sums.items():
        if not isinstance(digest, str) or not PATTERNS[algorithm].fullmatch(digest):
            raise InputError(where, f"{label} '{algorithm}' of {kind} is not {DIGITS[algorithm]} "
                                    f"lowercase hex digits: {one_line(repr(digest), 80)}")
    return dict(sums)


def simplified_entry(root: StoreRoot, manifest: dict, bounds: np.ndarray | None,
                     read_headers: bool = True) -> SimplifiedInfo | None:
    """Check the manifest's optional ``"simplified"`` entry as a domain entry is checked.

    Its files must stay inside the store and be named ``<kind>.npy``; its counts must be whole
    numbers that the ``.npy`` headers (and ``bytes``) agree with; it needs a checksum of every
    file (it is newer than format version 2, so always has them); it carries the attributes
    the scene declares; its box is finite and lies inside the scene ``bounds`` (when given);
    ``ratio`` is in (0, 1] and ``rate``, ``memory_rate`` are finite numbers >= 0.

    Returns
    -------
    The checked entry, or None when the store has no simplified model (stores written before
    it existed).

    Raises
    ------
    InputError
        Naming the manifest, or the ``.npy`` file whose header disagrees with it.
    """
    if SIMPLIFIED not in manifest:
        return None
    where = root.manifest
    label = "simplified model"
    entry = manifest[SIMPLIFIED]
    if not isinstance(entry, dict):
        raise InputError(where, f"'{SIMPLIFIED}' must be an object, found "
                                f"{one_line(repr(entry), 60)}; {RESIMPLIFY}")
    n_tri = _count(entry.get("triangles"), where, f"{label} 'triangles'")
    n_vert = _count(entry.get("vertices"), where, f"{label} 'vertices'")
    nbytes = _count(entry.get("bytes"), where, f"{label} 'bytes'")
    min_faces = _count(entry.get("min_faces", 0), where, f"{label} 'min_faces'")
    if n_tri and not n_vert:
        raise InputError(where, f"{label} has {n_tri:,} triangles but 0 vertices; {RESIMPLIFY}")
    ratio = entry.get("ratio")
    if not (_is_number(ratio) and 0 < ratio <= 1):
        raise InputError(where, f"{label} 'ratio' must be a number in (0, 1], found "
                                f"{one_line(repr(ratio), 40)}; {RESIMPLIFY}")
    rate, memory_rate = (_rate(entry.get(key), where, f"{label} '{key}'")
                         for key in ("rate", "memory_rate"))
    lo, hi = box(entry.get("bounds"), where, f"{label} bounds")
    if bounds is not None and n_tri and not _inside(lo, hi, bounds[0], bounds[1]):
        raise InputError(where, f"{label} bounds stick out of the scene 'bounds'; {RESIMPLIFY}")
    parser = DomainParser(root, manifest, check_headers=False)
    files = parser._files(entry.get("files"), label, n_tri)
    sha = checked_checksums(entry.get("sha256"), files, label, where)
    # written since version 4, by any vastray that writes CRC-32s (also into older stores)
    crc = ({} if manifest["version"] < 4 and CRC32 not in entry
           else checked_checksums(entry.get(CRC32), files, label, where, CRC32))
    if read_headers:
        check_headers(root, files, n_tri, n_vert, nbytes, label)
    return SimplifiedInfo(-1, lo, hi, n_tri, n_vert, nbytes, dict(files), dict(sha), dict(crc),
                          ratio=float(ratio), rate=rate, memory_rate=memory_rate,
                          min_faces=min_faces)


def _rate(value, where: Path, what: str) -> float:
    if not (_is_number(value) and math.isfinite(value) and value >= 0):
        raise InputError(where, f"{what} must be a finite number >= 0, found "
                                f"{one_line(repr(value), 40)}; {RESIMPLIFY}")
    return float(value)


def domain_file(root: StoreRoot, rel, kind: str, label: str) -> Path:
    """The path of a file a manifest names, refused unless it stays inside the store.

    Parameters
    ----------
    root : the store.
    rel : the path as written in the manifest.
    kind : which array it holds; the file must be named ``<kind>.npy``.
    label : ``"domain N"``, for messages.

    Returns
    -------
    ``root.path / rel`` (as the user would name it).

    Raises
    ------
    InputError
        Naming the manifest: not a string, absolute, with ``..`` or ``\\``, another name than
        ``<kind>.npy``, or resolving (through a symlink) outside the store.
    """
    where = root.manifest
    shown = one_line(repr(rel), 120)
    if not isinstance(rel, str) or not rel or "\x00" in rel:
        raise InputError(where, f"{label} {kind} file must be a relative path, found {shown}")
    if rel.startswith("/") or _DRIVE.match(rel):
        raise InputError(where, f"{label} {kind} file {shown} is an absolute path; files must be "
                                f"relative to the store folder, like 'domains/00000/{kind}.npy'")
    if "\\" in rel:
        raise InputError(where, f"{label} {kind} file {shown} contains '\\'; separate folders "
                                f"with '/', like 'domains/00000/{kind}.npy'")
    parts = rel.split("/")
    if ".." in parts:
        raise InputError(where, f"{label} {kind} file {shown} climbs out with '..'; files must "
                                "be inside the store folder")
    if parts[-1] != f"{kind}.npy":
        raise InputError(where, f"{label} {kind} file {shown} must be named '{kind}.npy'")
    real = os.path.realpath(os.path.join(root.real, rel))
    if os.path.commonpath([real, root.real]) != str(root.real):
        raise InputError(where, f"{label} {kind} file {shown} resolves to {real}, outside the "
                                "store (a symlink?); store files must live inside the store folder")
    return root.path / rel


# --- .npy headers ------------------------------------------------------------------------------


def expected_array(kind: str, n_triangles: int, n_vertices: int) -> tuple[tuple, np.dtype]:
    """Shape and dtype the manifest's counts promise for the ``kind`` file."""
    t, v = n_triangles, n_vertices
    return {
        "vertices": ((v, 3), np.dtype(np.float32)),
        "indices": ((t, 3), np.dtype(np.uint32)),
        "objects": ((t,), np.dtype(np.uint16)),
        "scalars": ((v,), np.dtype(np.float32)),
        "colors": ((v, 3), np.dtype(np.float32)),
    }[kind]


def mismatch(kind: str, n_triangles: int, n_vertices: int, shape: tuple,
             dtype: np.dtype) -> str | None:
    """Why an array of ``shape``/``dtype`` cannot be the ``kind`` file, or None if it can."""
    want_shape, want_dtype = expected_array(kind, n_triangles, n_vertices)
    if tuple(shape) == want_shape and np.dtype(dtype) == want_dtype:
        return None
    return (f"does not match the manifest: expected {want_shape} {want_dtype}, found "
            f"{tuple(shape)} {np.dtype(dtype)} (the manifest says {n_triangles:,} triangles, "
            f"{n_vertices:,} vertices); {REWRITE}")


def check_headers(root: StoreRoot, files: dict, n_tri: int, n_vert: int, nbytes: int,
                  label: str) -> None:
    """Compare each file's ``.npy`` header with the counts (no data is read).

    Raises
    ------
    InputError
        Naming the ``.npy`` file whose shape or dtype is not the promised one, or the manifest
        when its ``bytes`` is not the sum of the arrays' sizes.
    """
    total = 0
    for kind, rel in files.items():
        path = root.path / rel
        header = read_npy_header(path)
        problem = mismatch(kind, n_tri, n_vert, header.shape, header.dtype)
        if problem:
            raise InputError(path, problem)
        total += header.nbytes
    if total != nbytes:
        raise InputError(root.manifest, f"{label} 'bytes' says {nbytes:,} but its arrays hold "
                                        f"{total:,}; {REWRITE}")


def read_npy_header(path: Path) -> NpyHeader:
    """The header of a ``.npy`` file, read without its data.

    Raises
    ------
    InputError
        Naming ``path``: missing, not a regular file, or not a ``.npy`` header numpy reads.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(path, "domain file missing (store is incomplete; re-run partition)") from None
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(path, "is not a regular file; store arrays are .npy files")
    try:
        with open(path, "rb") as fh:
            return parse_npy_header(fh)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(path, f"not a readable .npy file ({one_line(exc)})") from None


#: Every ``.npy`` header is parsed under this lock (``with NPY_HEADERS:`` around ``np.load`` as
#: well). numpy parses a header with ``ast.literal_eval``, and CPython 3.11 keeps the AST
#: constructor's recursion depth in state shared by threads (python/cpython#106905): a render
#: worker and the preloader parsing headers at once failed a domain load with "SystemError: AST
#: constructor recursion depth mismatch" (CI, 2026-11-29, Python 3.11.7).
NPY_HEADERS = threading.Lock()


def parse_npy_header(fh) -> NpyHeader:
    """Read a ``.npy`` header from the binary file object ``fh`` (left at the data).

    Raises
    ------
    ValueError
        Not a ``.npy`` header, or a format version other than 1.0 and 2.0.
    """
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        with NPY_HEADERS:
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        with NPY_HEADERS:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        raise ValueError(f".npy format version {version} (vastray writes 1.0)")
    if dtype.hasobject:
        raise ValueError("holds Python objects, not numbers")
    return NpyHeader(tuple(shape), dtype, bool(fortran), fh.tell())


def array_from_bytes(data) -> np.ndarray:
    """The array a ``.npy`` file's bytes hold (``data``: bytes, or a writable buffer such as a
    bytearray or a uint8 array, for a writable array), without copying them.

    Raises
    ------
    ValueError
        Not a ``.npy`` file, or more or fewer data bytes than the header promises.
    """
    header = parse_npy_header(_BufferReader(data))
    have = len(data) - header.offset
    if have != header.nbytes:
        raise ValueError(f"{have:,} bytes of data where the header promises {header.nbytes:,}")
    count = math.prod(header.shape)
    if count == 0:
        return np.empty(header.shape, header.dtype)
    flat = np.frombuffer(data, header.dtype, count=count, offset=header.offset)
    return flat.reshape(header.shape, order="F" if header.fortran_order else "C")


class _BufferReader:
    """``read`` and ``tell`` over a buffer, copying only what is read (``io.BytesIO`` copies a
    whole bytearray)."""

    def __init__(self, data):
        self._view = memoryview(data).cast("B")
        self._at = 0

    def read(self, size: int = -1) -> bytes:
        end = len(self._view) if size is None or size < 0 else self._at + size
        out = bytes(self._view[self._at:end])
        self._at += len(out)
        return out

    def tell(self) -> int:
        return self._at


# --- values ------------------------------------------------------------------------------------


def box(value, where: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    """A ``[[xlo, ylo, zlo], [xhi, yhi, zhi]]`` box as two (3,) float64 arrays.

    Raises
    ------
    InputError
        Naming ``where``: not 2x3 numbers, not finite, or lo > hi on some axis.
    """
    if not (isinstance(value, list) and len(value) == 2
            and all(isinstance(c, list) and len(c) == 3 and all(map(_is_number, c)) for c in value)):
        raise InputError(where, f"{what} must be [[xlo, ylo, zlo], [xhi, yhi, zhi]], found "
                                f"{one_line(repr(value), 80)}")
    lo, hi = np.array(value, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise InputError(where, f"{what} are not finite ({one_line(value, 80)}); {REWRITE}")
    if (lo > hi).any():
        axis = "xyz"[int(np.argmax(lo > hi))]
        raise InputError(where, f"{what} have lo > hi on {axis} ({one_line(value, 80)}); {REWRITE}")
    return lo, hi


def _count(value, where: Path, what: str) -> int:
    if not _is_int(value) or value < 0:
        raise InputError(where, f"{what} must be a whole number >= 0, found "
                                f"{one_line(repr(value), 40)}; {REWRITE}")
    return value


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
