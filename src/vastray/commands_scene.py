"""Scene commands: ``partition`` (files -> domain store), ``generate`` (procedural scene ->
domain store), ``simplify`` (add the simplified whole-scene model to a store), ``info``
(describe a store) and ``verify`` (check every file of a store)."""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import numpy as np

from vastray.request import positive_int
from vastray.scene import meshops
from vastray.scene.errors import InputError
from vastray.scene.extent import check_extent
from vastray.scene.fields import SCENES
from vastray.scene.generate import generate
from vastray.scene.isosurface import DEFAULT_BRICK
from vastray.scene.manifest import MAX_DOMAINS
from vastray.scene.partition import partition_grid, partition_kd, partition_pieces
from vastray.scene.readers import SUPPORTED, read_input
from vastray.scene.simplify import DEFAULT_MIN_FACES, build_simplified, check_ratio
from vastray.scene.store import ATTRIBUTES, Store, StoreWriter, check_replaceable, is_store
from vastray.scene.verify import verify_store

log = logging.getLogger(__name__)

DEFAULT_GRID = (2, 2, 2)

PARTITION_EPILOG = """\
examples:
  vastray data fetch -o samples                                     # the sample meshes
  vastray partition samples/stanford_bunny.ply -o bunny.store       # 2x2x2 grid (default)
  vastray partition samples/stanford_bunny.ply samples/spot.obj -o two.store --grid 4x2x2
  vastray partition samples/lucy_100k.ply -o lucy.store --domains 12 --split kd
  vastray partition volume.npy -o vol.store --iso 0.5               # volume -> isosurface
  vastray partition flow.vtu -o flow.store --array pressure         # VTK XML mesh + scalar
  vastray partition cth.vtr -o cth.store --iso 0.5 --array armor --color-by pressure
  vastray partition run.pvtu -o run.store                           # one domain per piece

supported inputs: {supported}
volumes (.npy .raw/.json .nii .nii.gz .vtk) need --iso; a .raw file needs a JSON header
(shape, dtype, spacing, origin, optional order "F"|"C", file, offset) beside it.
VTK XML (needs `pip install 'vastray[vtk]'`): grids (.vti .vtr .vts) are volumes: --iso on
--array NAME (default: the first one-component array), and --color-by NAME samples another
array on the surface for colouring; unstructured grids and poly data (.vtu .vtp) give their
boundary surface, triangulated, and keep --array NAME (default: the first point array, else
cell array) as the scalar coloured by `vastray render --colormap`. Vector arrays count by
their magnitude. Parallel files (.pvti .pvtr .pvts .pvtu .pvtp): when every input is one and
neither --grid nor --domains is given, each piece becomes one domain as it is (not
re-partitioned; empty pieces are dropped); with --grid or --domains the pieces are joined
and split like any other input.
"""

GENERATE_EPILOG = """\
examples:
  vastray generate rm -o rm.store --resolution 64 --grid 2x2x2          # ~40k triangles, <1 s
  vastray generate cosmo -o cosmo.store --resolution 512 --grid 4x4x4 --seed 7  # ~3M, ~12 s

scenes:
  rm     Richtmyer-Meshkov-like mixing layer: a perturbed, turbulent density interface
  cosmo  cosmology-like density: Gaussian halos strung along filaments (a cosmic web)
The field is evaluated and isosurfaced brick by brick; memory holds one brick and the
triangles of one x-slab of the grid, never the whole volume.
"""

SIMPLIFY_EPILOG = """\
examples:
  vastray generate rm -o rm.store --resolution 128 --grid 4x4x4
  vastray simplify rm.store --ratio 0.05          # keep 5 % of the triangles
  vastray simplify rm.store --ratio 0.01 --force  # replace it
  vastray partition samples/lucy_100k.ply -o lucy.store --simplify 0.02   # in one go

Every object piece (one material slot of one domain) is decimated by quadric edge collapse;
pieces with fewer than --min-faces triangles are kept whole. The result is one mesh of the
whole scene in STORE/simplified/, checksummed in the manifest with its triangle rate
(triangles kept / all triangles) and memory rate (its bytes / the domains' bytes).
"""

VERIFY_EPILOG = """\
example:
  vastray generate rm -o rm.store --resolution 32
  vastray verify rm.store        # rm.store: OK: 8 domains, ... (checksums checked)

checks: the manifest's size and fields; every file it names stays inside the store (relative,
no '..', no symlink out) and is the expected <kind>.npy; counts, dtypes and shapes agree with
the .npy headers and data; boxes are finite with lo <= hi and hold their triangles; ids are
0..N-1; every triangle index is below its domain's vertex count; every file's SHA-256 matches
the manifest (stores written by this version; older ones have no checksums).
exit status: 0 when the store is sound, 2 when any problem was found.
"""


def parse_grid(text: str) -> tuple[int, int, int]:
    """``"AxBxC"`` -> (A, B, C), each >= 1 (an argparse type)."""
    try:
        dims = tuple(int(p) for p in text.lower().split("x"))
    except ValueError:
        dims = ()
    if len(dims) != 3 or min(dims) < 1:
        raise argparse.ArgumentTypeError(f"expected AxBxC with positive integers, got {text!r}")
    return dims


def _ratio(text: str) -> float:
    try:
        return check_ratio(float(text))
    except (ValueError, InputError):
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1] (the share of triangles "
                                         f"kept), got {text!r}") from None


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def _show_progress(args) -> bool:
    return not args.quiet and sys.stderr.isatty()


def _add_store_output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace STORE if it is a vastray store (never another folder)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or summary")


def _add_simplify_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--simplify", type=_ratio, metavar="RATIO",
                   help="also build the simplified whole-scene model keeping RATIO of the "
                        "triangles (in (0, 1]; see `vastray simplify -h`)")


def _simplify_after(args, out: Path) -> None:
    """``--simplify RATIO``: build the simplified model into the store just written."""
    if args.simplify is None:
        return
    result = build_simplified(Store(out), args.simplify, progress=_show_progress(args))
    if not args.quiet:
        print(result.summary(out))


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``partition``, ``generate``, ``simplify``, ``info`` and ``verify`` sub-commands."""
    fmt = argparse.RawDescriptionHelpFormatter

    p = sub.add_parser(
        "partition", help="split meshes/volumes into spatial domains on disk",
        description="Read one or more meshes or volumes (each becomes one object / material "
                    "slot) and split them into spatial domains written as a STORE folder.",
        epilog=PARTITION_EPILOG.format(supported=" ".join(SUPPORTED)), formatter_class=fmt)
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="mesh or volume files")
    p.add_argument("-o", "--output", required=True, metavar="STORE", help="STORE folder to write")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--grid", type=parse_grid, metavar="AxBxC",
                     help="uniform grid of domains (default: 2x2x2)")
    how.add_argument("--domains", type=positive_int, metavar="N",
                     help="number of domains of a balanced k-d split")
    p.add_argument("--split", choices=("grid", "kd"),
                   help="grid (default) or kd; --domains implies kd")
    p.add_argument("--iso", type=float, metavar="VALUE", help="iso value for volume inputs")
    p.add_argument("--array", metavar="NAME",
                   help="VTK XML: the array isosurfaced (grids) or kept as the colouring "
                        "scalar (meshes); default the first one-component array")
    p.add_argument("--color-by", metavar="NAME",
                   help="VTK XML grids: the array sampled on the isosurface as its colouring "
                        "scalar (default: none)")
    p.add_argument("--brick", type=positive_int, default=DEFAULT_BRICK, metavar="CELLS",
                   help=f"marching-cubes brick edge in cells (default {DEFAULT_BRICK})")
    _add_simplify_option(p)
    _add_store_output_options(p)
    p.set_defaults(func=cmd_partition)

    g = sub.add_parser(
        "generate", help="make a procedural scientific scene straight into a store",
        description="Evaluate a procedural density field brick by brick, isosurface it and "
                    "write the triangles into the domains of a grid, without ever holding the "
                    "whole volume.", epilog=GENERATE_EPILOG, formatter_class=fmt)
    g.add_argument("scene", choices=sorted(SCENES))
    g.add_argument("-o", "--output", required=True, metavar="STORE", help="STORE folder to write")
    g.add_argument("--resolution", type=positive_int, required=True, metavar="N",
                   help="voxels per axis of the unit cube (64: ~tens of thousands of "
                        "triangles; 512: millions)")
    g.add_argument("--grid", type=parse_grid, default=DEFAULT_GRID, metavar="AxBxC",
                   help="domain grid (default 2x2x2)")
    g.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    g.add_argument("--brick", type=positive_int, default=DEFAULT_BRICK, metavar="CELLS",
                   help=f"brick edge in cells (default {DEFAULT_BRICK})")
    _add_simplify_option(g)
    _add_store_output_options(g)
    g.set_defaults(func=cmd_generate)

    s = sub.add_parser(
        "simplify", help="add the simplified whole-scene model to a store",
        description="Decimate every object of every domain of STORE by quadric edge collapse "
                    "and store the result as one resident whole-scene mesh (paper 6.1), "
                    "checksummed, with its triangle and memory rates in the manifest.",
        epilog=SIMPLIFY_EPILOG, formatter_class=fmt)
    s.add_argument("store", metavar="STORE")
    s.add_argument("--ratio", type=_ratio, required=True, metavar="RATIO",
                   help="fraction of the triangles kept, in (0, 1] (1: an identical copy)")
    s.add_argument("--min-faces", type=_count, default=DEFAULT_MIN_FACES, metavar="N",
                   help=f"keep object pieces with fewer triangles whole (default "
                        f"{DEFAULT_MIN_FACES})")
    s.add_argument("--force", action="store_true", help="replace an existing simplified model")
    s.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    s.set_defaults(func=cmd_simplify)

    i = sub.add_parser("info", help="describe a domain store",
                       description="Print a store's domains, totals, bounds and attributes.",
                       epilog="example:\n  vastray info bunny.store\n", formatter_class=fmt)
    i.add_argument("store", metavar="STORE")
    i.set_defaults(func=cmd_info)

    v = sub.add_parser("verify", help="check every file of a domain store, checksums included",
                       description="Read every domain of a store once and check it against its "
                                   "manifest and checksums. Prints one line per problem (the "
                                   "file, then what is wrong) and a summary.",
                       epilog=VERIFY_EPILOG, formatter_class=fmt)
    v.add_argument("store", metavar="STORE")
    v.add_argument("--quiet", action="store_true", help="no progress bar and no summary line")
    v.set_defaults(func=cmd_verify)


def cmd_partition(args) -> int:
    out = Path(args.output)
    check_replaceable(out, args.force)
    split = args.split or ("kd" if args.domains else "grid")
    if split == "kd" and not args.domains:
        raise InputError(None, "--split kd needs --domains N")
    if split == "grid" and args.domains:
        raise InputError(None, "--domains N needs --split kd (a grid takes --grid AxBxC)")
    if split == "grid" and args.grid is not None and math.prod(args.grid) > MAX_GRID_CELLS:
        raise InputError(None, f"--grid {'x'.join(map(str, args.grid))} is "
                               f"{math.prod(args.grid):,} cells; a partition grid may have at "
                               f"most {MAX_GRID_CELLS:,} (a store holds at most "
                               f"{MAX_DOMAINS:,} domains): use a coarser grid, or --domains N")
    if len(args.inputs) > np.iinfo(np.uint16).max:
        raise InputError(None, f"at most {np.iinfo(np.uint16).max} inputs")
    for name in args.inputs:
        if Path(name).is_dir():
            raise InputError(name, "is a store already; render it with `vastray render "
                                   f"{name}`" if is_store(Path(name)) else
                             "is a folder; give the mesh or volume files in it")

    progress = _show_progress(args)
    inputs = [read_input(p, iso=args.iso, brick=args.brick, progress=progress,
                         array=args.array, color_by=args.color_by) for p in args.inputs]
    for name, inp in zip(args.inputs, inputs, strict=True):
        check_extent(_world_box(inp.pieces), name, "partition it")
    meshes = [piece for inp in inputs for piece in inp.pieces]
    for name in ("scalars", "colors"):
        have = [getattr(m, name) is not None for m in meshes]
        if any(have) and not all(have):
            log.warning("only some inputs have per-vertex %s; dropped for the whole scene", name)
    several = len(inputs) > 1
    owner = [i for i, inp in enumerate(inputs) for _ in inp.pieces]
    mesh = meshops.concat(meshes, objects=owner if several else None)
    if several:  # each fits, but they may lie too far apart
        check_extent(_world_box([mesh]), out, "partition them")
    if all(inp.parallel for inp in inputs) and not (args.grid or args.domains or args.split):
        split = "pieces"
        piece = np.repeat(np.arange(len(meshes)), [m.n_triangles for m in meshes])
        part = partition_pieces(mesh, piece, len(meshes))
    elif split == "kd":
        _check_domain_count(args.domains, mesh.n_triangles)
        part = partition_kd(mesh, args.domains)
    else:
        part = partition_grid(mesh, args.grid or DEFAULT_GRID)

    objects = [{"name": Path(p).name, "source": str(Path(p).resolve())} for p in args.inputs]
    with StoreWriter(out, objects=objects, overwrite=args.force) as writer:
        for dom in part.domains:
            writer.add_domain(dom)
        writer.extra = {"partition": part.manifest_entry()}
        scalar_name = _scalar_name(inputs, mesh)
        if scalar_name is not None:
            writer.extra["scalar_name"] = scalar_name
    if not args.quiet:
        print(f"{out}: {mesh.n_triangles:,} triangles from {len(inputs)} input(s) in "
              f"{len(part.domains)} domains ({split})")
    _simplify_after(args, out)
    return 0


def _world_box(pieces) -> np.ndarray:
    """(2, 3) float64 box of the vertices of ``pieces`` (DomainArrays) with triangles, in
    world coordinates (their ``origin`` added)."""
    boxes = [np.stack([p.vertices.min(axis=0), p.vertices.max(axis=0)]).astype(np.float64)
             + (0.0 if p.origin is None else p.origin) for p in pieces if p.n_triangles]
    if not boxes:
        return np.zeros((2, 3))
    return np.stack([np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)])


#: Most cells of a ``--grid`` (each cell's box is built before the empty ones are dropped): ten
#: for each domain a store may hold, so a sparse surface may leave most cells empty.
MAX_GRID_CELLS = 10 * MAX_DOMAINS


#: Fewer triangles than this per domain on average and each domain's own costs (its file,
#: its Embree scene, its ray queues) outweigh its triangles.
FEW_TRIANGLES_PER_DOMAIN = 64


def _check_domain_count(domains: int, triangles: int) -> None:
    """Refuse more k-d domains than triangles; warn when they would hold only a few each."""
    if domains > triangles:
        raise InputError(None, f"--domains {domains:,} is more than the {triangles:,} "
                               "triangles of the input; ask for fewer domains")
    if triangles / domains < FEW_TRIANGLES_PER_DOMAIN:
        log.warning("--domains %s leaves about %d triangles per domain: each domain's own "
                    "costs will outweigh them; fewer domains render faster", f"{domains:,}",
                    triangles // domains)


def _scalar_name(inputs, mesh) -> str | None:
    """The name of the scene's scalar field (for the colour bar), where the inputs name it."""
    if mesh.scalars is None:
        return None
    names = [inp.scalar_name for inp in inputs if inp.scalar_name]
    if len(set(names)) > 1:
        log.warning("the inputs' scalars are different arrays (%s): one colour scale for all",
                    ", ".join(dict.fromkeys(names)))
        return " / ".join(dict.fromkeys(names))
    return names[0] if names else None


def cmd_generate(args) -> int:
    out = Path(args.output)
    check_replaceable(out, args.force)
    total = generate(args.scene, out, args.resolution, args.grid, seed=args.seed,
                     brick=args.brick, overwrite=args.force, progress=_show_progress(args))
    if not args.quiet:
        print(f"{out}: {args.scene} at {args.resolution}^3, {total:,} triangles "
              f"({'x'.join(map(str, args.grid))} grid)")
    _simplify_after(args, out)
    return 0


def cmd_simplify(args) -> int:
    """``vastray simplify STORE --ratio R``: build and store the simplified model."""
    store = Store(args.store)
    result = build_simplified(store, args.ratio, min_faces=args.min_faces, force=args.force,
                              progress=_show_progress(args))
    if not args.quiet:
        print(result.summary(store.path))
    return 0


def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"


def _box(lo, hi, digits: int = 4) -> str:
    return ("[" + " ".join(f"{v:.{digits}g}" for v in lo) + "] .. ["
            + " ".join(f"{v:.{digits}g}" for v in hi) + "]")


def cmd_info(args) -> int:
    store = Store(args.store)
    m = store.manifest
    print(f"store: {store.path}  ({m['format']} v{m['version']})")
    lines = [f"{'id':>5} {'triangles':>12} {'vertices':>12} {'bytes':>10}  bounds"]
    for d in store.domains:
        lines.append(f"{d.id:>5} {d.n_triangles:>12,} {d.n_vertices:>12,} "
                     f"{_size(d.nbytes):>10}  {_box(d.lo, d.hi)}")
    print("\n".join(lines))
    n_vert = sum(d.n_vertices for d in store.domains)
    n_bytes = sum(d.nbytes for d in store.domains)
    print(f"total: {len(store.domains)} domains, {store.n_triangles:,} triangles, "
          f"{n_vert:,} vertices, {_size(n_bytes)}")
    lo, hi = store.world_bounds
    print(f"scene bounds: {_box(lo, hi, digits=4 if not store.origin.any() else 10)}")
    if store.origin.any():  # domain boxes above are relative to it
        print(f"frame origin: ({', '.join(f'{c:.9g}' for c in store.origin)}); domain boxes "
              "are relative to it")
    attrs = [a for a in ATTRIBUTES if m.get("attributes", {}).get(a)]
    extra = f" (scalar range {store.scalar_range[0]:.4g} .. {store.scalar_range[1]:.4g})" \
        if store.scalar_range else ""
    print(f"attributes: {', '.join(attrs) if attrs else 'none'}{extra}")
    print("objects: " + ", ".join(o.get("name", "?") for o in store.objects))
    part = m.get("partition")
    if part:
        how = "x".join(map(str, part["grid"])) if "grid" in part else f"{part.get('domains')}"
        print(f"partition: {part.get('method')} {how}")
    gen = m.get("generator")
    if gen:
        print(f"generator: {gen['scene']} resolution {gen['resolution']} seed {gen['seed']}")
    simp = store.simplified
    if simp is not None:
        print(f"simplified: {simp.n_triangles:,} triangles, {simp.n_vertices:,} vertices, "
              f"{_size(simp.nbytes)}; triangle rate {simp.rate:.2%} (asked {simp.ratio:.2%}, "
              f"pieces under {simp.min_faces:,} triangles kept whole), memory rate "
              f"{simp.memory_rate:.2%}")
    return 0


def cmd_verify(args) -> int:
    """``vastray verify STORE``: one line per problem, a summary; 0 when sound, else 2."""
    from tqdm import tqdm

    result = verify_store(args.store, progress=_show_progress(args),
                          report=lambda problem: tqdm.write(str(problem)))
    if not args.quiet:
        print(result.summary())
    return 0 if result.ok else 2
