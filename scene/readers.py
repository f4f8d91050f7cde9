"""Read one input file into triangle arrays: meshes through trimesh, volumes by isosurface.

Meshes (PLY, OBJ, GLB/GLTF, STL) load with ``trimesh.load(path, force="mesh", process=False)``
and are validated: finite vertices, at least one triangle, indices in range; zero-area triangles
are dropped with a warning (an error if all are). Per-vertex colours are kept when the file has
them; a PLY's first extra vertex property (e.g. the Stanford bunny's ``confidence``) becomes the
per-vertex scalar field.

Volumes (see :mod:`vastray.scene.volumes`) need an iso value; they are isosurfaced brick by
brick (:mod:`vastray.scene.isosurface`) and the pieces welded exactly.

VTK XML files (``.vti .vtr .vts .vtu .vtp`` and parallel ``.pvt*``) go through
:mod:`vastray.scene.vtkxml`: grids are isosurfaced like volumes, unstructured grids and poly
data give their boundary surface, and a parallel file's pieces stay apart
(:func:`read_input`), so that each can become one domain.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vastray.scene import meshops, vtkxml
from vastray.scene.errors import InputError
from vastray.scene.isosurface import DEFAULT_BRICK, iter_brick_triangles
from vastray.scene.store import DomainArrays, frame_for, relative_to
from vastray.scene.volumes import VOLUME_SUFFIXES, read_volume, volume_suffix

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf")
SUPPORTED = MESH_SUFFIXES + VOLUME_SUFFIXES + vtkxml.SUFFIXES

# PLY vertex properties that are geometry or colour, not a scalar field
_PLY_STANDARD = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha", "r", "g", "b",
                 "a", "s", "t", "u", "v", "texture_u", "texture_v", "texture_s", "texture_t"}


@dataclass
class Input:
    """One input file read into triangles.

    Attributes
    ----------
    pieces : the file's triangles: one part, or one per piece of a parallel VTK XML file
        (each in its own frame; ``meshops.concat`` joins them).
    scalar_name : name of the array kept as the per-vertex scalars, where the file names it.
    parallel : True for a parallel VTK XML file (its pieces are ready-made domains).
    """

    pieces: list[DomainArrays]
    scalar_name: str | None = None
    parallel: bool = False


def read_input(path: str | os.PathLike, iso: float | None = None, brick: int = DEFAULT_BRICK,
               progress: bool = False, array: str | None = None,
               color_by: str | None = None) -> Input:
    """Read any supported file (mesh, volume or VTK XML) into triangles, keeping pieces apart.

    Parameters
    ----------
    path, iso, brick, progress : as for :func:`read_mesh`.
    array, color_by : VTK XML only (see :func:`vastray.scene.vtkxml.read_vtk_xml`): the array
        isosurfaced (grids) or kept as scalars (meshes), and the array sampled on a grid's
        isosurface as its scalars. Ignored, with a warning, for other files.

    Raises
    ------
    InputError : naming the file, as :func:`read_mesh` and ``read_vtk_xml`` do.
    """
    path = Path(path)
    if vtkxml.vtk_xml_suffix(path) is not None:
        if not vtkxml.is_structured(path) and iso is not None:
            log.warning("%s: is a mesh; --iso %s ignored", path, iso)
        pieces = vtkxml.read_vtk_xml(path, iso=iso, array=array, color_by=color_by,
                                     brick=brick, progress=progress)
        for piece in pieces:
            if piece.mesh.n_triangles:
                piece.mesh = _drop_degenerate(piece.mesh, piece.source, logging.INFO)
        names = {p.scalar_name for p in pieces}
        return Input([p.mesh for p in pieces], names.pop() if len(names) == 1 else None,
                     vtkxml.is_parallel(path))
    for option, value in (("--array", array), ("--color-by", color_by)):
        if value is not None:
            log.warning("%s: %s applies to VTK XML files only; ignored", path, option)
    return Input([read_mesh(path, iso=iso, brick=brick, progress=progress)])


def is_volume(path: str | os.PathLike) -> bool:
    """True when ``path`` names a volume format (isosurfaced with an iso value)."""
    return volume_suffix(path) is not None


def read_mesh(path: str | os.PathLike, iso: float | None = None,
              brick: int = DEFAULT_BRICK, progress: bool = False) -> DomainArrays:
    """Read a mesh file, or isosurface a volume file, into triangle arrays.

    Parameters
    ----------
    path : a mesh (``.ply .obj .stl .glb .gltf``), volume (``.npy .raw .json .nii .nii.gz
        .vtk``) or VTK XML (``.vti .vtr .vts .vtu .vtp .pvt*``, default arrays; pieces joined)
        file.
    iso : iso value; required for volumes, ignored (with a warning) for meshes.
    brick : most cells per marching-cubes brick edge (volumes).
    progress : tqdm bar on stderr while isosurfacing.

    Returns
    -------
    DomainArrays
        vertices (V, 3) float32, indices (T, 3) uint32, scalars (V,) float32 or None,
        colors (V, 3) float32 linear RGB in [0, 1] or None; objects is None.

    Raises
    ------
    InputError : naming ``path``: missing file, unsupported extension, unreadable content,
        NaN/Inf vertices, no triangles, index out of range, only degenerate triangles, or a
        volume without ``iso``.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    if vtkxml.vtk_xml_suffix(path) is not None:
        return meshops.concat(read_input(path, iso, brick, progress).pieces)
    if is_volume(path):
        if iso is None:
            raise InputError(path, "is a volume: give an iso value with --iso VALUE")
        return _isosurface(path, float(iso), brick, progress)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(path, f"unsupported file type {suffix or '(none)'!r}; "
                               f"supported: {' '.join(SUPPORTED)}")
    if iso is not None:
        log.warning("%s: is a mesh; --iso %s ignored", path, iso)
    return _read_trimesh(path)


def _read_trimesh(path: Path) -> DomainArrays:
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh's loaders raise many types for malformed files
        raise InputError(path, f"cannot read as {path.suffix.lower()[1:].upper()} "
                               f"({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "empty mesh: no triangles")
    if path.suffix.lower() == ".ply":
        _check_ply_counts(path, len(mesh.vertices), len(mesh.faces))
    vertices64 = np.asarray(mesh.vertices, dtype=np.float64)
    indices = np.asarray(mesh.faces)
    if not np.all(np.isfinite(vertices64)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(vertices64), axis=1)))
        raise InputError(path, f"{bad} vertices have NaN or infinite coordinates")
    framed = relative_to(vertices64)  # far from the world origin: relative to the data's centre
    vertices = framed.vertices
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "vertex coordinates overflow float32")
    if indices.min() < 0 or indices.max() >= len(vertices):
        raise InputError(path, f"triangle index out of range (indices {indices.min()}.."
                               f"{indices.max()}, {len(vertices)} vertices)")
    result = DomainArrays(
        vertices=vertices,
        indices=indices.astype(np.uint32),
        scalars=_ply_scalars(mesh, path),
        colors=_vertex_colors(mesh, path),
        origin=framed.origin,
    )
    if path.suffix.lower() == ".stl":  # STL stores three private vertices per triangle
        result = meshops.weld(result)
    return _drop_degenerate(result, path, logging.WARNING)


def _check_ply_counts(path: Path, vertices: int, triangles: int) -> None:
    """Refuse a PLY with fewer vertices or faces than its header declares (trimesh reads a
    truncated ASCII PLY without a word: a file cut short lost its last triangles).
    Polygons of more than three corners are split into triangles, so there may be more
    triangles than faces, never fewer."""
    declared = {}
    with open(path, "rb") as fh:
        for _ in range(1000):  # a header's lines; the body is not read
            line = fh.readline(4096)
            if not line or line.strip() == b"end_header":
                break
            words = line.split()
            if len(words) == 3 and words[0] == b"element" and words[2].isdigit():
                declared[words[1].decode("ascii", "replace")] = int(words[2])
    if declared.get("vertex", vertices) > vertices or declared.get("face", triangles) > triangles:
        raise InputError(path, f"holds {vertices:,} vertices and {triangles:,} triangles where "
                               f"its header declares {declared.get('vertex', 0):,} vertices and "
                               f"{declared.get('face', 0):,} faces: truncated or damaged")


def _drop_degenerate(mesh: DomainArrays, path: Path, level: int) -> DomainArrays:
    bad = meshops.degenerate_mask(mesh.vertices, mesh.indices)
    n_bad = int(bad.sum())
    if n_bad == 0:
        return mesh
    if n_bad == mesh.n_triangles:
        raise InputError(path, f"all {n_bad} triangles are degenerate (zero area)")
    log.log(level, "%s: dropped %d degenerate (zero-area) triangles of %d",
            path, n_bad, mesh.n_triangles)
    mesh.indices = mesh.indices[~bad]
    return mesh


def _ply_scalars(mesh, path: Path) -> np.ndarray | None:
    """The first non-geometry, non-colour PLY vertex property as (V,) float32, or None."""
    raw = mesh.metadata.get("_ply_raw", {}).get("vertex")
    if raw is None:
        return None
    for name in raw.get("properties", {}):
        if name.lower() in _PLY_STANDARD:
            continue
        values = np.asarray(raw["data"][name]).reshape(-1)
        if values.dtype.kind not in "biuf" or len(values) != len(mesh.vertices):
            continue
        values = values.astype(np.float32)
        if not np.all(np.isfinite(values)):
            log.warning("%s: vertex property %r has NaN/Inf values; not used as scalars",
                        path, name)
            return None
        log.info("%s: per-vertex scalar field from PLY property %r", path, name)
        return values
    return None


def _vertex_colors(mesh, path: Path) -> np.ndarray | None:
    """Per-vertex colours as linear RGB (V, 3) float32, only when the file has them.

    trimesh gives 8-bit RGBA. glTF ``COLOR_0`` is linear by specification; the 8-bit colours
    of PLY/OBJ/STL files are sRGB-encoded by convention and are decoded to linear here.
    """
    visual = mesh.visual
    if getattr(visual, "kind", None) != "vertex":
        return None
    rgb = np.asarray(visual.vertex_colors)[:, :3].astype(np.float32) / np.float32(255.0)
    if len(rgb) != len(mesh.vertices):
        return None
    if path.suffix.lower() in (".glb", ".gltf"):
        return rgb
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4).astype(
        np.float32)


def _isosurface(path: Path, iso: float, brick: int, progress: bool) -> DomainArrays:
    vol = read_volume(path)
    # far from the world origin: vertices relative to the volume's centre (``frame_for``)
    far_corner = vol.origin + vol.spacing * (np.asarray(vol.data.shape[:3], np.float64) - 1)
    frame = frame_for(np.minimum(vol.origin, far_corner), np.maximum(vol.origin, far_corner))
    offset = vol.origin if frame is None else vol.origin - frame
    try:
        parts = [DomainArrays(v, f, origin=frame) for _, v, f in
                 iter_brick_triangles(vol.data, iso, brick, vol.spacing, offset, progress)]
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
    if not parts:
        raise InputError(path, f"empty isosurface: level {iso} is not crossed by the volume")
    mesh = meshops.weld(meshops.concat(parts))
    log.info("%s: isosurface at %g: %d triangles from %d bricks",
             path, iso, mesh.n_triangles, len(parts))
    # marching cubes makes zero-area triangles where voxels equal the level; drop them quietly
    mesh = _drop_degenerate(mesh, path, logging.INFO)
    return meshops.subset(mesh, np.arange(mesh.n_triangles))
