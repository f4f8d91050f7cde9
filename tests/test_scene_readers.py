"""Readers: real meshes and volumes from ../shared/data, synthetic formats, and bad inputs."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

from vastray.scene.errors import InputError
from vastray.scene.isosurface import iter_brick_triangles
from vastray.scene.readers import read_mesh
from vastray.scene.volumes import read_volume

# ---------------------------------------------------------------- real data (shared/data)


@pytest.mark.shared_data
def test_bunny_with_scalar_field(shared_data):
    mesh = read_mesh(shared_data / "meshes" / "stanford_bunny.ply")
    assert mesh.n_triangles == 69_451
    assert len(mesh.vertices) == 35_947
    assert mesh.vertices.dtype == np.float32 and mesh.indices.dtype == np.uint32
    assert mesh.scalars is not None and mesh.scalars.shape == (35_947,)
    assert mesh.scalars[0] == pytest.approx(0.850855)  # first extra property: confidence
    assert mesh.colors is None


@pytest.mark.shared_data
def test_spot_obj(shared_data):
    mesh = read_mesh(shared_data / "meshes" / "spot.obj")
    assert mesh.n_triangles == 5_856
    assert len(mesh.vertices) == 3_225
    assert mesh.scalars is None and mesh.colors is None


@pytest.mark.shared_data
def test_iron_protein_isosurface(shared_data):
    path = shared_data / "volumes" / "iron_protein_68.vtk"
    vol = read_volume(path)
    assert vol.shape == (68, 68, 68)
    # marching cubes brick by brick gives the README's count exactly ...
    raw = sum(len(f) for _, _, f in iter_brick_triangles(vol.data, 64, brick=32))
    assert raw == 26_154
    # ... and the reader drops the zero-area triangles of voxels equal to the level
    mesh = read_mesh(path, iso=64)
    whole = np.asarray(vol.data, np.float32)
    _, faces, _, _ = marching_cubes(whole, 64, allow_degenerate=False)
    assert mesh.n_triangles == len(faces) == 25_147
    lo, hi = mesh.bounds()
    assert np.all(lo >= 0) and np.all(hi <= 67)


@pytest.mark.shared_data
def test_carotid_origin_and_first_array(shared_data):
    vol = read_volume(shared_data / "volumes" / "carotid_flow.vtk")
    assert vol.shape == (76, 49, 45)
    np.testing.assert_array_equal(vol.origin, [100, 80, 1])
    assert sum(len(f) for _, _, f in iter_brick_triangles(vol.data, 100)) == 61_768


@pytest.mark.shared_data
def test_hydrogen_nifti(shared_data):
    path = shared_data / "volumes" / "hydrogen_orbital_64.nii.gz"
    try:
        import nibabel  # noqa: F401
    except ImportError:
        with pytest.raises(InputError, match=r"pip install vastray\[nifti\]"):
            read_mesh(path, iso=0.05)
        pytest.skip("nibabel not installed; checked the install hint instead")
    vol = read_volume(path)
    assert sum(len(f) for _, _, f in iter_brick_triangles(vol.data, 0.05)) == 19_672


# ---------------------------------------------------------------- synthetic formats


def test_ply_vertex_colors_are_kept_as_linear_rgb(tmp_path):
    box = trimesh.creation.box()
    rgba = np.zeros((8, 4), np.uint8)
    rgba[:, 0], rgba[:, 3] = np.arange(8) * 30, 255
    box.visual.vertex_colors = rgba
    box.export(tmp_path / "c.ply")
    mesh = read_mesh(tmp_path / "c.ply")
    assert mesh.colors.shape == (8, 3) and mesh.colors.dtype == np.float32
    srgb = rgba[:, 0] / 255.0
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(mesh.colors[:, 0], linear, atol=1e-6)
    assert np.all(mesh.colors[:, 1:] == 0)


def test_plain_ply_has_no_colors_or_scalars(tmp_path):
    trimesh.creation.box().export(tmp_path / "b.ply")
    mesh = read_mesh(tmp_path / "b.ply")
    assert mesh.colors is None and mesh.scalars is None and mesh.n_triangles == 12


@pytest.mark.parametrize("suffix", [".stl", ".glb", ".obj"])
def test_other_mesh_formats(tmp_path, suffix):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    sphere.export(tmp_path / f"s{suffix}")
    mesh = read_mesh(tmp_path / f"s{suffix}")
    assert mesh.n_triangles == len(sphere.faces)
    if suffix == ".stl":
        assert len(mesh.vertices) == len(sphere.vertices)  # welded
    assert trimesh.Trimesh(mesh.vertices, mesh.indices, process=False).is_watertight


def _sphere_field(shape=(20, 24, 18)) -> np.ndarray:
    axes = [np.linspace(-1, 1, n, dtype=np.float32) for n in shape]
    return np.sqrt(axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2
                   + axes[2][None, None, :] ** 2)


@pytest.mark.parametrize("order", ["F", "C"])
def test_raw_volume_with_json_header(tmp_path, order):
    vol = _sphere_field()
    (tmp_path / "v.raw").write_bytes(vol.astype(">f4").tobytes(order=order))
    header = {"shape": list(vol.shape), "dtype": ">f4", "spacing": [1, 2, 3],
              "origin": [5, 0, 0], "order": order}
    (tmp_path / "v.json").write_text(json.dumps(header))
    expect = len(marching_cubes(vol, 0.8)[1])
    for name in ("v.raw", "v.json"):
        mesh = read_mesh(tmp_path / name, iso=0.8, brick=7)
        assert mesh.n_triangles == expect
        assert mesh.bounds()[0][0] >= 5 and mesh.bounds()[1][2] <= 17 * 3
    (tmp_path / "v.raw").write_bytes(b"\0" * 100)
    with pytest.raises(InputError, match="truncated") as err:
        read_mesh(tmp_path / "v.json", iso=0.8)
    assert "v.raw" in str(err.value)


def test_raw_without_header(tmp_path):
    (tmp_path / "lonely.raw").write_bytes(b"\0" * 64)
    with pytest.raises(InputError, match="JSON header") as err:
        read_mesh(tmp_path / "lonely.raw", iso=1)
    assert "lonely.raw" in str(err.value)


def test_npy_volume_and_missing_iso(tmp_path):
    np.save(tmp_path / "v.npy", _sphere_field().astype(np.float64))
    mesh = read_mesh(tmp_path / "v.npy", iso=0.5)
    assert mesh.n_triangles == len(marching_cubes(_sphere_field(), 0.5)[1])
    with pytest.raises(InputError, match="--iso") as err:
        read_mesh(tmp_path / "v.npy")
    assert "v.npy" in str(err.value)
    with pytest.raises(InputError, match="not crossed"):
        read_mesh(tmp_path / "v.npy", iso=99)
    np.save(tmp_path / "flat.npy", np.zeros((4, 4)))
    with pytest.raises(InputError, match="3-D"):
        read_mesh(tmp_path / "flat.npy", iso=0)


def test_truncated_npy_volume(tmp_path):
    np.save(tmp_path / "t.npy", _sphere_field())
    data = (tmp_path / "t.npy").read_bytes()
    (tmp_path / "t.npy").write_bytes(data[:500])
    with pytest.raises(InputError, match="t.npy"):
        read_mesh(tmp_path / "t.npy", iso=0.5)


def test_legacy_vtk_structured_points(tmp_path):
    vol = _sphere_field((12, 10, 8))
    header = (b"# vtk DataFile Version 3.0\nsphere\nBINARY\nDATASET STRUCTURED_POINTS\n"
              b"DIMENSIONS 12 10 8\nSPACING 0.5 0.5 0.5\nORIGIN -1 -2 -3\nPOINT_DATA 960\n"
              b"SCALARS r float 1\nLOOKUP_TABLE default\n")
    (tmp_path / "s.vtk").write_bytes(header + vol.transpose(2, 1, 0).astype(">f4").tobytes())
    v = read_volume(tmp_path / "s.vtk")
    np.testing.assert_array_equal(np.asarray(v.data), vol)
    np.testing.assert_array_equal(v.origin, [-1, -2, -3])
    (tmp_path / "a.vtk").write_bytes(header.replace(b"BINARY", b"ASCII") + b"0 " * 960)
    with pytest.raises(InputError, match="ASCII"):
        read_volume(tmp_path / "a.vtk")
    (tmp_path / "t.vtk").write_bytes(header + b"\0" * 10)
    with pytest.raises(InputError, match="truncated"):
        read_volume(tmp_path / "t.vtk")


# ---------------------------------------------------------------- bad inputs

BAD = {
    "nan.obj": ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "NaN"),
    "inf.ply": ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                "end_header\n0 0 0\n1 0 0\ninf 1 0\n3 0 1 2\n", "NaN or infinite"),
    "empty.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "empty mesh"),
    "nothing.stl": ("", "empty mesh"),
    "degenerate.obj": ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 1 1 2\n", "degenerate"),
    "range.ply": ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                  "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                  "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "out of range"),
    "range.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "out of bounds"),
    "garbage.ply": ("hello", "cannot read as PLY"),
    "model.fbx": ("whatever", "supported: .ply .obj"),
    "noext": ("whatever", "unsupported"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_input_names_the_file(tmp_path, name):
    text, problem = BAD[name]
    (tmp_path / name).write_text(text)
    with pytest.raises(InputError, match=problem) as err:
        read_mesh(tmp_path / name)
    assert err.value.path == str(tmp_path / name)
    assert str(err.value).startswith(str(tmp_path / name) + ": ")


def test_missing_file(tmp_path):
    for name in ("missing.ply", "missing.npy"):
        with pytest.raises(InputError, match="no such file") as err:
            read_mesh(tmp_path / name, iso=1)
        assert name in str(err.value)


def test_some_degenerate_triangles_are_dropped_with_a_warning(tmp_path, caplog):
    (tmp_path / "d.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 4\n")
    with caplog.at_level(logging.WARNING, logger="vastray.scene.readers"):
        mesh = read_mesh(tmp_path / "d.obj")
    assert mesh.n_triangles == 1
    assert "dropped 1 degenerate" in caplog.text
