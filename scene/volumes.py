"""Volume file readers that memory-map (or lazily proxy) the voxels instead of loading them.

Every reader returns a :class:`Volume` whose ``data`` is indexed ``[x, y, z]`` and supports basic
slicing, so :func:`vastray.scene.isosurface.iter_brick_triangles` reads one brick at a time.

Formats
-------
``.npy``
    A 3-D numeric array, axes (x, y, z); spacing 1, origin 0.
``.raw`` + ``.json`` header
    ``X.raw`` with ``X.json`` beside it, or ``X.json`` naming its raw file. JSON keys:

    - ``shape``: [nx, ny, nz] voxels (required)
    - ``dtype``: numpy dtype string with byte order, e.g. ``"uint8"``, ``"<u2"``, ``">f4"``
      (required)
    - ``spacing``: [sx, sy, sz] world size of a voxel step (default [1, 1, 1])
    - ``origin``: [ox, oy, oz] world position of voxel (0, 0, 0) (default [0, 0, 0])
    - ``order``: ``"F"`` = x varies fastest in the file (default; the usual layout of raw
      volume dumps, VTK and NIfTI) or ``"C"`` = z varies fastest (``array.tofile()`` of an
      array indexed [x, y, z])
    - ``file``: raw file name relative to the JSON file (default: the JSON's stem + ``.raw``)
    - ``offset``: bytes to skip at the start of the raw file (default 0)
``.nii`` / ``.nii.gz``
    NIfTI-1/2 through nibabel (``pip install vastray[nifti]``); spacing from the header's voxel
    sizes, origin from the affine's translation (rotations/flips in the affine are ignored).
``.vtk``
    Legacy VTK ``STRUCTURED_POINTS`` in BINARY (big-endian) form, first ``SCALARS`` array,
    one component; ``SPACING`` or (version 1) ``ASPECT_RATIO``, and ``ORIGIN``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vastray.scene.errors import InputError
from vastray.scene.manifest import NPY_HEADERS

VOLUME_SUFFIXES = (".npy", ".raw", ".json", ".nii", ".nii.gz", ".vtk")


@dataclass
class Volume:
    """A scalar volume on a regular grid.

    Attributes
    ----------
    data : array-like (nx, ny, nz), indexed [x, y, z]; a memmap or lazy proxy.
    spacing : (3,) float64 world size of one voxel step.
    origin : (3,) float64 world position of voxel (0, 0, 0).
    path : the file it came from (for error messages).
    """

    data: object
    spacing: np.ndarray
    origin: np.ndarray
    path: Path

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape)


def volume_suffix(path: str | os.PathLike) -> str | None:
    """The volume format suffix of ``path`` (``".nii.gz"`` counts as one), or None."""
    name = Path(path).name.lower()
    for suffix in sorted(VOLUME_SUFFIXES, key=len, reverse=True):
        if name.endswith(suffix):
            return suffix
    return None


def read_volume(path: str | os.PathLike) -> Volume:
    """Open a volume file without reading its voxels.

    Parameters
    ----------
    path : a ``.npy``, ``.raw``/``.json``, ``.nii``/``.nii.gz`` or legacy ``.vtk`` file.

    Raises
    ------
    InputError : missing, unsupported, malformed or truncated file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    suffix = volume_suffix(path)
    readers = {".npy": _read_npy, ".raw": _read_raw, ".json": _read_raw,
               ".nii": _read_nifti, ".nii.gz": _read_nifti, ".vtk": _read_vtk}
    if suffix not in readers:
        raise InputError(path, f"not a volume file (supported: {', '.join(VOLUME_SUFFIXES)})")
    vol = readers[suffix](path)
    _check_shape(vol)
    return vol


def _check_shape(vol: Volume) -> None:
    shape = vol.data.shape
    if len(shape) != 3:
        raise InputError(vol.path, f"a volume must be 3-D, found shape {tuple(shape)}")
    if min(shape) < 2:
        raise InputError(vol.path, f"a volume needs at least 2 voxels per axis, found {shape}")
    dtype = np.dtype(getattr(vol.data, "dtype", np.float32))
    if dtype.kind not in "biuf":
        raise InputError(vol.path, f"voxel type {dtype} is not a real number type")


def _unit() -> tuple[np.ndarray, np.ndarray]:
    return np.ones(3), np.zeros(3)


def _read_npy(path: Path) -> Volume:
    try:
        with NPY_HEADERS:
            data = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(path, f"unreadable or truncated .npy file ({exc})") from None
    return Volume(data, *_unit(), path)


def _read_raw(path: Path) -> Volume:
    header = path if path.suffix.lower() == ".json" else path.with_suffix(".json")
    if not header.is_file():
        raise InputError(path, f"a raw volume needs a JSON header beside it ({header.name}, "
                               "keys: shape, dtype, spacing, origin, optional order/file/offset)")
    try:
        meta = json.loads(header.read_text())
        shape = tuple(int(n) for n in meta["shape"])
        dtype = np.dtype(meta["dtype"])
        spacing = np.asarray(meta.get("spacing", [1, 1, 1]), dtype=np.float64).reshape(3)
        origin = np.asarray(meta.get("origin", [0, 0, 0]), dtype=np.float64).reshape(3)
        order = str(meta.get("order", "F")).upper()
        offset = int(meta.get("offset", 0))
        raw = header.parent / meta.get("file", header.stem + ".raw")
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(header, f"malformed raw-volume header ({exc!r}); needs shape [nx, ny, "
                                 "nz] and dtype, optional spacing, origin, order, file, offset") from None
    if order not in ("C", "F") or len(shape) != 3:
        raise InputError(header, "order must be \"F\" or \"C\" and shape must have 3 entries")
    if not raw.is_file():
        raise InputError(raw, f"raw voxel file named by {header.name} is missing")
    need = offset + int(np.prod(shape)) * dtype.itemsize
    if raw.stat().st_size < need:
        raise InputError(raw, f"truncated: {raw.stat().st_size} bytes, header says {need}")
    data = np.memmap(raw, dtype=dtype, mode="r", offset=offset, shape=shape, order=order)
    return Volume(data, spacing, origin, raw)


class _Squeezed:
    """A 4-D (x, y, z, 1) proxy seen as 3-D."""

    def __init__(self, proxy):
        self.proxy = proxy
        self.shape = tuple(proxy.shape[:3])
        self.dtype = proxy.dtype

    def __getitem__(self, key):
        return np.asarray(self.proxy[(*key, 0)])


def _read_nifti(path: Path) -> Volume:
    try:
        import nibabel
    except ImportError:
        raise InputError(path, "reading NIfTI needs nibabel: pip install vastray[nifti]") from None
    try:
        img = nibabel.load(str(path))
        proxy = img.dataobj
        zooms = img.header.get_zooms()
    except Exception as exc:  # nibabel raises many types for bad files
        raise InputError(path, f"unreadable NIfTI file ({exc})") from None
    if len(proxy.shape) == 4 and proxy.shape[3] == 1:
        proxy = _Squeezed(proxy)
    spacing = np.asarray(zooms[:3], dtype=np.float64)
    origin = np.asarray(img.affine[:3, 3], dtype=np.float64)
    return Volume(proxy, spacing, origin, path)


_VTK_TYPES = {
    "bit": None, "unsigned_char": "u1", "char": "i1", "unsigned_short": ">u2", "short": ">i2",
    "unsigned_int": ">u4", "int": ">i4", "unsigned_long": ">u8", "long": ">i8",
    "float": ">f4", "double": ">f8", "vtktypeint8": "i1", "vtktypeuint8": "u1",
    "vtktypeint16": ">i2", "vtktypeuint16": ">u2", "vtktypeint32": ">i4",
    "vtktypeuint32": ">u4", "vtktypeint64": ">i8", "vtktypeuint64": ">u8",
}


def _read_vtk(path: Path) -> Volume:
    fields: dict[str, list[str]] = {}
    with open(path, "rb") as fh:
        first = fh.readline()
        if not first.startswith(b"# vtk DataFile"):
            raise InputError(path, "not a legacy VTK file (first line must be '# vtk DataFile')")
        fh.readline()  # title
        for _ in range(64):
            line = fh.readline()
            if not line:
                raise InputError(path, "truncated legacy VTK header")
            words = line.decode("ascii", errors="replace").split()
            if not words:
                continue
            key = words[0].upper()
            fields[key] = words[1:]
            if key == "ASCII":
                raise InputError(path, "ASCII legacy VTK is not supported; save it as BINARY")
            if key == "SCALARS":
                pos = fh.tell()
                nxt = fh.readline()
                if not nxt.upper().startswith(b"LOOKUP_TABLE"):
                    fh.seek(pos)
                offset = fh.tell()
                break
        else:
            raise InputError(path, "no SCALARS array found in the legacy VTK header")
    try:
        if fields.get("DATASET", [""])[0].upper() != "STRUCTURED_POINTS":
            raise InputError(path, "only DATASET STRUCTURED_POINTS legacy VTK files are "
                                   f"supported, found {' '.join(fields.get('DATASET', ['?']))}")
        nx, ny, nz = (int(w) for w in fields["DIMENSIONS"][:3])
        spacing = np.asarray(fields.get("SPACING", fields.get("ASPECT_RATIO", [1, 1, 1]))[:3],
                             dtype=np.float64)
        origin = np.asarray(fields.get("ORIGIN", [0, 0, 0])[:3], dtype=np.float64)
        scalars = fields["SCALARS"]
        type_name = scalars[1].lower()
        n_comp = int(scalars[2]) if len(scalars) > 2 else 1
    except (KeyError, IndexError, ValueError) as exc:
        raise InputError(path, f"malformed legacy VTK header ({exc!r})") from None
    dtype = _VTK_TYPES.get(type_name)
    if dtype is None:
        raise InputError(path, f"unsupported VTK scalar type {type_name!r}")
    if n_comp != 1:
        raise InputError(path, f"the first SCALARS array has {n_comp} components; need 1")
    need = offset + nx * ny * nz * np.dtype(dtype).itemsize
    if path.stat().st_size < need:
        raise InputError(path, f"truncated: {path.stat().st_size} bytes, header says {need}")
    raw = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(nz, ny, nx))
    return Volume(raw.transpose(2, 1, 0), spacing, origin, path)
