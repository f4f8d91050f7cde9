"""The on-disk domain store: a versioned JSON manifest plus one set of ``.npy`` files per domain.

Layout of a STORE folder::

    STORE/manifest.json
    STORE/domains/00000/vertices.npy   (V, 3) float32
    STORE/domains/00000/indices.npy    (T, 3) uint32, indices into this domain's vertices
    STORE/domains/00000/objects.npy    (T,)   uint16, index into manifest["objects"]   [optional]
    STORE/domains/00000/scalars.npy    (V,)   float32 per-vertex scalar field           [optional]
    STORE/domains/00000/colors.npy     (V, 3) float32 per-vertex linear RGB in [0, 1]   [optional]

Every file loads with ``np.load(path, mmap_mode="r")``. A store is written into a temporary
folder and renamed into place when complete, so a failed run never leaves a partial store.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vastray.scene.errors import InputError
from vastray.scene.filemode import publish_mode

FORMAT = "vastray-store"
VERSION = 1
MANIFEST = "manifest.json"
ATTRIBUTES = ("objects", "scalars", "colors")


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
    """

    vertices: np.ndarray
    indices: np.ndarray
    objects: np.ndarray | None = None
    scalars: np.ndarray | None = None
    colors: np.ndarray | None = None

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


@dataclass(frozen=True)
class DomainInfo:
    """A domain's manifest entry: id, box (may overlap neighbours), counts and files."""

    id: int
    lo: np.ndarray  # (3,) float64
    hi: np.ndarray  # (3,) float64
    n_triangles: int
    n_vertices: int
    nbytes: int
    files: dict = field(hash=False)


class Store:
    """A read-only view of a STORE folder; loads domains on demand.

    Parameters
    ----------
    path : path to the STORE folder.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        manifest_path = self.path / MANIFEST
        if not self.path.exists():
            raise InputError(self.path, "no such store (run `vastray partition` or `vastray generate`)")
        if not manifest_path.is_file():
            raise InputError(manifest_path, "missing manifest; is this a vastray store?")
        try:
            self.manifest = json.loads(manifest_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(manifest_path, f"not valid JSON ({exc})") from None
        if self.manifest.get("format") != FORMAT:
            raise InputError(manifest_path, f"not a {FORMAT} manifest")
        if self.manifest.get("version") != VERSION:
            raise InputError(
                manifest_path,
                f"store format version {self.manifest.get('version')} is not supported "
                f"(this vastray reads version {VERSION}); re-run `vastray partition`",
            )
        try:
            self.domains = [
                DomainInfo(
                    id=int(d["id"]),
                    lo=np.asarray(d["bounds"][0], dtype=np.float64),
                    hi=np.asarray(d["bounds"][1], dtype=np.float64),
                    n_triangles=int(d["triangles"]),
                    n_vertices=int(d["vertices"]),
                    nbytes=int(d["bytes"]),
                    files=dict(d["files"]),
                )
                for d in self.manifest["domains"]
            ]
            self.bounds = np.asarray(self.manifest["bounds"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(manifest_path, f"malformed manifest entry ({exc!r})") from None
        if [d.id for d in self.domains] != list(range(len(self.domains))):
            raise InputError(manifest_path, "domain ids must be 0..N-1 in order")

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
    def n_triangles(self) -> int:
        return sum(d.n_triangles for d in self.domains)

    def domain_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Domain boxes as arrays.

        Returns
        -------
        lo, hi : (D, 3) float64 each
        """
        if not self.domains:
            return np.zeros((0, 3)), np.zeros((0, 3))
        return np.stack([d.lo for d in self.domains]), np.stack([d.hi for d in self.domains])

    def load_domain(self, domain_id: int, mmap: bool = True, drop_cache: bool = False) -> DomainArrays:
        """Read one domain's arrays and check them against the manifest.

        Parameters
        ----------
        domain_id : index into ``self.domains``.
        mmap : memory-map the files instead of reading them.
        drop_cache : after reading (``mmap=False`` only), advise the kernel to drop the files'
            pages so a later load is a real read from disk.
        """
        info = self.domains[domain_id]
        arrays = {}
        for name in ("vertices", "indices", *ATTRIBUTES):
            rel = info.files.get(name)
            if rel is None:
                arrays[name] = None
                continue
            arrays[name] = _read_array(self.path / rel, mmap=mmap, drop_cache=drop_cache)
        if arrays["vertices"] is None or arrays["indices"] is None:
            raise InputError(self.path / MANIFEST, f"domain {domain_id} lists no vertices/indices file")
        dom = DomainArrays(**arrays)
        _check_domain(dom, info, self.path)
        return dom


def _read_array(path: Path, mmap: bool, drop_cache: bool) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "domain file missing (store is incomplete; re-run partition)")
    try:
        if mmap:
            return np.load(path, mmap_mode="r", allow_pickle=False)
        with open(path, "rb") as fh:
            arr = np.load(fh, allow_pickle=False)
            if drop_cache and hasattr(os, "posix_fadvise"):
                os.posix_fadvise(fh.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
        return arr
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(path, f"unreadable or truncated domain file ({exc})") from None


def _check_domain(dom: DomainArrays, info: DomainInfo, root: Path) -> None:
    where = root / info.files["indices"]
    expect = {
        "vertices": ((info.n_vertices, 3), np.float32),
        "indices": ((info.n_triangles, 3), np.uint32),
        "objects": ((info.n_triangles,), np.uint16),
        "scalars": ((info.n_vertices,), np.float32),
        "colors": ((info.n_vertices, 3), np.float32),
    }
    for name, (shape, dtype) in expect.items():
        arr = getattr(dom, name)
        if arr is None:
            continue
        if arr.shape != shape or arr.dtype != dtype:
            raise InputError(
                root / info.files[name],
                f"does not match the manifest: expected {shape} {np.dtype(dtype)}, "
                f"found {arr.shape} {arr.dtype}",
            )
    if info.n_triangles and info.n_vertices and int(np.max(dom.indices)) >= info.n_vertices:
        raise InputError(where, "triangle index out of range of the domain's vertices")


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
                 overwrite: bool = True):
        self.path = Path(path)
        self.objects = list(objects or [{"name": "default"}])
        self.overwrite = overwrite
        self._entries: list[dict] = []
        self._tmp: Path | None = None
        self._scalar_lo = np.inf
        self._scalar_hi = -np.inf
        self._has = {"objects": False, "scalars": False, "colors": False}
        self.extra: dict = {}

    def __enter__(self) -> StoreWriter:
        check_replaceable(self.path, self.overwrite)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        publish_mode(self._tmp, directory=True)
        return self

    def add_domain(self, dom: DomainArrays, bounds: np.ndarray | None = None) -> int:
        """Write one domain; returns its id.

        Parameters
        ----------
        dom : the domain's arrays (converted to the store dtypes here).
        bounds : (2, 3) box; defaults to the box of the domain's triangles.
        """
        assert self._tmp is not None, "use StoreWriter as a context manager"
        did = len(self._entries)
        rel_dir = Path("domains") / f"{did:05d}"
        (self._tmp / rel_dir).mkdir(parents=True)
        arrays = {
            "vertices": np.ascontiguousarray(dom.vertices, dtype=np.float32),
            "indices": np.ascontiguousarray(dom.indices, dtype=np.uint32),
            "objects": None if dom.objects is None else np.ascontiguousarray(dom.objects, np.uint16),
            "scalars": None if dom.scalars is None else np.ascontiguousarray(dom.scalars, np.float32),
            "colors": None if dom.colors is None else np.ascontiguousarray(dom.colors, np.float32),
        }
        files = {}
        nbytes = 0
        for name, arr in arrays.items():
            if arr is None:
                continue
            rel = rel_dir / f"{name}.npy"
            np.save(self._tmp / rel, arr, allow_pickle=False)
            files[name] = rel.as_posix()
            nbytes += arr.nbytes
            if name in self._has:
                self._has[name] = True
        if arrays["scalars"] is not None and arrays["scalars"].size:
            self._scalar_lo = min(self._scalar_lo, float(arrays["scalars"].min()))
            self._scalar_hi = max(self._scalar_hi, float(arrays["scalars"].max()))
        box = np.asarray(bounds if bounds is not None else DomainArrays(**arrays).bounds(), float)
        self._entries.append({
            "id": did,
            "bounds": box.tolist(),
            "triangles": int(arrays["indices"].shape[0]),
            "vertices": int(arrays["vertices"].shape[0]),
            "bytes": nbytes,
            "files": files,
        })
        return did

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._tmp is not None
        if exc_type is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            return
        boxes = [e["bounds"] for e in self._entries if e["triangles"] > 0] or [[[0, 0, 0], [0, 0, 0]]]
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        manifest = {
            "format": FORMAT,
            "version": VERSION,
            "bounds": [lo.tolist(), hi.tolist()],
            "objects": self.objects,
            "attributes": self._has,
            "scalar_range": (None if not np.isfinite(self._scalar_lo)
                             else [self._scalar_lo, self._scalar_hi]),
            "triangles": int(sum(e["triangles"] for e in self._entries)),
            "domains": self._entries,
            **self.extra,
        }
        (self._tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
        try:
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


def is_store(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder holding a vastray store manifest."""
    manifest = Path(path) / MANIFEST
    try:
        return json.loads(manifest.read_text()).get("format") == FORMAT
    except (OSError, ValueError, AttributeError):
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
        return
    raise InputError(path, "exists and is not a vastray store (no manifest.json of one); "
                           "refusing to replace it, even with --force")
