"""VTK XML files (``.vti .vtr .vts .vtu .vtp`` and their parallel ``.pvt*`` forms) read through
the ``vtk`` wheel (``pip install vastray[vtk]``).

Why ``vtk`` and not ``meshio``: meshio (a 166 KB wheel) reads only ``.vtu`` of the VTK XML
formats; the ``vtk`` wheel (about 140 MB to download, 565 MB installed) reads every one of
them, every encoding (ASCII, base64, raw appended, zlib/lz4/lzma compressed) and every cell
type, and turns volumetric cells into their boundary surface. So it is an optional extra,
imported only when such a file is read.

What each format becomes
------------------------
``.vti`` / ``.vtr`` / ``.vts`` (image, rectilinear and curvilinear grids)
    A volume: the array chosen (``array``, default the first one-component point array, else
    the first cell array) is isosurfaced at ``iso`` in index space, brick by brick, and the
    vertices are mapped to the grid's world positions (origin, spacing and direction; the
    rectilinear axes; the curvilinear node positions, trilinearly). Cell arrays are averaged
    to the nodes first (VTK's ``vtkCellDataToPointData``, as ParaView contours them). With
    ``color_by``, that array is sampled at the surface's vertices and kept as its scalars.
``.vtu`` / ``.vtp`` (unstructured grid, poly data)
    A mesh: the boundary surface of the cells (``vtkDataSetSurfaceFilter``: triangles and
    polygons as they are, 3-D cells by their outer faces), triangulated; lines and vertices are
    left out. A point array is kept as per-vertex scalars; a cell array is kept exactly per
    triangle, by giving every triangle its own three vertices.
``.pvt*``
    Each piece file the parallel file names is read as above, into one :class:`Piece`.

Arrays with several components (vectors) are used by their magnitude.
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vastray.scene.errors import InputError
from vastray.scene.isosurface import DEFAULT_BRICK, iter_brick_triangles
from vastray.scene.store import DomainArrays, relative_to

log = logging.getLogger(__name__)

#: VTK XML type of each serial suffix
SERIAL = {".vti": "ImageData", ".vtr": "RectilinearGrid", ".vts": "StructuredGrid",
          ".vtu": "UnstructuredGrid", ".vtp": "PolyData"}
PARALLEL = {".p" + s[1:]: s for s in SERIAL}  # ".pvtu" -> ".vtu"
SUFFIXES = tuple(SERIAL) + tuple(PARALLEL)
STRUCTURED = (".vti", ".vtr", ".vts")

INSTALL = "reading VTK XML files needs the vtk package: pip install 'vastray[vtk]'"


@dataclass
class Piece:
    """Triangles read from one (piece) file, with the name of the array kept as scalars."""

    mesh: DomainArrays
    scalar_name: str | None
    source: Path


def vtk_xml_suffix(path: str | os.PathLike) -> str | None:
    """The VTK XML suffix of ``path`` (``".vtu"``, ``".pvti"``, ...), or None."""
    suffix = Path(path).suffix.lower()
    return suffix if suffix in SUFFIXES else None


def is_parallel(path: str | os.PathLike) -> bool:
    """True for a parallel VTK XML file (``.pvti``, ``.pvtu``, ...): a list of piece files."""
    return vtk_xml_suffix(path) in PARALLEL


def is_structured(path: str | os.PathLike) -> bool:
    """True for VTK XML grids (``.vti .vtr .vts`` and parallel forms): volumes needing --iso."""
    suffix = vtk_xml_suffix(path)
    return PARALLEL.get(suffix, suffix) in STRUCTURED


def piece_files(path: str | os.PathLike) -> list[Path]:
    """The piece files a parallel VTK XML file names (``<Piece Source=...>``), in order.

    Raises
    ------
    InputError : unreadable XML, no pieces, or a piece file missing.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not a readable parallel VTK XML file ({exc})") from None
    want = "P" + SERIAL[PARALLEL[path.suffix.lower()]]
    if root.tag != "VTKFile" or root.get("type") != want:
        raise InputError(path, f"not a parallel VTK XML {want} file (found <{root.tag} "
                               f"type={root.get('type')!r}>)")
    sources = [p.get("Source") for p in root.iter("Piece")]
    if not sources or any(not s for s in sources):
        raise InputError(path, "names no piece files (<Piece Source=...>)")
    pieces = [path.parent / s for s in sources]
    for piece in pieces:
        if not piece.is_file():
            raise InputError(piece, f"piece file named by {path.name} is missing")
    return pieces


def read_vtk_xml(path: str | os.PathLike, iso: float | None = None, array: str | None = None,
                 color_by: str | None = None, brick: int = DEFAULT_BRICK,
                 progress: bool = False) -> list[Piece]:
    """Read a VTK XML file into triangles: one :class:`Piece` per piece file.

    Parameters
    ----------
    path : a ``.vti .vtr .vts .vtu .vtp`` file or a parallel ``.pvt*`` file.
    iso : the iso value; required for grids (``.vti .vtr .vts``), ignored otherwise.
    array : grids: the array isosurfaced; meshes: the array kept as scalars (default: the
        first one-component point array, else the first cell array).
    color_by : grids only: the array sampled at the isosurface's vertices as their scalars.
    brick : most cells per marching-cubes brick edge.
    progress : tqdm bar while isosurfacing.

    Returns
    -------
    list of Piece; a piece whose isosurface is empty has a mesh with no triangles.

    Raises
    ------
    InputError : naming the file: vtk missing, unreadable or wrong-type file, unknown array,
        no iso value for a grid, no surface cells, or an empty isosurface over all pieces.
    """
    path = Path(path)
    suffix = vtk_xml_suffix(path)
    if suffix is None:
        raise InputError(path, f"not a VTK XML file (supported: {' '.join(SUFFIXES)})")
    if not path.is_file():
        raise InputError(path, "no such file")
    structured = is_structured(path)
    if structured and iso is None:
        raise InputError(path, "is a grid (volume): give an iso value with --iso VALUE")
    if not structured and color_by is not None:
        raise InputError(path, "--color-by is for grids (volumes); for a mesh pick the array "
                               "kept with --array NAME")
    files = piece_files(path) if suffix in PARALLEL else [path]
    serial = PARALLEL.get(suffix, suffix)
    pieces = []
    for f in files:
        data = _read(f, serial)
        if structured:
            pieces.append(_isosurface(f, data, float(iso), array, color_by, brick, progress))
        else:
            pieces.append(_surface(f, data, array))
    if structured and not any(p.mesh.n_triangles for p in pieces):
        raise InputError(path, f"empty isosurface: level {iso} is not crossed by the grid")
    return pieces


def _vtk():
    """The vtk modules used here (imported on first use: the wheel is large and optional)."""
    try:
        from vtkmodules import vtkCommonDataModel, vtkIOXML
        from vtkmodules.util import numpy_support
        from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow
        from vtkmodules.vtkFiltersCore import vtkCellDataToPointData, vtkTriangleFilter
        from vtkmodules.vtkFiltersGeometry import vtkDataSetSurfaceFilter
    except ImportError:
        return None
    if not isinstance(vtkOutputWindow.GetInstance(), vtkStringOutputWindow):
        # VTK prints its errors to stderr; keep them to report one line naming the file
        vtkOutputWindow.SetInstance(vtkStringOutputWindow())
        vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    # VTK 9.6 moved the cell-type names to vtkCellTypeUtilities (the old one warns)
    cell_types = (getattr(vtkCommonDataModel, "vtkCellTypeUtilities", None)
                  or vtkCommonDataModel.vtkCellTypes)
    return {"io": vtkIOXML, "np": numpy_support, "window": vtkOutputWindow,
            "CellTypes": cell_types, "CellToPoint": vtkCellDataToPointData,
            "Triangles": vtkTriangleFilter, "Surface": vtkDataSetSurfaceFilter}


def _update(vtk, algorithm) -> str | None:
    """Run ``algorithm``; the first error VTK reported meanwhile, or None."""
    window = vtk["window"].GetInstance()
    before = len(window.GetOutput())
    algorithm.Update()
    text = window.GetOutput()[before:]
    for block in text.split("ERROR:")[1:]:
        lines = [ln.strip() for ln in block.strip().splitlines() if ln.strip()]
        if len(lines) > 1:  # "In file.cxx, line N" then "vtkClass (0x..): message"
            message = lines[1].split("): ", 1)[-1]
            return " ".join(message.split())
    return None


def _sniff_type(path: Path) -> str | None:
    """The ``type`` attribute of the file's ``<VTKFile>`` tag, from its first 4 KB."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096).decode("latin-1")
    except OSError:
        return None
    start = head.find("<VTKFile")
    if start < 0:
        return None
    tag = head[start:head.find(">", start)]
    for quote in ('"', "'"):
        key = f"type={quote}"
        if key in tag:
            return tag.split(key, 1)[1].split(quote, 1)[0]
    return None


def _read(path: Path, suffix: str):
    """The dataset of one serial VTK XML file."""
    vtk = _vtk()
    if vtk is None:
        raise InputError(path, INSTALL)
    want = SERIAL[suffix]
    found = _sniff_type(path)
    if found is None:
        raise InputError(path, f"not a VTK XML file (no <VTKFile type=...> tag; a {suffix} "
                               f"file holds {want})")
    if found != want:
        raise InputError(path, f"holds VTK XML {found}, not the {want} a {suffix} file holds")
    reader = getattr(vtk["io"], f"vtkXML{want}Reader")()
    reader.SetFileName(str(path))
    error = _update(vtk, reader)
    data = reader.GetOutput()
    if error is not None or reader.GetErrorCode() != 0:
        raise InputError(path, f"cannot read as VTK XML {want} ({error or 'read error'})")
    if data is None or data.GetNumberOfPoints() == 0:
        raise InputError(path, "has no points")
    return data


def _arrays(data) -> dict[str, tuple[str, object]]:
    """name -> ("point" | "cell", vtkDataArray) of the dataset's numeric arrays, points first."""
    found: dict[str, tuple[str, object]] = {}
    for where, attrs in (("point", data.GetPointData()), ("cell", data.GetCellData())):
        for i in range(attrs.GetNumberOfArrays()):
            arr = attrs.GetArray(i)  # None for string / id arrays
            if arr is not None and arr.GetName() and arr.GetName() not in found:
                found[arr.GetName()] = (where, arr)
    return found


def _pick(path: Path, data, name: str | None, option: str) -> tuple[str, str, object] | None:
    """(name, "point" | "cell", vtkDataArray) of the array ``name`` (default: the first
    one-component point array, else the first one-component cell array, else the first), or
    None when the dataset has no arrays and none was asked for."""
    arrays = _arrays(data)
    if name is not None:
        if name not in arrays:
            raise InputError(path, f"no array {name!r} for {option} (arrays: "
                                   f"{', '.join(arrays) or 'none'})")
        return (name, *arrays[name])
    if not arrays:
        return None
    ordered = sorted(arrays.items(), key=lambda kv: (kv[1][1].GetNumberOfComponents() != 1,
                                                     kv[1][0] != "point"))
    return (ordered[0][0], *ordered[0][1])


def _values(vtk, arr) -> np.ndarray:
    """(n,) float64 values of a VTK array; vectors by their magnitude."""
    values = np.asarray(vtk["np"].vtk_to_numpy(arr), dtype=np.float64)
    if values.ndim == 2:
        values = values[:, 0] if values.shape[1] == 1 else np.linalg.norm(values, axis=1)
    return values


def _finite(path: Path, name: str, values: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(values)):
        raise InputError(path, f"array {name!r} has NaN or infinite values")
    return values


# ---------------------------------------------------------------------------------------------
# grids: isosurface


def _isosurface(path: Path, data, iso: float, array: str | None, color_by: str | None,
                brick: int, progress: bool) -> Piece:
    vtk = _vtk()
    picked = _pick(path, data, array, "--array")
    if picked is None:
        raise InputError(path, "has no data arrays to isosurface")
    colored = _pick(path, data, color_by, "--color-by") if color_by is not None else None
    if picked[1] == "cell" or (colored is not None and colored[1] == "cell"):
        to_points = vtk["CellToPoint"]()
        to_points.SetInputData(data)
        to_points.ProcessAllArraysOn()
        _update(vtk, to_points)
        data = to_points.GetOutput()
    ext = data.GetExtent()
    dims = (ext[1] - ext[0] + 1, ext[3] - ext[2] + 1, ext[5] - ext[4] + 1)
    if min(dims) < 2:
        raise InputError(path, f"grid is {dims[0]}x{dims[1]}x{dims[2]} points: an isosurface "
                               "needs at least 2 points per axis")

    def grid(name: str) -> np.ndarray:
        arr = data.GetPointData().GetArray(name)
        values = _finite(path, name, _values(vtk, arr))
        return values.reshape(dims[2], dims[1], dims[0]).transpose(2, 1, 0)  # -> [x, y, z]

    field = grid(picked[0])
    try:
        parts = [(v, f) for _, v, f in iter_brick_triangles(field, iso, brick,
                                                            progress=progress)]
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
    empty = DomainArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32))
    if not parts:
        return Piece(empty, None, path)
    from vastray.scene import meshops

    joined = meshops.weld(meshops.concat([DomainArrays(v, f) for v, f in parts]))
    keep = ~meshops.degenerate_mask(joined.vertices, joined.indices)
    joined = meshops.subset(joined, np.flatnonzero(keep))
    index_xyz = joined.vertices.astype(np.float64)
    mesh = relative_to(_world(path, data, dims, index_xyz))
    mesh.indices = joined.indices
    if colored is not None:
        mesh.scalars = _trilinear(grid(colored[0]), index_xyz).astype(np.float32)
    log.info("%s: isosurface of %r at %g: %d triangles", path, picked[0], iso, mesh.n_triangles)
    return Piece(mesh, None if colored is None else colored[0], path)


def _world(path: Path, data, dims: tuple[int, int, int], ijk: np.ndarray) -> np.ndarray:
    """World positions (V, 3) float64 of index-space points ``ijk`` of the grid ``data``."""
    kind = data.GetClassName()
    if kind == "vtkImageData":
        first = np.asarray(data.GetPoint(0), np.float64)
        spacing = np.asarray(data.GetSpacing(), np.float64)
        direction = np.array([[data.GetDirectionMatrix().GetElement(r, c) for c in range(3)]
                              for r in range(3)])
        return first + (ijk * spacing) @ direction.T
    if kind == "vtkRectilinearGrid":
        vtk = _vtk()
        axes = [data.GetXCoordinates(), data.GetYCoordinates(), data.GetZCoordinates()]
        out = np.empty_like(ijk)
        for a, coords in enumerate(axes):
            c = np.asarray(vtk["np"].vtk_to_numpy(coords), np.float64)
            out[:, a] = np.interp(ijk[:, a], np.arange(len(c)), c)
        return out
    if kind == "vtkStructuredGrid":
        vtk = _vtk()
        pts = np.asarray(vtk["np"].vtk_to_numpy(data.GetPoints().GetData()), np.float64)
        pts = pts.reshape(dims[2], dims[1], dims[0], 3).transpose(2, 1, 0, 3)
        return _trilinear(pts, ijk)
    raise InputError(path, f"unexpected grid type {kind}")


def _trilinear(grid: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """``grid`` ((nx, ny, nz) or (nx, ny, nz, k)) at fractional indices ``ijk`` ((V, 3)).

    Marching-cubes vertices lie on grid edges, where this is the linear interpolation between
    the edge's two nodes: exact for the positions of a curvilinear grid's straight cell edges.
    """
    n = np.asarray(grid.shape[:3])
    lo = np.clip(np.floor(ijk).astype(np.int64), 0, n - 2)
    f = ijk - lo
    out = np.zeros((len(ijk),) + grid.shape[3:])
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = ((f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1])
                     * (f[:, 2] if dz else 1 - f[:, 2]))
                out += w.reshape((-1,) + (1,) * (grid.ndim - 3)) * grid[
                    lo[:, 0] + dx, lo[:, 1] + dy, lo[:, 2] + dz]
    return out


# ---------------------------------------------------------------------------------------------
# unstructured grids and poly data: boundary surface


def _surface(path: Path, data, array: str | None) -> Piece:
    vtk = _vtk()
    picked = _pick(path, data, array, "--array")
    surface = vtk["Surface"]()
    surface.SetInputData(data)
    triangles = vtk["Triangles"]()
    triangles.SetInputConnection(surface.GetOutputPort())
    triangles.PassLinesOff()
    triangles.PassVertsOff()
    error = _update(vtk, triangles)
    poly = triangles.GetOutput()
    if error is not None:
        raise InputError(path, f"cannot extract its surface ({error})")
    n_tri = poly.GetNumberOfPolys()
    if n_tri == 0:
        raise InputError(path, f"has no surface to render: its cells are {_cell_types(vtk, data)} "
                               "(need triangles, quads, polygons, strips or 3-D cells)")
    conn = np.asarray(vtk["np"].vtk_to_numpy(poly.GetPolys().GetConnectivityArray()), np.int64)
    indices = conn.reshape(n_tri, 3)
    points = np.asarray(vtk["np"].vtk_to_numpy(poly.GetPoints().GetData()), np.float64)
    if not np.all(np.isfinite(points)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(points), axis=1)))
        raise InputError(path, f"{bad} points have NaN or infinite coordinates")
    scalars = None
    if picked is not None:
        name, where, _ = picked
        attrs = poly.GetPointData() if where == "point" else poly.GetCellData()
        scalars = _finite(path, name, _values(vtk, attrs.GetArray(name)))
        if where == "cell":  # exact per-triangle values: every triangle gets its own vertices
            points = points[indices.reshape(-1)]
            indices = np.arange(3 * n_tri, dtype=np.int64).reshape(n_tri, 3)
            scalars = np.repeat(scalars, 3)
    mesh = relative_to(points)
    if not np.all(np.isfinite(mesh.vertices)):
        raise InputError(path, "point coordinates overflow float32")
    mesh.indices = indices.astype(np.uint32)
    mesh.scalars = None if scalars is None else scalars.astype(np.float32)
    log.info("%s: %d surface triangles%s", path, n_tri,
             "" if picked is None else f", scalars from {picked[1]} array {picked[0]!r}")
    return Piece(mesh, None if picked is None else picked[0], path)


def _cell_types(vtk, data) -> str:
    """The names of the cell types in ``data``, e.g. ``"VTK_LINE, VTK_VERTEX"``."""
    types = sorted({int(data.GetCellType(i)) for i in range(data.GetNumberOfCells())})
    if not types:
        return "none (no cells)"
    names = []
    for t in types:
        name = vtk["CellTypes"].GetClassNameFromTypeId(t) or f"type {t}"
        names.append(name.replace("vtk", "VTK_", 1).upper() if name.startswith("vtk") else name)
    return ", ".join(names)
