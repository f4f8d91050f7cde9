"""VTK XML inputs: files written here (by hand, ASCII, and by VTK's own writers, binary), read,
partitioned (parallel pieces as domains) and rendered coloured by their scalars."""

from __future__ import annotations

import json

import numpy as np
import pytest
from skimage.measure import marching_cubes

from vastray.cli import main
from vastray.render.imageio import read_image, to_srgb8
from vastray.scene import vtkxml
from vastray.scene.errors import InputError
from vastray.scene.readers import read_input, read_mesh
from vastray.scene.store import Store

from vtkxml_files import (
    HEXAHEDRON,
    LINE,
    QUAD,
    VERTEX,
    plate,
    write_parallel,
    write_vti,
    write_vtp,
    write_vtr,
    write_vts,
    write_vtu,
)

pytest.importorskip("vtkmodules", reason="the vtk extra is not installed (pip install 'vastray[vtk]')")


def ball(n: int = 12) -> np.ndarray:
    """Distance from the grid's centre, indexed [x, y, z] (n points per axis)."""
    x, y, z = np.meshgrid(*[np.arange(n, dtype=np.float64)] * 3, indexing="ij")
    c = (n - 1) / 2
    return np.sqrt((x - c) ** 2 + (y - 0.9 * c) ** 2 + (z - 1.1 * c) ** 2)


def read_png(path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def world(mesh) -> np.ndarray:
    return mesh.vertices.astype(np.float64) + (0 if mesh.origin is None else mesh.origin)


def halves_plate(tmp_path, name="halves.vtu"):
    """An 8 x 4 plate of quads whose left half has cell value 0 and right half 1."""
    points, quads = plate()
    values = [0.0 if i % 8 < 4 else 1.0 for i in range(len(quads))]
    return write_vtu(tmp_path / name, points, [(QUAD, q) for q in quads],
                     cell_data={"phase": values})


# ---------------------------------------------------------------- meshes: .vtu .vtp


def test_vtu_cell_scalars_stay_per_triangle(tmp_path):
    got = read_input(halves_plate(tmp_path))
    mesh = got.pieces[0]
    assert got.scalar_name == "phase" and not got.parallel
    assert mesh.n_triangles == 64  # 32 quads, two triangles each
    # every triangle has its own vertices, all three with its cell's value
    tri = mesh.scalars[mesh.indices]
    assert np.all(tri == tri[:, :1])
    centre_x = world(mesh)[mesh.indices].mean(axis=1)[:, 0]
    np.testing.assert_array_equal(tri[:, 0], (centre_x > 4).astype(np.float32))


def test_vtp_polygons_triangulated_point_scalars(tmp_path):
    points, quads = plate(3, 1)
    # a pentagon too, and a named point array chosen over the first one
    points = np.vstack([points, [(5, 0, 0), (6, 0, 0), (6.5, 0.5, 0), (6, 1, 0), (5, 1, 0)]])
    polys = [*quads, [8, 9, 10, 11, 12]]
    path = write_vtp(tmp_path / "p.vtp", points, polys,
                     point_data={"id": np.arange(len(points)), "height": points[:, 0] * 10})
    got = read_input(path, array="height")
    mesh = got.pieces[0]
    assert mesh.n_triangles == 3 * 2 + 3
    assert got.scalar_name == "height"
    np.testing.assert_allclose(mesh.scalars, world(mesh)[:, 0] * 10, rtol=1e-6)


def test_vtu_volume_cells_give_their_boundary(tmp_path):
    cube = [(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1)]
    hexa = [0, 1, 3, 2, 4, 5, 7, 6]
    path = write_vtu(tmp_path / "hex.vtu", cube, [(HEXAHEDRON, hexa), (LINE, [0, 7])],
                     point_data={"t": np.arange(8)})
    mesh = read_mesh(path)
    assert mesh.n_triangles == 12  # six faces; the line is left out
    lo, hi = mesh.bounds()
    np.testing.assert_allclose([lo, hi], [[0, 0, 0], [1, 1, 1]])


def test_vtk_written_binary_file_reads_the_same(tmp_path):
    """VTK's own writer: appended, zlib-compressed binary, another encoding than ASCII."""
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader, vtkXMLUnstructuredGridWriter

    ascii_path = halves_plate(tmp_path)
    reader = vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(ascii_path))
    reader.Update()
    writer = vtkXMLUnstructuredGridWriter()
    writer.SetInputData(reader.GetOutput())
    writer.SetFileName(str(tmp_path / "binary.vtu"))
    writer.SetDataModeToAppended()
    writer.Write()
    assert b'format="appended"' in (tmp_path / "binary.vtu").read_bytes()
    a, b = read_mesh(ascii_path), read_mesh(tmp_path / "binary.vtu")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.scalars, b.scalars)


# ---------------------------------------------------------------- grids: .vti .vtr .vts


def test_vti_isosurface_matches_marching_cubes_and_lies_in_world(tmp_path):
    field = ball()
    path = write_vti(tmp_path / "b.vti", {"r": field}, origin=(100, -5, 2), spacing=(0.5, 1, 2))
    mesh = read_mesh(path, iso=4.0)
    verts, faces, _, _ = marching_cubes(field.astype(np.float32), 4.0)
    area = np.linalg.norm(np.cross(verts[faces[:, 1]] - verts[faces[:, 0]],
                                   verts[faces[:, 2]] - verts[faces[:, 0]]), axis=1)
    assert mesh.n_triangles == int(np.count_nonzero(area > 0))
    lo, hi = world(mesh).min(axis=0), world(mesh).max(axis=0)
    expect_lo = np.array([100, -5, 2]) + verts.min(axis=0) * [0.5, 1, 2]
    expect_hi = np.array([100, -5, 2]) + verts.max(axis=0) * [0.5, 1, 2]
    np.testing.assert_allclose(lo, expect_lo, atol=1e-3)
    np.testing.assert_allclose(hi, expect_hi, atol=1e-3)
    assert mesh.scalars is None  # no --color-by: nothing to colour by on an isosurface


def test_vtr_and_vts_map_vertices_through_their_coordinates(tmp_path):
    field = ball(10)
    n = field.shape[0]
    base = read_mesh(write_vti(tmp_path / "b.vti", {"r": field}), iso=3.0)
    # rectilinear: x node coordinates squared (non-uniform), y and z unit steps
    xs = np.arange(n, dtype=np.float64) ** 2
    rect = read_mesh(write_vtr(tmp_path / "b.vtr", xs, np.arange(n), np.arange(n), {"r": field}),
                     iso=3.0)
    assert rect.n_triangles == base.n_triangles
    i = world(base)[:, 0]
    np.testing.assert_allclose(world(rect)[:, 0], np.interp(i, np.arange(n), xs), rtol=1e-5)
    np.testing.assert_allclose(world(rect)[:, 1:], world(base)[:, 1:], atol=1e-5)
    # curvilinear: node positions twice the index, shifted
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).astype(np.float64)
    curv = read_mesh(write_vts(tmp_path / "b.vts", 2 * ijk + 7, {"r": field}), iso=3.0)
    np.testing.assert_allclose(world(curv), 2 * world(base) + 7, atol=1e-4)


def test_color_by_samples_another_array_on_the_isosurface(tmp_path):
    field = ball()
    x = np.meshgrid(*[np.arange(12)] * 3, indexing="ij")[0]
    side = (x >= 6).astype(np.float64)  # 0 on the left half, 1 on the right
    path = write_vti(tmp_path / "b.vti", {"r": field, "side": side})
    got = read_input(path, iso=4.0, color_by="side")
    mesh = got.pieces[0]
    assert got.scalar_name == "side"
    vx = world(mesh)[:, 0]
    assert np.all(mesh.scalars[vx <= 5] == 0) and np.all(mesh.scalars[vx >= 6] == 1)


def test_cell_array_grid_is_averaged_to_points(tmp_path):
    cells = ball(11)[:10, :10, :10]  # one value per cell of an 11^3-point grid
    path = write_vti(tmp_path / "c.vti", cell_data={"r": cells}, shape=(11, 11, 11))
    mesh = read_mesh(path, iso=3.5)
    assert mesh.n_triangles > 100
    lo, hi = mesh.bounds()
    assert np.all(lo >= 0) and np.all(hi <= 10)


# ---------------------------------------------------------------- parallel pieces -> domains


def test_pvtu_pieces_become_domains_unless_a_split_is_asked(tmp_path, capsys):
    for k in range(3):
        points, quads = plate(4, 2, x0=4 * k)
        write_vtu(tmp_path / f"p_{k}.vtu", points, [(QUAD, q) for q in quads],
                  point_data={"temperature": points[:, 0]})
    pvtu = write_parallel(tmp_path / "p.pvtu", "UnstructuredGrid",
                          [f"p_{k}.vtu" for k in range(3)])
    out = tmp_path / "p.store"
    assert main(["partition", str(pvtu), "-o", str(out), "--quiet"]) == 0
    store = Store(out)
    assert len(store.domains) == 3
    assert store.manifest["partition"]["method"] == "pieces"
    assert store.scalar_name == "temperature" and store.scalar_range == (0.0, 12.0)
    for k in range(3):  # domain k is piece k, whole
        dom = store.load_domain(k)
        assert dom.n_triangles == 16
        assert dom.vertices[:, 0].min() == 4 * k and dom.vertices[:, 0].max() == 4 * k + 4
    assert main(["partition", str(pvtu), "-o", str(out), "--force", "--quiet",
                 "--grid", "1x1x1"]) == 0
    assert len(Store(out).domains) == 1 and Store(out).n_triangles == 48


def test_pvti_pieces_share_a_plane_and_join_without_loss(tmp_path):
    field = ball()
    whole = read_mesh(write_vti(tmp_path / "whole.vti", {"r": field}), iso=4.0)
    # two pieces sharing the point plane x = 6, as VTK's parallel writers split image data
    write_vti(tmp_path / "a.vti", {"r": field[:7]})
    b = write_vti(tmp_path / "b.vti", {"r": field[6:]}, origin=(6, 0, 0))
    assert b.exists()
    pvti = write_parallel(tmp_path / "ab.pvti", "ImageData", ["a.vti", "b.vti"],
                          extents=["0 6 0 11 0 11", "6 11 0 11 0 11"], whole="0 11 0 11 0 11")
    got = read_input(pvti, iso=4.0)
    assert got.parallel and len(got.pieces) == 2
    assert sum(p.n_triangles for p in got.pieces) == whole.n_triangles
    assert np.all(world(got.pieces[0])[:, 0] <= 6) and np.all(world(got.pieces[1])[:, 0] >= 6)


# ---------------------------------------------------------------- bad files: one line


@pytest.mark.parametrize("case", ["garbage", "wrong-type", "truncated", "missing-piece",
                                  "lines-only", "unknown-array", "no-iso", "flat-grid"])
def test_bad_vtk_xml_fails_with_one_line_naming_the_file(tmp_path, capsys, case):
    points, quads = plate(2, 1)
    good = write_vtu(tmp_path / "good.vtu", points, [(QUAD, q) for q in quads],
                     point_data={"t": points[:, 0]})
    extra = []
    if case == "garbage":
        bad = tmp_path / "bad.vtu"
        bad.write_text("<VTKFile garbage")
    elif case == "wrong-type":
        bad = write_vti(tmp_path / "bad.vtu", {"r": ball(4)})
    elif case == "truncated":
        bad = tmp_path / "bad.vtu"
        bad.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    elif case == "missing-piece":
        bad = write_parallel(tmp_path / "bad.pvtu", "UnstructuredGrid", ["good.vtu", "gone.vtu"])
    elif case == "lines-only":
        bad = write_vtu(tmp_path / "bad.vtu", points, [(LINE, [0, 1]), (VERTEX, [2])])
    elif case == "unknown-array":
        bad, extra = good, ["--array", "pressure"]
    elif case == "no-iso":
        bad = write_vti(tmp_path / "bad.vti", {"r": ball(4)})
    else:
        bad, extra = write_vti(tmp_path / "bad.vti", {"r": ball(4)[:, :, :1]}), ["--iso", "1"]
    capsys.readouterr()
    assert main(["partition", str(bad), "-o", str(tmp_path / "out.store"), "--quiet",
                 *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vastray partition: error: ") and "\n" not in err
    assert ("gone.vtu" if case == "missing-piece" else bad.name) in err
    assert not (tmp_path / "out.store").exists()
    if case == "lines-only":
        assert "VTK_LINE" in err and "VTK_VERTEX" in err
    if case == "unknown-array":
        assert "'pressure'" in err and "t" in err.rsplit("arrays:", 1)[1]


def test_missing_vtk_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setattr(vtkxml, "_vtk", lambda: None)  # as when the wheel is not installed
    with pytest.raises(InputError, match=r"halves\.vtu: .*pip install 'vastray\[vtk\]'"):
        read_mesh(halves_plate(tmp_path))


# ---------------------------------------------------------------- colour by scalar, legend


def test_render_colours_the_halves_by_their_scalar_with_a_legend(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="--colormap needs matplotlib")
    store = tmp_path / "h.store"
    assert main(["partition", str(halves_plate(tmp_path)), "-o", str(store), "--quiet"]) == 0
    size = ["--width", "96", "--height", "64", "--spp", "1", "--quiet"]
    capsys.readouterr()
    # as a user runs it (no --quiet): the summary line is still the last
    assert main(["render", str(store), "-o", str(tmp_path / "h.exr"), "--png",
                 str(tmp_path / "h.png"), "--colormap", "autumn", *size[:-1]]) == 0
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("wrote ")
    image = read_image(tmp_path / "h.exr")
    lit = image[..., 0] > 2 * image[..., 2] + 0.02  # the plate: autumn has no blue; sky is grey
    cols = np.nonzero(lit.any(axis=0))[0]
    left, right = cols[: len(cols) // 4], cols[-len(cols) // 4:]

    def green_over_red(c):
        px = image[:, c][lit[:, c]]
        return float(px[:, 1].sum() / px[:, 0].sum())

    # autumn runs from red (1, 0, 0) at 0 to yellow (1, 1, 0) at 1; one half is each
    low, high = sorted([green_over_red(left), green_over_red(right)])
    assert low < 0.1 and high > 0.8
    # the PNG: the picture above, the colour bar along the bottom
    png = read_png(tmp_path / "h.png")
    plain = to_srgb8(image)
    assert np.array_equal(png[:20], plain[:20])
    bottom = png[-20:].reshape(-1, 3).astype(int)
    red = (bottom[:, 0] > 200) & (bottom[:, 1] < 40) & (bottom[:, 2] < 40)
    yellow = (bottom[:, 0] > 200) & (bottom[:, 1] > 200) & (bottom[:, 2] < 40)
    assert red.any() and yellow.any()
    assert main(["render", str(store), "-o", str(tmp_path / "n.png"), "--colormap", "autumn",
                 "--no-legend", *size]) == 0
    assert np.array_equal(read_png(tmp_path / "n.png"), plain)
    # no --colormap: the built-in map and no bar unless --legend asks
    assert main(["render", str(store), "-o", str(tmp_path / "d.png"), *size]) == 0
    default = read_png(tmp_path / "d.png")
    assert not np.array_equal(default[:20], plain[:20])  # viridis, not autumn
    capsys.readouterr()
    assert main(["render", str(store), "-o", str(tmp_path / "l.png"), "--legend",
                 *size[:-1]]) == 0  # as a user runs it, without --quiet
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("wrote ")
    assert np.array_equal(read_png(tmp_path / "l.png")[:20], default[:20])
    assert not np.array_equal(read_png(tmp_path / "l.png")[-20:], default[-20:])


def test_unknown_colormap_lists_close_names(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="--colormap needs matplotlib")
    store = tmp_path / "h.store"
    assert main(["partition", str(halves_plate(tmp_path)), "-o", str(store), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["render", str(store), "-o", str(tmp_path / "x.png"), "--colormap", "virdis",
                 "--width", "8", "--height", "8", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "virdis" in err and "viridis" in err and "\n" not in err
    assert not (tmp_path / "x.png").exists()


def test_scalar_name_reaches_the_manifest(tmp_path):
    store = tmp_path / "h.store"
    assert main(["partition", str(halves_plate(tmp_path)), "-o", str(store), "--quiet"]) == 0
    assert json.loads((store / "manifest.json").read_text())["scalar_name"] == "phase"


# ---------------------------------------------------------------- real data (shared/data)


def nondegenerate(field: np.ndarray, level: float) -> int:
    return len(marching_cubes(np.asarray(field, np.float32), level, allow_degenerate=False)[1])


def _write_with_vtk(kind: str, path, data) -> None:
    from vtkmodules import vtkIOXML

    writer = getattr(vtkIOXML, f"vtkXML{kind}Writer")()
    writer.SetInputData(data)
    writer.SetFileName(str(path))
    writer.Write()


def _vtk_array(values: np.ndarray, name: str):
    from vtkmodules.util.numpy_support import numpy_to_vtk

    arr = numpy_to_vtk(np.ascontiguousarray(np.swapaxes(values, 0, 2)).reshape(-1), deep=True)
    arr.SetName(name)
    return arr


@pytest.mark.shared_data
def test_real_volumes_as_vtk_xml_grids(shared_data, tmp_path):
    """shared/data has no VTK XML file; its real grids are written as .vti / .vtr / .vts here
    (VTK's binary writer) and must give the isosurfaces its README lists (less the zero-area
    triangles, which every reader drops)."""
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkImageData, vtkRectilinearGrid, vtkStructuredGrid

    from vastray.scene.volumes import read_volume

    iron = np.asarray(read_volume(shared_data / "volumes" / "iron_protein_68.vtk").data)
    img = vtkImageData()
    img.SetDimensions(*iron.shape)
    img.GetPointData().AddArray(_vtk_array(iron, "potential"))
    _write_with_vtk("ImageData", tmp_path / "iron.vti", img)
    # the README's 26,154 less the zero-area triangles of voxels equal to the level, as the
    # legacy .vtk reader gives
    assert read_mesh(tmp_path / "iron.vti", iso=64).n_triangles == 25_147

    cth = np.load(shared_data / "volumes" / "cth_projectile_armor.npz")
    armor = cth["volume_fraction_for_armor_plate"]  # cells; nodes at the cell centres here
    centres = [(c[1:] + c[:-1]) / 2 for c in (cth["x_nodes"], cth["y_nodes"], cth["z_nodes"])]
    rect = vtkRectilinearGrid()
    rect.SetDimensions(*armor.shape)
    for axis, c in zip("XYZ", centres, strict=True):
        from vtkmodules.util.numpy_support import numpy_to_vtk

        getattr(rect, f"Set{axis}Coordinates")(numpy_to_vtk(c.astype(np.float64), deep=True))
    rect.GetPointData().AddArray(_vtk_array(armor, "armor"))
    _write_with_vtk("RectilinearGrid", tmp_path / "cth.vtr", rect)
    mesh = read_mesh(tmp_path / "cth.vtr", iso=0.5)
    assert mesh.n_triangles == nondegenerate(armor, 0.5)  # README: 20,834 with zero-area ones
    pts = world(mesh)
    for a in range(3):
        assert centres[a].min() <= pts[:, a].min() and pts[:, a].max() <= centres[a].max()

    comb = np.load(shared_data / "volumes" / "combustor_plot3d.npz")
    grid = vtkStructuredGrid()
    grid.SetDimensions(*comb["density"].shape)
    points = vtkPoints()
    from vtkmodules.util.numpy_support import numpy_to_vtk

    points.SetData(numpy_to_vtk(np.swapaxes(comb["xyz"], 0, 2).reshape(-1, 3).astype(np.float64),
                                deep=True))
    grid.SetPoints(points)
    grid.GetPointData().AddArray(_vtk_array(comb["density"], "density"))
    grid.GetPointData().AddArray(_vtk_array(np.linalg.norm(comb["momentum"], axis=-1), "speed"))
    _write_with_vtk("StructuredGrid", tmp_path / "comb.vts", grid)
    got = read_input(tmp_path / "comb.vts", iso=0.38, array="density", color_by="speed")
    assert got.pieces[0].n_triangles == nondegenerate(comb["density"], 0.38)  # README: 11,806
    assert got.scalar_name == "speed" and np.ptp(got.pieces[0].scalars) > 0
    xyz = comb["xyz"].reshape(-1, 3)
    assert np.all(world(got.pieces[0]) >= xyz.min(axis=0) - 1e-4)
    assert np.all(world(got.pieces[0]) <= xyz.max(axis=0) + 1e-4)
