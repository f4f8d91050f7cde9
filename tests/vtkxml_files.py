"""Small VTK XML files written by hand (ASCII), as the VTK file-format document describes them,
so the reader is tested on files its own library did not write."""

from __future__ import annotations

from pathlib import Path

import numpy as np

HEAD = '<?xml version="1.0"?>\n<VTKFile type="{kind}" version="1.0" byte_order="LittleEndian">\n'
TAIL = "</VTKFile>\n"

#: VTK cell type ids
VERTEX, LINE, TRIANGLE, POLYGON, QUAD, TETRA, HEXAHEDRON = 1, 3, 5, 7, 9, 10, 12


def data_array(values, name: str | None = None, kind: str = "Float64", components: int = 1) -> str:
    flat = " ".join(repr(float(v)) if kind.startswith("Float") else str(int(v))
                    for v in np.asarray(values).reshape(-1))
    named = f' Name="{name}"' if name else ""
    return (f'<DataArray type="{kind}"{named} NumberOfComponents="{components}" '
            f'format="ascii">{flat}</DataArray>\n')


def _fields(point_data: dict | None, cell_data: dict | None) -> str:
    """<PointData> and <CellData>; arrays of shape (n,) or (n, k). Values for grids are given
    indexed [x, y, z] and written x fastest."""
    out = []
    for tag, arrays in (("PointData", point_data or {}), ("CellData", cell_data or {})):
        out.append(f"<{tag}>\n")
        for name, values in arrays.items():
            values = np.asarray(values, np.float64)
            comps = values.shape[-1] if values.ndim in (2, 4) else 1
            if values.ndim >= 3:  # a grid [x, y, z(, k)] -> x fastest
                values = np.swapaxes(values, 0, 2)
            out.append(data_array(values, name, components=comps))
        out.append(f"</{tag}>\n")
    return "".join(out)


def _extent(shape) -> str:
    return " ".join(f"0 {n - 1}" for n in shape)


def write_vti(path, point_data: dict | None = None, cell_data: dict | None = None,
              shape=None, origin=(0, 0, 0), spacing=(1, 1, 1)) -> Path:
    """ImageData of ``shape`` points; arrays indexed [x, y, z]."""
    path = Path(path)
    shape = shape or next(iter(point_data.values())).shape[:3]
    ext = _extent(shape)
    path.write_text(
        HEAD.format(kind="ImageData")
        + f'<ImageData WholeExtent="{ext}" Origin="{" ".join(map(str, origin))}" '
          f'Spacing="{" ".join(map(str, spacing))}">\n<Piece Extent="{ext}">\n'
        + _fields(point_data, cell_data) + "</Piece>\n</ImageData>\n" + TAIL)
    return path


def write_vtr(path, x, y, z, point_data: dict) -> Path:
    """RectilinearGrid with node coordinates ``x, y, z``; arrays indexed [x, y, z]."""
    path = Path(path)
    ext = _extent((len(x), len(y), len(z)))
    coords = "".join(data_array(c) for c in (x, y, z))
    path.write_text(
        HEAD.format(kind="RectilinearGrid") + f'<RectilinearGrid WholeExtent="{ext}">\n'
        + f'<Piece Extent="{ext}">\n' + _fields(point_data, None)
        + f"<Coordinates>\n{coords}</Coordinates>\n</Piece>\n</RectilinearGrid>\n" + TAIL)
    return path


def write_vts(path, points: np.ndarray, point_data: dict) -> Path:
    """StructuredGrid with node positions ``points`` (nx, ny, nz, 3); arrays [x, y, z]."""
    path = Path(path)
    ext = _extent(points.shape[:3])
    pts = data_array(np.swapaxes(points, 0, 2), components=3)
    path.write_text(
        HEAD.format(kind="StructuredGrid") + f'<StructuredGrid WholeExtent="{ext}">\n'
        + f'<Piece Extent="{ext}">\n' + _fields(point_data, None)
        + f"<Points>\n{pts}</Points>\n</Piece>\n</StructuredGrid>\n" + TAIL)
    return path


def write_vtu(path, points, cells: list[tuple[int, list[int]]], point_data: dict | None = None,
              cell_data: dict | None = None) -> Path:
    """UnstructuredGrid; ``cells`` are (VTK type id, point ids)."""
    path = Path(path)
    conn = [i for _, ids in cells for i in ids]
    offsets = np.cumsum([len(ids) for _, ids in cells])
    path.write_text(
        HEAD.format(kind="UnstructuredGrid") + "<UnstructuredGrid>\n"
        + f'<Piece NumberOfPoints="{len(points)}" NumberOfCells="{len(cells)}">\n'
        + _fields(point_data, cell_data)
        + "<Points>\n" + data_array(points, components=3) + "</Points>\n<Cells>\n"
        + data_array(conn, "connectivity", "Int64") + data_array(offsets, "offsets", "Int64")
        + data_array([t for t, _ in cells], "types", "UInt8")
        + "</Cells>\n</Piece>\n</UnstructuredGrid>\n" + TAIL)
    return path


def write_vtp(path, points, polys: list[list[int]], point_data: dict | None = None,
              cell_data: dict | None = None) -> Path:
    """PolyData of polygons (any number of corners each)."""
    path = Path(path)
    conn = [i for ids in polys for i in ids]
    offsets = np.cumsum([len(ids) for ids in polys])
    path.write_text(
        HEAD.format(kind="PolyData") + "<PolyData>\n"
        + f'<Piece NumberOfPoints="{len(points)}" NumberOfVerts="0" NumberOfLines="0" '
          f'NumberOfStrips="0" NumberOfPolys="{len(polys)}">\n'
        + _fields(point_data, cell_data)
        + "<Points>\n" + data_array(points, components=3) + "</Points>\n<Polys>\n"
        + data_array(conn, "connectivity", "Int64") + data_array(offsets, "offsets", "Int64")
        + "</Polys>\n</Piece>\n</PolyData>\n" + TAIL)
    return path


def write_parallel(path, kind: str, sources: list[str], extents: list[str] | None = None,
                   whole: str = "") -> Path:
    """A parallel file (``kind`` "UnstructuredGrid", "ImageData", ...) naming piece files."""
    path = Path(path)
    attrs = f' WholeExtent="{whole}" Origin="0 0 0" Spacing="1 1 1"' if kind == "ImageData" else ""
    pieces = "".join(
        f'<Piece{"" if extents is None else f" Extent={chr(34)}{extents[i]}{chr(34)}"} '
        f'Source="{s}"/>\n' for i, s in enumerate(sources))
    path.write_text(HEAD.format(kind="P" + kind) + f'<P{kind} GhostLevel="0"{attrs}>\n'
                    + pieces + f"</P{kind}>\n" + TAIL)
    return path


def plate(nx: int = 8, ny: int = 4, x0: int = 0) -> tuple[np.ndarray, list]:
    """Points and quads of a flat plate of nx by ny unit quads in z = 0, from x = x0."""
    points = np.array([(x0 + i, j, 0.0) for j in range(ny + 1) for i in range(nx + 1)])
    quads = [[j * (nx + 1) + i, j * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i + 1,
              (j + 1) * (nx + 1) + i] for j in range(ny) for i in range(nx)]
    return points, quads
