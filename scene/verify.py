"""Checking a whole store, as ``vastray verify`` does: every problem, not just the first.

Opening a :class:`~vastray.scene.store.Store` stops at the first problem and reads only the
manifest and the ``.npy`` headers. :func:`verify_store` goes on past each problem and reads
every file once, so it also checks what needs the data:

* each file's SHA-256 against the manifest (stores of format version 2 and later), and its
  CRC-32, the checksum every load checks (version 4 and later);
* the file holds exactly the bytes its header promises (not truncated, nothing appended);
* every triangle index is below the domain's vertex count, every object index names an object;
* vertices, scalars and colours are finite, and the vertices the triangles use lie inside the
  domain's box (a ray skips a domain whose box misses its triangles);
* each domain's occupancy mask (format version 5 and later) is the one its triangles give:
  recomputed and compared, a cell holding a triangle but marked empty (rays would skip it: the
  mask is not conservative) and a cell marked occupied that holds none are both reported.

The simplified whole-scene model, when the manifest has one, gets the same checks as a domain
(its box must also lie inside the scene bounds).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vastray.scene import occupancy
from vastray.scene.checksums import CRC32, SHA256, checksum_mismatch
from vastray.scene.errors import InputError
from vastray.scene.manifest import (
    ARRAYS,
    MANIFEST,
    MAX_DOMAINS,
    REWRITE,
    DomainInfo,
    DomainParser,
    StoreRoot,
    array_from_bytes,
    domain_file,
    parse_npy_header,
    read_manifest,
    scene_fields,
    simplified_entry,
    totals,
)
from vastray.scene.progressbar import Bar
from vastray.scene.store import DomainArrays, domain_problems


@dataclass
class VerifyResult:
    """What :func:`verify_store` found.

    Attributes
    ----------
    store : the store folder.
    domains : entries in the manifest.
    checked : domains whose data was read and checked.
    triangles : triangles in the checked domains.
    files : array files read.
    checksummed : the store records checksums (format version 2 and later).
    simplified : triangles of the simplified model checked, None when the store has none.
    problems : every problem, each naming its file.
    """

    store: Path
    domains: int = 0
    checked: int = 0
    triangles: int = 0
    files: int = 0
    checksummed: bool = False
    simplified: int | None = None
    problems: list[InputError] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        """One line: the verdict and what was checked."""
        sums = ("checksums checked" if self.checksummed
                else "a version 1 store has no checksums; rewrite it to add them")
        simplified = ("" if self.simplified is None
                      else f", a simplified model of {self.simplified:,} triangles")
        what = (f"{self.domains:,} domains, {self.triangles:,} triangles{simplified}, "
                f"{self.files:,} files, {sums}")
        if self.ok:
            return f"{self.store}: OK: {what}"
        n = len(self.problems)
        return (f"{self.store}: {n} problem{'s' if n != 1 else ''}: fix the files named above or "
                f"{REWRITE} ({what})")


def verify_store(path: str | Path, progress: bool = False,
                 report: Callable[[InputError], None] | None = None) -> VerifyResult:
    """Check a store's manifest and read every domain once, collecting every problem.

    Parameters
    ----------
    path : the STORE folder.
    progress : show a progress bar over the domains (after a second).
    report : called with each problem as soon as it is found (e.g. to print it).

    Returns
    -------
    VerifyResult, whose ``problems`` is empty when the store is sound.

    Raises
    ------
    InputError
        When the manifest cannot be read at all (missing, too large, not JSON, not a store).
    """
    root = StoreRoot.of(path)
    manifest = read_manifest(root)
    result = VerifyResult(store=root.path, checksummed=manifest["version"] >= 2)

    def found(problem: InputError) -> None:
        result.problems.append(problem)
        if report is not None:
            report(problem)

    try:
        bounds = scene_fields(manifest, root.manifest)
    except InputError as exc:
        found(exc)
        bounds = None
        if not _domains_listed(manifest):
            return result
    result.domains = len(manifest["domains"])
    objects = manifest.get("objects")
    n_objects = len(objects) if isinstance(objects, list) else 0
    infos = []
    entries = DomainParser(root, manifest)
    for item in Bar(entries, total=result.domains, desc="verify", unit="domain", delay=1.0,
                     disable=not progress, leave=False):
        if isinstance(item, InputError):
            found(item)
            continue
        infos.append(item)
        for problem in check_domain_data(root, item, n_objects):
            found(problem)
        result.checked += 1
        result.triangles += item.n_triangles
        result.files += len(item.files)
    if bounds is not None and len(infos) == result.domains:
        try:
            totals(manifest, infos, bounds, root.manifest)
        except InputError as exc:
            found(exc)
    _verify_simplified(root, manifest, bounds, n_objects, result, found)
    return result


def _verify_simplified(root: StoreRoot, manifest: dict, bounds, n_objects: int,
                       result: VerifyResult, found: Callable[[InputError], None]) -> None:
    """Check the simplified model's entry and data like a domain's (nothing when absent)."""
    try:
        info = simplified_entry(root, manifest, bounds)
    except InputError as exc:
        found(exc)
        return
    if info is None:
        return
    for problem in check_domain_data(root, info, n_objects):
        found(problem)
    result.simplified = info.n_triangles
    result.files += len(info.files)


def _domains_listed(manifest: dict) -> bool:
    domains = manifest.get("domains")
    return isinstance(domains, list) and len(domains) <= MAX_DOMAINS


def check_domain_data(root: StoreRoot, info: DomainInfo, n_objects: int) -> list[InputError]:
    """Read a domain's files once and check their checksums and data.

    Parameters
    ----------
    root : the store.
    info : the domain's checked manifest entry (headers already match the counts).
    n_objects : entries in the manifest's ``objects``.

    Returns
    -------
    Every problem found, each naming the ``.npy`` file.
    """
    arrays = dict.fromkeys(ARRAYS)
    problems = []
    unreadable = False
    for kind, rel in info.files.items():
        try:
            path = domain_file(root, rel, kind, info.label)
            mismatch = _size_mismatch(path)
            if mismatch:  # found without reading a file of any size into memory
                raise InputError(path, f"unreadable or truncated domain file ({mismatch}); "
                                       f"{REWRITE}")
            data = path.read_bytes()
        except InputError as exc:
            problems.append(exc)
            unreadable = True
            continue
        except OSError as exc:
            problems.append(InputError(root.path / rel, f"cannot be read ({exc.strerror})"))
            unreadable = True
            continue
        problems += _checksum_problems(path, data, info, kind)
        try:
            arrays[kind] = array_from_bytes(data)
        except ValueError as exc:
            problems.append(InputError(path, f"unreadable or truncated domain file ({exc}); "
                                             f"{REWRITE}"))
            unreadable = True
    if unreadable:
        return problems
    dom = DomainArrays(**arrays)
    shape_problems = domain_problems(dom, info, root.path, n_objects)
    if shape_problems:
        return problems + shape_problems
    values = value_problems(dom, info, root.path)
    if problems or values:  # (a changed file's mask differs as a consequence: not reported)
        return problems + values
    return occupancy_problems(dom, info, root.path)


def _size_mismatch(path: Path) -> str | None:
    """How the size of the ``.npy`` file at ``path`` differs from what its header promises,
    or None (also where the header cannot be read: the whole read then says why)."""
    try:
        with open(path, "rb") as fh:
            header = parse_npy_header(fh)
            size = os.fstat(fh.fileno()).st_size
    except (OSError, ValueError):
        return None
    expected = header.offset + int(np.prod(header.shape)) * header.dtype.itemsize
    if size == expected:
        return None
    return f"{size:,} bytes where its header promises {expected:,}"


def occupancy_problems(dom: DomainArrays, info: DomainInfo, root: Path) -> list[InputError]:
    """How a domain's occupancy mask differs from the one its triangles give (nothing for a
    store without masks).

    Parameters
    ----------
    dom : the domain's arrays (checked: finite, inside the box).
    info : its manifest entry.
    root : the store folder, to name the manifest.
    """
    if info.occupancy is None:
        return []
    stored = info.occupancy
    truth = occupancy.compute(dom.vertices, dom.indices, info.lo, info.hi, stored.shape)
    missing = int(np.count_nonzero(truth & ~stored))
    extra = int(np.count_nonzero(stored & ~truth))
    problems = []
    grid = "x".join(map(str, stored.shape))
    if missing:
        problems.append(InputError(
            root / MANIFEST,
            f"{info.label} occupancy mask is not conservative: {missing:,} of its {grid} cells "
            f"hold triangles but are marked empty (rays would skip them); {REWRITE}"))
    if extra:
        problems.append(InputError(
            root / MANIFEST,
            f"{info.label} occupancy mask does not match its triangles: {extra:,} of its {grid} "
            f"cells are marked occupied but hold none; {REWRITE}"))
    return problems


def _checksum_problems(path: Path, data: bytes, info: DomainInfo, kind: str) -> list[InputError]:
    """The SHA-256 mismatch of the ``kind`` file, else its CRC-32's (one problem at most)."""
    for algorithm, sums in ((SHA256, info.sha256), (CRC32, info.crc32)):
        why = checksum_mismatch(data, (algorithm, sums[kind]) if kind in sums else None)
        if why:
            return [InputError(path, f"checksum mismatch: {why}; the file changed after the "
                                     f"store was written: restore it or {REWRITE}")]
    return []


def value_problems(dom: DomainArrays, info: DomainInfo, root: Path) -> list[InputError]:
    """Non-finite values, and vertices in use outside the domain's box.

    Parameters
    ----------
    dom : the domain's arrays (shapes, dtypes and index ranges already checked).
    info : its manifest entry.
    root : the store folder, to name the files.
    """
    problems = []
    for kind in ("vertices", "scalars", "colors"):
        arr = getattr(dom, kind)
        if arr is not None and arr.size and not np.isfinite(arr).all():
            bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=-1) if arr.ndim > 1
                                       else ~np.isfinite(arr)))
            problems.append(InputError(root / info.files[kind],
                                       f"{bad:,} {kind} entries are NaN or infinite; {REWRITE}"))
    if problems or not info.n_triangles:
        return problems
    used = np.zeros(info.n_vertices, dtype=bool)
    used[dom.indices.ravel()] = True
    points = dom.vertices[used]
    slack = 1e-6 * max(1.0, float(np.abs(np.concatenate([info.lo, info.hi])).max()))
    outside = ((points < info.lo - slack) | (points > info.hi + slack)).any(axis=1)
    if outside.any():
        problems.append(InputError(
            root / info.files["vertices"],
            f"{int(outside.sum()):,} vertices used by triangles lie outside the domain's bounds "
            f"in the manifest (rays would miss them); {REWRITE}"))
    return problems
