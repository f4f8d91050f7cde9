"""The on-disk domain store: a versioned JSON manifest plus one set of ``.npy`` files per domain.

Layout of a STORE folder::

    STORE/manifest.json
    STORE/domains/00000/vertices.npy   (V, 3) float32
    STORE/domains/00000/indices.npy    (T, 3) uint32, indices into this domain's vertices
    STORE/domains/00000/objects.npy    (T,)   uint16, index into manifest["objects"]   [optional]
    STORE/domains/00000/scalars.npy    (V,)   float32 per-vertex scalar field           [optional]
    STORE/domains/00000/colors.npy     (V, 3) float32 per-vertex linear RGB in [0, 1]   [optional]
    STORE/simplified/vertices.npy      the simplified whole-scene model, the same files as a
    STORE/simplified/indices.npy ...   domain's                                        [optional]

Every file is a ``.npy`` file. A store is written into a temporary folder and renamed into
place when complete, so a failed run never leaves a partial store. Since format version 2 each
domain entry records the SHA-256 of each of its files (``"sha256": {"vertices": ..., ...}``),
which ``vastray verify`` checks; version 1 stores (no checksums) still open. Since version 4 it
also records their CRC-32 (``"crc32"``), which every load checks (the SHA-256 where a store has
no CRC-32): a domain whose files changed since they were written is refused, naming the file,
never rendered (:mod:`vastray.scene.checksums`). Loads read the files into memory by default
rather than mapping them: a mapped file truncated or rewritten while a render uses it would
kill the process with SIGBUS or change the picture halfway. Since version 3 the manifest's
``"origin"`` places the store's frame in the world: vertices and boxes are stored relative to
it (float32 vertices of data far from the world origin keep their precision; the renderer
moves camera and lights into that frame). Since version 5 each domain entry also carries its
occupancy mask (``"occupancy"``: a coarse grid of bits over its box, set where triangles are;
:mod:`vastray.scene.occupancy`), which the ray-domain queries use to skip a domain's empty
space; older stores open without (every cell occupied).
How a manifest is checked on opening: :mod:`vastray.scene.manifest`.

The optional ``"simplified"`` manifest entry describes a decimated copy of the whole scene
(:mod:`vastray.scene.simplify`; paper §6.1): its counts, box, files and checksums like a
domain entry, plus ``ratio`` (asked), ``rate`` (achieved triangle fraction), ``memory_rate``
(its bytes over the domains' bytes) and ``min_faces``. :func:`write_simplified` adds or
replaces it in an existing store; stores without it open as before.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, replace
from mmap import ACCESS_READ
from mmap import mmap as MemoryMap
from pathlib import Path

import numpy as np

from vastray.scene import occupancy
from vastray.scene.checksums import (
    CRC32,
    SHA256,
    HashingWriter,
    RunningDigest,
    checksum_mismatch,
    digest_mismatch,
    load_check,
)
from vastray.scene.errors import InputError
from vastray.scene.filemode import publish_mode
from vastray.scene.manifest import (  # noqa: F401  (FORMAT, MANIFEST, DomainInfo: re-exported)
    ARRAYS,
    ATTRIBUTES,
    FORMAT,
    MANIFEST,
    MAX_DOMAINS,
    MAX_MANIFEST_BYTES,
    NPY_HEADERS,
    REWRITE,
    SIMPLIFIED,
    VERSION,
    DomainInfo,
    DomainParser,
    SimplifiedInfo,
    StoreRoot,
    array_from_bytes,
    domain_file,
    frame_origin,
    manifest_size_ok,
    mismatch,
    one_line,
    read_manifest,
    scene_fields,
    simplified_entry,
    totals,
)
from vastray.scene.occupancy import Occupancy


@dataclass
class DomainArrays:
    """Triangles of one domain, with optional attributes.

    Attributes
    ----------
    vertices : (V, 3) float32
    indices : (T, 3) uint32
    objects : (T,) uint16 or None
        Index of the input object (material slot) of each triangle.
    scalars : (V,) float32 or None
        Per-vertex scalar field (colour-mapped at render time).
    colors : (V, 3) float32 or None
        Per-vertex linear RGB colour in [0, 1].
    origin : (3,) float64 or None
        World position the vertices are relative to (None: the world origin). Readers set it
        for data far from the world origin (``frame_for``), so float32 vertices stay precise.
    """

    vertices: np.ndarray
    indices: np.ndarray
    objects: np.ndarray | None = None
    scalars: np.ndarray | None = None
    colors: np.ndarray | None = None
    origin: np.ndarray | None = None

    @property
    def n_triangles(self) -> int:
        return int(self.indices.shape[0])

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 box of the vertices referenced by triangles."""
        if self.n_triangles == 0:
            return np.zeros((2, 3))
        used = self.vertices[np.unique(self.indices)]
        return np.stack([used.min(axis=0), used.max(axis=0)]).astype(np.float64)

    def nbytes(self) -> int:
        arrays = [self.vertices, self.indices, self.objects, self.scalars, self.colors]
        return int(sum(a.nbytes for a in arrays if a is not None))


def frame_for(lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """A frame origin for data in the box ``[lo, hi]`` ((3,) float64 each): None (the world
    origin) when the box reaches to within its own size of the world origin, where float32
    coordinates lose nothing worth keeping; otherwise the box centre, rounded to float32.

    Returns
    -------
    (3,) float64 or None
    """
    center = (np.asarray(lo, np.float64) + np.asarray(hi, np.float64)) / 2.0
    extent = float(np.max(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), initial=0.0))
    if float(np.abs(center).max(initial=0.0)) <= max(extent, 0.0):
        return None
    return center


def relative_to(vertices64: np.ndarray) -> DomainArrays:
    """``vertices64`` ((V, 3) float64 world positions) as float32 vertices in their own frame
    (``frame_for`` of their box): DomainArrays with no triangles yet (fill ``indices``)."""
    v = np.asarray(vertices64, np.float64)
    origin = frame_for(v.min(axis=0), v.max(axis=0)) if len(v) else None
    rel = v if origin is None else v - origin
    return DomainArrays(rel.astype(np.float32), np.zeros((0, 3), np.uint32), origin=origin)


class Store:
    """A read-only view of a STORE folder; loads domains on demand.

    Opening checks the whole manifest and the ``.npy`` header of every file it names (see
    :mod:`vastray.scene.manifest`); loading a domain checks its data (shapes, dtypes, index
    ranges) and its files' checksums (:mod:`vastray.scene.checksums`). Nothing the manifest
    says is used unchecked, so a damaged or hand-edited store fails with an
    :class:`InputError` naming the file, never a silently missing domain.

    Parameters
    ----------
    path : path to the STORE folder.

    Raises
    ------
    InputError
        The first problem found, naming ``manifest.json`` or the ``.npy`` file at fault.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.root = StoreRoot.of(self.path)
        self.manifest = read_manifest(self.root)
        self.bounds = scene_fields(self.manifest, self.root.manifest)
        #: (3,) float64 world position of the store's frame: vertices, ``bounds`` and domain
        #: boxes are relative to it (zero before format version 3).
        self.origin = frame_origin(self.manifest, self.root.manifest)
        self.domains: list[DomainInfo] = [_raise_if_error(item)
                                          for item in DomainParser(self.root, self.manifest)]
        totals(self.manifest, self.domains, self.bounds, self.root.manifest)
        #: The checked ``"simplified"`` entry, or None when the store has no simplified model.
        self.simplified: SimplifiedInfo | None = simplified_entry(self.root, self.manifest,
                                                                  self.bounds)
        self._occupancy: Occupancy | None = None

    @property
    def objects(self) -> list[dict]:
        """Input objects (material slots), in the order ``objects.npy`` indexes them."""
        return self.manifest.get("objects", [])

    @property
    def has_scalars(self) -> bool:
        return bool(self.manifest.get("attributes", {}).get("scalars"))

    @property
    def has_colors(self) -> bool:
        return bool(self.manifest.get("attributes", {}).get("colors"))

    @property
    def scalar_range(self) -> tuple[float, float] | None:
        r = self.manifest.get("scalar_range")
        return None if r is None else (float(r[0]), float(r[1]))

    @property
    def scalar_name(self) -> str | None:
        """Name of the scalar field (from the input file, or the generator's field)."""
        name = self.manifest.get("scalar_name") or (self.manifest.get("generator") or {}).get(
            "scalars")
        return name if isinstance(name, str) else None

    @property
    def n_triangles(self) -> int:
        return sum(d.n_triangles for d in self.domains)

    def domain_triangles(self) -> np.ndarray:
        """(D,) int64 triangles of each domain, from the manifest (nothing is loaded)."""
        return np.array([d.n_triangles for d in self.domains], np.int64)

    @property
    def world_bounds(self) -> np.ndarray:
        """(2, 3) float64 scene bounds in world coordinates (``bounds`` + ``origin``)."""
        return self.bounds + self.origin

    def domain_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Domain boxes as arrays.

        Returns
        -------
        lo, hi : (D, 3) float64 each
        """
        if not self.domains:
            return np.zeros((0, 3)), np.zeros((0, 3))
        return np.stack([d.lo for d in self.domains]), np.stack([d.hi for d in self.domains])

    def occupancy(self) -> Occupancy | None:
        """The domains' occupancy masks for the ray-domain queries, or None: a store older
        than format version 5 (every cell occupied), or masks turned off (``VASTRAY_OCCUPANCY``
        set to 0, for measurements)."""
        if not occupancy.enabled() or all(d.occupancy is None for d in self.domains):
            return None
        if self._occupancy is None:  # built once per store (every render setup asks)
            lo, hi = self.domain_boxes()
            self._occupancy = Occupancy(lo, hi, [d.occupancy for d in self.domains])
        return self._occupancy

    def domain_path(self, info: DomainInfo, kind: str) -> Path:
        """Path of a domain's ``kind`` file, checked again to stay inside the store (a symlink
        may have changed since the store was opened)."""
        return domain_file(self.root, info.files[kind], kind, info.label)

    def load_domain(self, domain_id: int, mmap: bool = False, drop_cache: bool = False,
                    attributes: Iterable[str] | None = None) -> DomainArrays:
        """Read one domain's arrays and check them against the manifest.

        Parameters
        ----------
        domain_id : index into ``self.domains``.
        attributes : the optional arrays (``"objects"``, ``"scalars"``, ``"colors"``) to read
            besides the vertices and indices; None reads every file the domain has. A render
            reads only those it shades with: an ``rm`` store's scalars are a tenth of its
            bytes, which a render not coloured by them never needs.
        mmap : memory-map the files instead of reading them into memory (no copy, but the
            arrays change with the files: one truncated while they are in use kills the
            process with SIGBUS; the renderer never maps).
        drop_cache : after reading (``mmap=False`` only), advise the kernel to drop the files'
            pages so a later load is a real read from disk.

        Raises
        ------
        InputError
            A file missing, truncated, or whose data does not match the manifest (shape, dtype,
            an index beyond the domain's vertices, an object beyond the manifest's objects), or
            whose checksum is not the manifest's (the file changed since it was written).
        """
        return self._load(self.domains[domain_id], mmap, drop_cache, attributes)

    def load_simplified(self, mmap: bool = False, drop_cache: bool = False) -> DomainArrays:
        """Read the simplified whole-scene model and check it against its manifest entry.

        Parameters
        ----------
        mmap, drop_cache : as for :meth:`load_domain`.

        Raises
        ------
        InputError
            The store has no simplified model, or a file of it is missing, truncated or does
            not match the manifest (as for :meth:`load_domain`).
        """
        if self.simplified is None:
            raise InputError(self.root.manifest, "the store has no simplified model; build one "
                                                 "with `vastray simplify STORE --ratio R`")
        return self._load(self.simplified, mmap, drop_cache)

    def _load(self, info: DomainInfo, mmap: bool, drop_cache: bool,
              attributes: Iterable[str] | None = None) -> DomainArrays:
        arrays = dict.fromkeys(ARRAYS)
        changed = None
        wanted = None if attributes is None else {"vertices", "indices", *attributes}
        for kind in info.files:
            if wanted is not None and kind not in wanted:
                continue
            path = self.domain_path(info, kind)
            arrays[kind], why = _read_array(path, mmap, drop_cache,
                                            load_check(info.crc32, info.sha256, kind))
            if why and changed is None:
                changed = InputError(path, _changed(info, why, self.path))
        dom = DomainArrays(**arrays, origin=self.origin)
        # what the data says first (an index out of range names the problem better)
        problems = domain_problems(dom, info, self.path, len(self.objects))
        if problems:
            raise problems[0]
        if changed is not None:
            raise changed
        return dom


def _raise_if_error(item: DomainInfo | InputError) -> DomainInfo:
    if isinstance(item, InputError):
        raise item
    return item


def _changed(info: DomainInfo, why: str, store: Path) -> str:
    # short: a node's report of it is cut at 300 characters
    return (f"{info.label} changed since the store was written ({why}); `vastray verify "
            f"{store}` lists every changed file")


def _read_array(path: Path, mmap: bool, drop_cache: bool,
                check: tuple[str, str] | None) -> tuple[np.ndarray, str | None]:
    """The array in the ``.npy`` file ``path`` and how its bytes differ from the checksum
    ``check`` (None: they match, or there is none): read whole into memory and checked as
    read, or (``mmap``) mapped, the file checked through a second mapping.

    Raises
    ------
    InputError
        The file is missing, unreadable, not a ``.npy`` file, or holds more or fewer bytes
        than its header promises.
    """
    if not path.is_file():
        raise InputError(path, "domain file missing (store is incomplete; re-run partition)")
    try:
        if mmap:
            with NPY_HEADERS:  # (a mapped load reads only the header)
                arr = np.load(path, mmap_mode="r", allow_pickle=False)
            return arr, None if check is None else checksum_mismatch(_mapped(path), check)
        digest = None if check is None else RunningDigest(check[0])
        data = _read_whole(path, drop_cache, digest)
        return array_from_bytes(data), None if check is None else digest_mismatch(
            digest.hexdigest(), check)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(path, f"unreadable or truncated domain file ({one_line(exc)})") from None


#: Bytes ``_read_whole`` reads a call: each piece is checksummed while it is in the CPU's cache.
#: Against one read of the whole file and a checksum over the buffer after it, 128 KiB pieces
#: took half to three quarters of the CPU and 0.15-0.23 against 0.25-0.37 s (60 of
#: ``bench/ooc.py --large``'s domain files, 187 MB, the page cache dropped before each).
READ_PIECE = 1 << 17


def _read_whole(path: Path, drop_cache: bool, digest: RunningDigest | None = None) -> np.ndarray:
    """The bytes of ``path``, read into one writable (n,) uint8 buffer (the arrays are views of
    it; not zeroed first), fed to ``digest`` piece by piece as they are read.

    Raises
    ------
    ValueError
        The file changed size while it was read.
    """
    with open(path, "rb", buffering=0) as fh:
        size = os.fstat(fh.fileno()).st_size
        data = np.empty(size, np.uint8)
        view, done = memoryview(data), 0
        while done < size:
            n = fh.readinto(view[done:min(size, done + READ_PIECE)])
            if not n:
                raise ValueError(f"the file shrank to {done:,} bytes while it was read")
            if digest is not None:
                digest.update(view[done:done + n])
            done += n
        if fh.read(1):
            raise ValueError("the file grew while it was read")
        if drop_cache and hasattr(os, "posix_fadvise"):
            os.posix_fadvise(fh.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
    return data


def _mapped(path: Path) -> MemoryMap | bytes:
    """``path`` mapped read-only whole (closed when collected; an empty file: b"")."""
    with open(path, "rb") as fh:
        if os.fstat(fh.fileno()).st_size == 0:
            return b""
        return MemoryMap(fh.fileno(), 0, access=ACCESS_READ)


def domain_problems(dom: DomainArrays, info: DomainInfo, root: Path,
                    n_objects: int) -> list[InputError]:
    """What is wrong with a domain's data, given its manifest entry (empty when nothing).

    Checks each array's shape and dtype against the counts, then (vectorised, one pass each)
    that every triangle index is below the vertex count and every object index names one of
    the manifest's ``n_objects`` objects.

    Parameters
    ----------
    dom : the arrays as read.
    info : the domain's (checked) manifest entry.
    root : the store folder, to name the files.
    n_objects : entries in the manifest's ``objects`` (0: one default object).

    Returns
    -------
    One :class:`InputError` per problem, each naming the ``.npy`` file.
    """
    problems = []
    for kind in ARRAYS:
        arr = getattr(dom, kind)
        why = None if arr is None else mismatch(kind, info.n_triangles, info.n_vertices,
                                                arr.shape, arr.dtype)
        if why:
            problems.append(InputError(root / info.files[kind], why))
    if problems or not info.n_triangles:
        return problems
    top = int(dom.indices.max())
    if top >= info.n_vertices:
        problems.append(InputError(
            root / info.files["indices"],
            f"triangle index {top:,} is out of range: the domain has {info.n_vertices:,} "
            f"vertices (indices must be < {info.n_vertices:,}); {REWRITE}"))
    if dom.objects is not None and int(dom.objects.max()) >= max(n_objects, 1):
        problems.append(InputError(
            root / info.files["objects"],
            f"object index {int(dom.objects.max()):,} is out of range: the manifest lists "
            f"{n_objects} object(s); {REWRITE}"))
    return problems


class StoreWriter:
    """Writes a store domain by domain, so generation can stream.

    Use as a context manager; the store appears at ``path`` only when the block exits cleanly.

    Parameters
    ----------
    path : destination STORE folder (replaced if it exists and ``overwrite``).
    objects : list of ``{"name": str, ...}`` dicts, the material slots ``objects.npy`` indexes.
    overwrite : replace an existing store.
    """

    def __init__(self, path: str | os.PathLike, objects: list[dict] | None = None,
                 overwrite: bool = True, origin: np.ndarray | None = None):
        self.path = Path(path)
        #: The store frame's world position: ``origin``, else the first domain's own.
        self.origin = None if origin is None else np.asarray(origin, np.float64)
        self.objects = list(objects or [{"name": "default"}])
        self.overwrite = overwrite
        self._entries: list[dict] = []
        self._tmp: Path | None = None
        self._scalar_lo = np.inf
        self._scalar_hi = -np.inf
        self._has = {"objects": False, "scalars": False, "colors": False}
        self._max_object = -1
        self.extra: dict = {}

    def __enter__(self) -> StoreWriter:
        check_replaceable(self.path, self.overwrite)
        above = self.path.parent.absolute()
        while not above.exists() and above != above.parent:
            above = above.parent
        if not above.is_dir():
            raise InputError(self.path, f"cannot be written: {above} is not a folder")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        except OSError as exc:  # a file in the way, a read-only or virtual file system
            raise InputError(self.path, f"cannot be written here ({exc.strerror or exc}"
                                        f"{': ' + str(exc.filename) if exc.filename else ''})"
                             ) from None
        publish_mode(self._tmp, directory=True)
        return self

    def add_domain(self, dom: DomainArrays, bounds: np.ndarray | None = None) -> int:
        """Write one domain; returns its id.

        Each file is hashed (SHA-256 and CRC-32) as it is written; the digests go into the
        manifest.

        Parameters
        ----------
        dom : the domain's arrays (converted to the store dtypes here); its vertices are moved
            (in float64) from its own frame (``dom.origin``) into the store's.
        bounds : (2, 3) box in the domain's frame; defaults to the box of its triangles.

        Raises
        ------
        InputError
            More than :data:`MAX_DOMAINS` domains, a box that is not finite (NaN or infinite
            vertices), or an object index beyond ``objects``: a store that could not be read.
        """
        assert self._tmp is not None, "use StoreWriter as a context manager"
        did = len(self._entries)
        if did >= MAX_DOMAINS:
            raise InputError(None, f"a store holds at most {MAX_DOMAINS:,} domains; use a "
                                   "coarser --grid or fewer --domains")
        own = np.zeros(3) if dom.origin is None else np.asarray(dom.origin, np.float64)
        if self.origin is None:
            self.origin = own
        shift = own - self.origin
        if shift.any():
            dom = replace(dom, vertices=np.asarray(dom.vertices, np.float64) + shift)
            bounds = None if bounds is None else np.asarray(bounds, float) + shift
        arrays = _store_dtypes(dom)
        self._check_domain(did, arrays)
        box = np.asarray(bounds if bounds is not None else DomainArrays(**arrays).bounds(), float)
        if box.shape != (2, 3) or not np.isfinite(box).all() or (box[0] > box[1]).any():
            raise InputError(None, f"domain {did}: bounds {one_line(box.tolist(), 80)} are not a "
                                   "finite box with lo <= hi (NaN or infinite vertices?)")
        rel_dir = Path("domains") / f"{did:05d}"
        (self._tmp / rel_dir).mkdir(parents=True)
        files, sha256, crc32, nbytes = {}, {}, {}, 0
        for name, arr in arrays.items():
            if arr is None:
                continue
            rel = rel_dir / f"{name}.npy"
            sha256[name], crc32[name] = _save_hashed(self._tmp / rel, arr)
            files[name] = rel.as_posix()
            nbytes += arr.nbytes
            if name in self._has:
                self._has[name] = True
        if arrays["scalars"] is not None and arrays["scalars"].size:
            self._scalar_lo = min(self._scalar_lo, float(arrays["scalars"].min()))
            self._scalar_hi = max(self._scalar_hi, float(arrays["scalars"].max()))
        self._entries.append({
            "id": did,
            "bounds": box.tolist(),
            "triangles": int(arrays["indices"].shape[0]),
            "vertices": int(arrays["vertices"].shape[0]),
            "bytes": nbytes,
            "files": files,
            SHA256: sha256,
            CRC32: crc32,
            "occupancy": occupancy.encode(occupancy.of_domain(
                arrays["vertices"], arrays["indices"], box[0], box[1], nbytes)),
        })
        return did

    def _check_domain(self, did: int, arrays: dict) -> None:
        """Refuse indices a reader would refuse; note the largest object index (checked
        against ``objects`` on exit)."""
        indices, objects = arrays["indices"], arrays["objects"]
        if indices.size and int(indices.max()) >= arrays["vertices"].shape[0]:
            raise InputError(None, f"domain {did}: triangle index {int(indices.max())} is out of "
                                   f"range of its {arrays['vertices'].shape[0]} vertices")
        if objects is not None and objects.size:
            self._max_object = max(self._max_object, int(objects.max()))

    def _manifest_text(self) -> str:
        """The manifest as JSON, refused when a reader would refuse it for its size."""
        boxes = [e["bounds"] for e in self._entries if e["triangles"] > 0] or [[[0, 0, 0], [0, 0, 0]]]
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        manifest = {
            "format": FORMAT,
            "version": VERSION,
            "origin": (np.zeros(3) if self.origin is None else self.origin).tolist(),
            "bounds": [lo.tolist(), hi.tolist()],
            "objects": self.objects,
            "attributes": self._has,
            "scalar_range": (None if not np.isfinite(self._scalar_lo)
                             else [self._scalar_lo, self._scalar_hi]),
            "triangles": int(sum(e["triangles"] for e in self._entries)),
            "domains": self._entries,
            **self.extra,
        }
        text = json.dumps(manifest, indent=1)
        if len(text) > MAX_MANIFEST_BYTES:
            raise InputError(None, f"the store's manifest would be {len(text):,} bytes, more than "
                                   f"the {MAX_MANIFEST_BYTES:,} a reader accepts; use fewer domains")
        return text

    def _check_attributes(self) -> None:
        """Every non-empty domain must carry the attributes any domain carries, and object
        indices must name one of ``objects``."""
        if self._max_object >= len(self.objects):
            raise InputError(None, f"object index {self._max_object} is out of range of the "
                                   f"{len(self.objects)} object(s) given")
        for name, present in self._has.items():
            lacking = [e["id"] for e in self._entries
                       if present and e["triangles"] and name not in e["files"]]
            if lacking:
                raise InputError(None, f"domain {lacking[0]} has no {name} while others do; give "
                                       f"every domain the same attributes")

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._tmp is not None
        if exc_type is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            return
        try:
            self._check_attributes()
            (self._tmp / MANIFEST).write_text(self._manifest_text())
            check_replaceable(self.path, self.overwrite)  # it may have appeared meanwhile
        except InputError:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise
        old = None
        if self.path.exists():  # move the old store aside first: never a moment without one
            old = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.old.", dir=self.path.parent))
            os.replace(self.path, old / "store")
        os.replace(self._tmp, self.path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _store_dtypes(dom: DomainArrays) -> dict:
    """A domain's arrays as the contiguous store dtypes (None for absent attributes)."""
    def conv(arr, dtype):
        return None if arr is None else np.ascontiguousarray(arr, dtype=dtype)

    return {
        "vertices": conv(dom.vertices, np.float32),
        "indices": conv(dom.indices, np.uint32),
        "objects": conv(dom.objects, np.uint16),
        "scalars": conv(dom.scalars, np.float32),
        "colors": conv(dom.colors, np.float32),
    }


def _save_hashed(path: Path, arr: np.ndarray) -> tuple[str, str]:
    """``np.save`` ``arr`` to ``path`` and return the file's checksums (hashed as written).

    Returns
    -------
    sha256, crc32 : the hex digests, as ``checksums.digest`` gives them of the file's bytes.
    """
    with open(path, "wb") as fh:
        writer = HashingWriter(fh)
        np.save(writer, arr, allow_pickle=False)
    sums = writer.digests()
    return sums[SHA256], sums[CRC32]


def check_simplified_replaceable(store: Store, force: bool) -> None:
    """Refuse to write a simplified model into ``store`` over an existing one (its manifest
    entry, or a ``simplified`` folder left behind) unless ``force``.

    Raises
    ------
    InputError
        Naming the ``simplified`` folder.
    """
    target = store.path / SIMPLIFIED
    there = SIMPLIFIED in store.manifest or target.exists() or target.is_symlink()
    if there and not force:
        raise InputError(target, "the store already has a simplified model (pass --force to "
                                 "replace it)")


def write_simplified(store: Store, model: DomainArrays, ratio: float, min_faces: int = 0,
                     force: bool = False) -> SimplifiedInfo:
    """Add the simplified whole-scene ``model`` to an existing store (or replace it, ``force``).

    The files are written and hashed in a temporary folder inside the store, then renamed to
    ``STORE/simplified``; the manifest is replaced atomically (a temporary file renamed over
    it). When an old model is replaced, the manifest first drops its entry, so at every moment
    the manifest names either the old files, no simplified model, or the new files.

    Parameters
    ----------
    store : the open store (its manifest as read when it was opened is the one rewritten).
    model : the simplified triangles and the attributes the scene declares.
    ratio : the triangle fraction asked for, in (0, 1].
    min_faces : the floor below which object pieces were kept whole (recorded).
    force : replace an existing simplified model.

    Returns
    -------
    The new entry, checked as a reader checks it.

    Raises
    ------
    InputError
        A simplified model exists and not ``force``; the model lacks an attribute the scene
        has, names an object beyond the manifest's, has a triangle index out of range or
        non-finite vertices; or the manifest would grow too large.
    """
    check_simplified_replaceable(store, force)
    arrays = _store_dtypes(model)
    _check_simplified(store, arrays)
    n_tri = int(arrays["indices"].shape[0])
    box = DomainArrays(**arrays).bounds()
    domain_bytes = sum(d.nbytes for d in store.domains)
    root = store.path
    tmp: Path | None = Path(tempfile.mkdtemp(prefix=f".{SIMPLIFIED}.", dir=root))
    old: Path | None = None
    try:
        publish_mode(tmp, directory=True)
        files, sha256, crc32, nbytes = {}, {}, {}, 0
        for name, arr in arrays.items():
            if arr is None:
                continue
            sha256[name], crc32[name] = _save_hashed(tmp / f"{name}.npy", arr)
            files[name] = f"{SIMPLIFIED}/{name}.npy"
            nbytes += arr.nbytes
        entry = {
            "triangles": n_tri,
            "vertices": int(arrays["vertices"].shape[0]),
            "bounds": box.tolist(),
            "ratio": float(ratio),
            "min_faces": int(min_faces),
            "rate": n_tri / store.n_triangles if store.n_triangles else 0.0,
            "bytes": nbytes,
            "memory_rate": nbytes / domain_bytes if domain_bytes else 0.0,
            "files": files,
            SHA256: sha256,
            CRC32: crc32,
        }
        without = {k: v for k, v in store.manifest.items() if k != SIMPLIFIED}
        text = _manifest_json({**without, SIMPLIFIED: entry})
        if SIMPLIFIED in store.manifest:
            _replace_manifest(root, _manifest_json(without))
        target = root / SIMPLIFIED
        if target.exists() or target.is_symlink():
            old = Path(tempfile.mkdtemp(prefix=f".{SIMPLIFIED}.old.", dir=root))
            os.replace(target, old / SIMPLIFIED)
        os.replace(tmp, target)
        tmp = None
        _replace_manifest(root, text)
    finally:
        for leftover in (tmp, old):
            if leftover is not None:
                shutil.rmtree(leftover, ignore_errors=True)
    manifest = json.loads(text)
    return simplified_entry(StoreRoot.of(root), manifest, store.bounds)


def _check_simplified(store: Store, arrays: dict) -> None:
    """Refuse a simplified model a reader would refuse."""
    n_vert = arrays["vertices"].shape[0]
    indices, objects = arrays["indices"], arrays["objects"]
    if indices.size and int(indices.max()) >= n_vert:
        raise InputError(None, f"simplified model: triangle index {int(indices.max())} is out of "
                               f"range of its {n_vert} vertices")
    if objects is not None and objects.size and int(objects.max()) >= max(len(store.objects), 1):
        raise InputError(None, f"simplified model: object index {int(objects.max())} is out of "
                               f"range of the store's {len(store.objects)} object(s)")
    if not np.isfinite(arrays["vertices"]).all():
        raise InputError(None, "simplified model: vertices are NaN or infinite")
    declared = store.manifest.get("attributes", {})
    for kind in ATTRIBUTES:
        if declared.get(kind) and indices.size and arrays[kind] is None:
            raise InputError(None, f"simplified model has no {kind}, but the scene has {kind}")


def _manifest_json(manifest: dict) -> str:
    """``manifest`` as the JSON a store holds, refused when a reader would refuse its size."""
    text = json.dumps(manifest, indent=1)
    if len(text) > MAX_MANIFEST_BYTES:
        raise InputError(None, f"the store's manifest would be {len(text):,} bytes, more than "
                               f"the {MAX_MANIFEST_BYTES:,} a reader accepts")
    return text


def _replace_manifest(root: Path, text: str) -> None:
    """Write ``root``'s manifest atomically: a temporary file, synced, renamed over it."""
    fd, name = tempfile.mkstemp(prefix=f".{MANIFEST}.", dir=root)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        publish_mode(name)
        os.replace(name, root / MANIFEST)
    except BaseException:
        Path(name).unlink(missing_ok=True)
        raise


def is_store(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder holding a vastray store manifest."""
    manifest = Path(path) / MANIFEST
    if not manifest_size_ok(manifest):  # never parse an oversized file
        return False
    try:
        return json.loads(manifest.read_text()).get("format") == FORMAT
    except (OSError, ValueError, AttributeError, RecursionError):
        return False


def check_replaceable(path: str | os.PathLike, force: bool) -> None:
    """Refuse to write a store at ``path`` unless nothing is there, or ``force`` is given and
    what is there is a vastray store (or an empty folder): ``--force`` never deletes a user's
    other files.

    Raises
    ------
    InputError
        Naming the path and why it is kept.
    """
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    if path.is_symlink() or not path.is_dir():
        raise InputError(path, "exists and is not a folder; give another STORE path "
                               "(--force replaces only vastray stores)")
    if is_store(path) or not any(path.iterdir()):
        if not force:
            raise InputError(path, "already exists (pass --force to replace it)")
        foreign = sorted(p.name for p in path.iterdir() if p.name not in _STORE_ENTRIES
                         and not p.name.startswith(_STORE_TEMPORARIES))
        if foreign:
            raise InputError(path, f"holds {foreign[0]!r}, which is not part of the store "
                                   f"({len(foreign)} such entr{'y' if len(foreign) == 1 else 'ies'}"
                                   "): replacing the store would delete it; move it out first")
        here = Path.cwd().resolve()
        if here == path.resolve() or path.resolve() in here.parents:
            raise InputError(path, "is the current folder or holds it: a store cannot be "
                                   "replaced from inside; cd out of it first")
        return
    raise InputError(path, "exists and is not a vastray store (no manifest.json of one); "
                           "refusing to replace it, even with --force")


#: What a store folder holds (its manifest, its domains, its simplified model): ``--force``
#: replaces a store only when nothing else is in it.
_STORE_ENTRIES = frozenset({MANIFEST, "domains", SIMPLIFIED})
#: The temporaries a killed write leaves in a store (``write_simplified``, the manifest's).
_STORE_TEMPORARIES = (f".{SIMPLIFIED}.", f".{MANIFEST}.")
