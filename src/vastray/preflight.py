"""Checks made before a render starts, so that a run that cannot finish fails in a second with a
one-line error instead of after the whole frame: output paths, and the memory the processes,
their films, paths in flight, outputs and domains will take against the memory this machine
has free (less a margin for the rest of the machine)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vastray.processes import proc_bytes
from vastray.render.film import FILM_BYTES_PER_PIXEL
from vastray.render.imageio import check_image_path
from vastray.scene.errors import InputError
from vastray.scene.footprint import (
    build_bytes,
    domain_footprints,  # noqa: F401  (the plan's, and its importers')
)

# The memory model: one process's peak resident memory is
#   base + pixels x bytes per pixel + paths in flight x (PATH_BYTES + shadow rays per hit x
#   SHADOW_RAY_BYTES) + the domains it holds.
# Every constant below was measured as peak RSS (VmHWM) of `vastray render` processes on
# the generated store `vastray generate rm --resolution 64 --grid 2x2x2` and the built-in
# scene (2-core, 24 GiB machine, Python 3.11, numpy 2, numba); `bench/memory.py` re-measures
# them and prints estimate / measured peak for every case (bench/README.md has the table): the
# estimate is within 0.8-1.5 of every measured peak there. A scene whose paths bounce more or
# whose materials shade more may use more per path than these two.

#: Resident bytes of a rendering process (single-process render or node) before its image:
#: the interpreter, numpy, numba's compiled kernels and Embree. Measured: 183-197 MB peak at
#: 64x64, 1 spp, 1 thread on the rm store, less its 6 MB of domains and 4096 paths, run on its
#: own; 255 MB in the same virtual environment at the end of a CI run (`.ci/run`; the cause
#: was not found: not the numba cache, not the bench's own peak). The constant sits between,
#: so that both stay within 0.8-1.5.
BASE_BYTES = 205_000_000

#: What a ``--memory-limit`` plan keeps back beyond the estimate's base (``cache_room``,
#: ``check_owned_fit``), so that the limit bounds the measured peak and is not only its central
#: estimate: the base measured 255 MB at the end of a CI run against ``BASE_BYTES`` (a render
#: under a limit that left it out peaked at 253 MB against 212 MB there), plus a margin. A few
#: tens of MB, nothing beside the gigabytes of domains a limit is for.
LIMIT_BASE_MARGIN = 75_000_000

#: Resident bytes of the coordinator of a ``--nodes`` render before its image (it loads no
#: Embree scene and traces nothing). Measured: 141-147 MB peak at 256x256 with 2 nodes, less
#: its 65,536 pixels, on its own; 220 MB at the end of a CI run (as above).
COORDINATOR_BASE_BYTES = 160_000_000

#: Film bytes per pixel when the figures below were measured (before issue 41's batches): a
#: larger film adds its growth once per copy each process holds.
_MEASURED_FILM_BYTES = 72
_FILM_GROWTH = FILM_BYTES_PER_PIXEL - _MEASURED_FILM_BYTES

#: Bytes per pixel of the process that makes the outputs, besides the film
#: (``FILM_BYTES_PER_PIXEL``): the image so far and its merged copy between passes, the mean
#: and variance temporaries (float64), the float32 image, depth and normal layers and the
#: encoder's copy. Measured: the peak grows by 179 B per pixel from 1024x1024 to 2048x2048
#: (1 spp, 1 thread: the paths in flight stay one batch), film included.
OUTPUT_BYTES_PER_PIXEL = 180 - _MEASURED_FILM_BYTES + 2 * _FILM_GROWTH

#: Bytes per pixel of a node besides its film: the film's encoded copy sent to the
#: coordinator. Measured: 207 B per pixel from 256x256 to 1024x1024 (2 nodes, image).
NODE_BYTES_PER_PIXEL = 210 - _MEASURED_FILM_BYTES + _FILM_GROWTH

#: Bytes per pixel of the coordinator: the films it receives, their merge and the outputs.
#: Measured: 240 B per pixel from 256x256 to 1024x1024 (2 nodes).
COORDINATOR_BYTES_PER_PIXEL = 240 + 3 * _FILM_GROWTH

#: Bytes per pixel of ``--reference``: the image read and the error computed against it.
#: Measured: +126 B per pixel at 2048x2048 against the same render without it.
REFERENCE_BYTES_PER_PIXEL = 130

#: Bytes per path in flight besides its shadow rays: path state, the radiance and
#: continuation rays of its wavefront, Embree's hit records, and the heap's high-water mark
#: over batch after batch (a render of many batches peaks up to 2x above one batch's working
#: set: the same 65,536 paths of rm at 256x256, 1 thread, 233 MB peak for 1 spp, 281 MB for
#: 16). Measured where every camera path hits (the built-in scene, 3 shadow rays per hit):
#: 850 B per path at 512x512 x 8 spp with 1 thread, 1,130 B with 2 (131,072 paths); 420 B in
#: spec-ooc's single tile of 262,144 paths. The value keeps those within the range below.
PATH_BYTES = 600

#: Bytes per path in flight for each shadow ray a hit spawns (origin, direction, t_max,
#: contribution, the shading temporaries and the occlusion query). Measured: the slope of
#: spec-ooc's peak over 262,144 paths (256x256 x 4 spp, 1 thread) between 3 and 17 shadow
#: rays per hit, 64 B on the built-in scene and 60 B on rm (where not every path hits); set
#: lower since PATH_BYTES already covers the batches' high water (AO, 16 rays and no bounce,
#: would otherwise be over-estimated 1.5x on rm).
SHADOW_RAY_BYTES = 45

#: spec-ooc's speculative copies: every shadow ray is queued into each domain it enters, and
#: one that enters more than ``SPECULATION_FREE_CROSSINGS`` domains costs this much more per
#: copy held (``speculative_copies``). Measured on `rm --resolution 256` at 256x256 x 4 spp
#: (17 shadow rays per hit, 3 bounces; `bench/memory.py`'s fine stores): the peak's bytes per
#: path were about 950-1,270 on grids 2x2x2-5x4x2 (a ray leaving the surface enters 1.7-2.6
#: domains), 1,780 at 6x6x4 (2.9) and 2,010 at 8x8x4 (3.3), against 1,365 in the model
#: without this term; with it the model is 1.1x the last two, 1.3-1.5x the others.
SPECULATIVE_COPY_BYTES = 16

#: Domains a ray leaving the surface may enter before spec-ooc's copies of it outgrow what
#: ``PATH_BYTES`` and ``SHADOW_RAY_BYTES`` already hold.
SPECULATION_FREE_CROSSINGS = 2.2

#: The most paths in flight the per-path constants above were fitted on: spec-ooc's single
#: tile of 262,144 paths (``DEFAULT_SAMPLES_IN_FLIGHT``). A larger tile (``--max-samples-in-
#: flight``) charges each path beyond these ``TAIL_PATH_SHARE`` of the per-path bytes.
CALIBRATED_PATHS = 262_144

#: Share of the per-path bytes that each path in flight beyond ``CALIBRATED_PATHS`` adds. The
#: per-path constants carry the heap's high water over batch after batch, which does not grow
#: with the tile: measured at 1024x1024 x 1 spp (PT, 3 bounces, 17 shadow rays per hit) as the
#: peak RSS of a 1,048,576-path tile less that of a smaller one, the same render otherwise,
#: a path beyond the first costs 230 B (``image``) and 690 B (``spec-ooc``) on
#: `rm --resolution 1600 --grid 6x6x2` (from 65,536 paths), 161 B and 414 B on
#: `rm --resolution 128 --grid 4x4x2` (from 262,144): 12-17 % and 20-29 % of the model's
#: 1,360 and 2,000-2,360 B. Half keeps the estimate above them with a margin of 1.7 or more;
#: the full per-path bytes kept 2.2 GiB for about 0.6 GiB of paths on the README's 100 M
#: store, so its 6 GiB budget held 16 of 72 domains with 3.3 GiB used.
TAIL_PATH_SHARE = 0.5

#: Share of ``MemAvailable`` a render may plan to use: the rest is left to the rest of the
#: machine (other processes, the page cache the domains are read through) and to the
#: estimate's own error (bench/memory.py: estimate / measured within 0.8-1.5).
MEMORY_HEADROOM = 0.85


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a render will hold at its peak, by part (one process, or summed over several).

    ``film``: the film's per-pixel sums; ``paths``: the paths in flight and their rays;
    ``outputs``: the other per-pixel arrays (merges, outputs, reference); ``base``: the
    processes' interpreter and libraries; ``domains``: the loaded domains.
    """

    film: int
    paths: int
    outputs: int
    base: int = 0
    domains: int = 0

    @property
    def total(self) -> int:
        return self.film + self.paths + self.outputs + self.base + self.domains

    def __add__(self, other: MemoryEstimate) -> MemoryEstimate:
        return MemoryEstimate(self.film + other.film, self.paths + other.paths,
                              self.outputs + other.outputs, self.base + other.base,
                              self.domains + other.domains)

    def times(self, n: int) -> MemoryEstimate:
        """The estimate of ``n`` processes like this one."""
        return MemoryEstimate(self.film * n, self.paths * n, self.outputs * n,
                              self.base * n, self.domains * n)

    def breakdown(self) -> str:
        """``base 0.2 GB, film 10 MB, ...``: the parts, for an error message."""
        parts = {"base": self.base, "film": self.film, "outputs": self.outputs,
                 "paths in flight": self.paths, "domains": self.domains}
        return ", ".join(f"{name} {gigabytes(n)}" for name, n in parts.items() if n)


@dataclass(frozen=True)
class RenderMemory:
    """What the preflight expects of a render: ``process``, the peak of one rendering process
    (the single process, or each node) with its domains; ``coordinator``, the coordinator's
    with ``--nodes`` (else None); ``machine``, every process started on this machine."""

    process: MemoryEstimate
    coordinator: MemoryEstimate | None
    machine: MemoryEstimate


def estimate_memory(width: int, height: int, paths_in_flight: int, shadow_rays_per_hit: int,
                    role: str = "render", reference: bool = False,
                    domains: int = 0, copies: float = 0.0) -> MemoryEstimate:
    """The peak memory of one process of a render.

    Parameters
    ----------
    width, height : image size.
    paths_in_flight : paths this process traces at once (batch x render workers, or its tile;
        those beyond ``CALIBRATED_PATHS`` are charged ``TAIL_PATH_SHARE`` each).
    shadow_rays_per_hit : shadow rays one hit spawns (lights x shadow samples, AO rays).
    role : ``"render"`` (a single-process render, which also writes the outputs),
        ``"node"`` (a node of ``--nodes``) or ``"coordinator"`` (traces nothing).
    reference : ``--reference`` is read and compared against (where the outputs are made).
    domains : bytes of the domains this process holds at once (``domain_footprints``).
    copies : spec-ooc's extra copies of each shadow ray per path (``speculative_copies``).
    """
    pixels = int(width) * int(height)
    if role == "coordinator":
        return MemoryEstimate(film=pixels * FILM_BYTES_PER_PIXEL, paths=0,
                              outputs=pixels * (COORDINATOR_BYTES_PER_PIXEL
                                                - FILM_BYTES_PER_PIXEL
                                                + REFERENCE_BYTES_PER_PIXEL * reference),
                              base=COORDINATOR_BASE_BYTES)
    if role not in ("render", "node"):
        raise ValueError(f"unknown role {role!r}")
    per_pixel = (NODE_BYTES_PER_PIXEL if role == "node"
                 else OUTPUT_BYTES_PER_PIXEL + REFERENCE_BYTES_PER_PIXEL * reference)
    per_path = int(PATH_BYTES + shadow_rays_per_hit * (SHADOW_RAY_BYTES
                                                       + copies * SPECULATIVE_COPY_BYTES))
    return MemoryEstimate(film=pixels * FILM_BYTES_PER_PIXEL,
                          paths=int(charged_paths(int(paths_in_flight)) * per_path),
                          outputs=pixels * per_pixel, base=BASE_BYTES, domains=int(domains))


def charged_paths(paths_in_flight: int) -> float:
    """Paths in flight as the per-path bytes charge them: every one up to
    ``CALIBRATED_PATHS``, ``TAIL_PATH_SHARE`` of each beyond."""
    head = min(paths_in_flight, CALIBRATED_PATHS)
    return head + TAIL_PATH_SHARE * (paths_in_flight - head)


def crossings_from_surface(lo: np.ndarray, hi: np.ndarray, weight: np.ndarray,
                           rays: int = 4096) -> float:
    """Mean number of domains a ray leaving the surface enters: rays from random points of
    the boxes (chosen by ``weight``, their triangles), in random directions, to infinity.
    A fixed seed: the same store always gives the same number.

    Parameters
    ----------
    lo, hi : (D, 3) domain boxes; weight : (D,) triangles per domain.
    """
    from vastray.schedule.geometry import DomainGeometry

    weight = np.asarray(weight, np.float64)
    if len(lo) < 2 or not weight.sum() > 0:
        return 1.0
    rng = np.random.default_rng(0)
    box = rng.choice(len(lo), rays, p=weight / weight.sum())
    origin = lo[box] + rng.random((rays, 3)) * (hi[box] - lo[box])
    direction = rng.normal(size=(rays, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    geometry = DomainGeometry(lo, hi, weight > 0, float(np.abs(origin).max()) + 1.0)
    ray = geometry.crossings(origin.astype(np.float32), direction.astype(np.float32),
                             np.full(rays, np.inf, np.float32))[0]
    return max(1.0, len(ray) / rays)


def speculative_copies(crossings: float, vertices: int) -> float:
    """spec-ooc's copies of a path's shadow rays beyond what the per-path constants hold:
    ``vertices`` (path vertices that cast shadow rays) times the domains a ray enters
    (``crossings_from_surface``) beyond ``SPECULATION_FREE_CROSSINGS``."""
    return max(0.0, crossings - SPECULATION_FREE_CROSSINGS) * vertices


def reference_paths_in_flight(paths: int, batch_size: int, threads: int,
                              all_domains_fit: bool) -> int:
    """Paths the single-process ``reference`` renderer traces at once: a batch on each render
    worker (one per thread when every domain fits, else one), its batch cut so that a pass
    of fewer paths still gives every worker two (as ``render.driver.render`` does)."""
    workers = threads if all_domains_fit and threads > 1 else 1
    batch = max(1, batch_size)
    if workers > 1:
        batch = min(batch, -(-paths // (2 * workers)))
    return min(paths, batch * workers)


def available_memory() -> int | None:
    """Bytes the kernel says can be allocated without swapping (``MemAvailable``), or None."""
    available = proc_bytes("/proc/meminfo", "MemAvailable")
    if available is not None:
        return available
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


#: The binary units sizes are read in (``parse_size``) and printed in (``gigabytes``).
BINARY_UNITS = {"K": ("KiB", 1 << 10), "M": ("MiB", 1 << 20), "G": ("GiB", 1 << 30),
                "T": ("TiB", 1 << 40)}


def gigabytes(n: int) -> str:
    """``700 MiB``, ``1.5 GiB``: bytes in the binary units ``--memory-limit`` is read in (its
    K, M, G and T are KiB, MiB, GiB and TiB), so that a limit is printed as it was given."""
    for name, factor in reversed(BINARY_UNITS.values()):
        if n >= factor:
            value = n / factor
            text = f"{value:.1f}".removesuffix(".0") if factor >= 1 << 30 else f"{value:.0f}"
            return f"{text} {name}"
    return f"{int(n)} B"


def physical_memory() -> int | None:
    """Bytes of memory this machine has (``MemTotal``), or None where it cannot be read."""
    total = proc_bytes("/proc/meminfo", "MemTotal")
    if total is not None:
        return total
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_limit_fits_machine(limit: int, physical: int | None = None) -> None:
    """Refuse a ``--memory-limit`` larger than this machine's memory (a typo such as ``1T``
    for ``1G``): the processes it bounds run here, so it could never bind.

    Parameters
    ----------
    physical : bytes of memory (default: ``physical_memory()``; None there: no check).
    """
    physical = physical_memory() if physical is None else physical
    if physical is not None and limit > physical:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} is more than this "
                               f"machine's {gigabytes(physical)} of memory; give a smaller "
                               "one (K, M, G, T are KiB, MiB, GiB, TiB)")


def check_memory(estimate: MemoryEstimate, width: int, height: int,
                 available: int | None = None) -> None:
    """Refuse a render whose estimate exceeds ``MEMORY_HEADROOM`` of the available memory:
    the rest is left to the machine and to the estimate's error.

    Parameters
    ----------
    estimate : the whole render on this machine (every process it starts here).
    available : bytes available (default: ``available_memory()``; None there: no check).

    Raises
    ------
    InputError
        Naming the sizes, the margin and what to lower.
    """
    available = available_memory() if available is None else available
    if available is None:
        return
    usable = int(available * MEMORY_HEADROOM)
    if estimate.total <= usable:
        return
    kept = round(100 * (1 - MEMORY_HEADROOM))
    raise InputError(None, f"a {width}x{height} render needs about "
                           f"{gigabytes(estimate.total)} ({estimate.breakdown()}) but only "
                           f"{gigabytes(usable)} of the {gigabytes(available)} available "
                           f"may be used ({kept}% is kept for the rest of the machine); "
                           "render a smaller --width/--height, use fewer --threads or "
                           "--nodes, lower --batch-size or --max-samples-in-flight, or bound "
                           "the domains held with --memory-limit or --cache")


def parse_size(text: str) -> int:
    """``"8G"``, ``"512M"``, ``"1.5GiB"``, ``"100000"`` -> bytes: K, M, G and T (with or without
    ``iB`` or ``B``) are KiB, MiB, GiB and TiB, powers of 1024, as ``gigabytes`` prints them."""
    units = {"": 1, **{unit: factor for unit, (_, factor) in BINARY_UNITS.items()}}
    upper = text.strip().upper().removesuffix("B").removesuffix("I")
    number, unit = (upper[:-1], upper[-1]) if upper[-1:] in units and upper[-1:] else (upper, "")
    try:
        value = float(number) * units[unit]
    except (ValueError, KeyError):
        raise ValueError(f"expected a size such as 8G, 512M or 100000 (K, M, G, T: KiB, MiB, "
                         f"GiB, TiB), got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"a size must be positive and finite, got {text!r}")
    return int(value)


def domain_build_bytes(domains, reads_ahead: bool = False) -> int:
    """Bytes a process's domain builds add at their peak (``scene.footprint.build_bytes``: two
    builds of the largest domain at once), on top of the domains it holds; ``reads_ahead``
    (a cache smaller than the store): also the arrays of two reads ahead
    (``DomainCache.read_ahead``: one a started load will take, one unclaimed)."""
    building = build_bytes(max((int(d.n_triangles) for d in domains), default=0))
    if reads_ahead:
        building += 2 * max((int(d.nbytes) for d in domains), default=0)
    return building


def cache_room(limit: int, fixed: MemoryEstimate, footprints: list[int], width: int,
               height: int, building: int = 0, smallest: int | None = None) -> int:
    """Bytes a process can give its domains under ``limit`` besides its film, paths and
    outputs (``fixed``), the builds in progress (``building``, ``domain_build_bytes``) and
    ``LIMIT_BASE_MARGIN``.

    ``smallest``: the smallest limit the render would accept (``smallest_limit``), named in
    the error; default: ``fixed`` and the largest domain.

    Raises
    ------
    InputError
        When even the film and paths, or those plus the largest domain, exceed the limit.
    """
    planned = fixed.total + LIMIT_BASE_MARGIN + building
    room = limit - planned
    smallest = limit_option(planned + max(footprints, default=0) if smallest is None
                            else smallest)
    if room <= 0:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} is too small: a "
                               f"{width}x{height} render needs {gigabytes(planned)} per process "
                               f"before any domain ({fixed.breakdown()}, domain builds "
                               f"{gigabytes(building)}, margin "
                               f"{gigabytes(LIMIT_BASE_MARGIN)}); the smallest that fits is "
                               f"{smallest}; or lower --width/--height, --threads or "
                               "--max-samples-in-flight")
    if max(footprints, default=0) > room:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} leaves {gigabytes(room)} "
                               f"for domains, but the largest needs "
                               f"{gigabytes(max(footprints))}; the smallest that fits is "
                               f"{smallest}, or partition finer")
    return room


def smallest_limit(in_core: MemoryEstimate, out_of_core: MemoryEstimate,
                   footprints: list[int], building: int = 0) -> int:
    """The smallest ``--memory-limit`` (bytes) ``cache_room`` accepts: every domain held with
    the process's in-core estimate, or the largest domain held with its out-of-core one (its
    paths in flight can differ), whichever is less. (The error once named a limit computed
    for one case, which the other then refused, naming a larger one.)"""
    base = LIMIT_BASE_MARGIN + building
    largest = max(footprints, default=0)
    all_held = in_core.total + base + sum(footprints)
    one_held = max(in_core.total, out_of_core.total) + base + largest
    return min(all_held, one_held)


def fitting_count(room: int, footprints: list[int], largest_first: bool = True) -> int:
    """How many domains fit in ``room`` bytes: counted with the largest first (any choice of
    that many fits), or with the smallest first (the most a cache bounded by bytes can hold)."""
    held, count = 0, 0
    for size in sorted(footprints, reverse=largest_first):
        if held + size > room:
            break
        held, count = held + size, count + 1
    return count


def limit_option(nbytes: int) -> str:
    """``--memory-limit 735M``: the option that allows ``nbytes``, rounded up to a MiB."""
    return f"--memory-limit {math.ceil(nbytes / 2**20)}M"


def check_owned_fit(limit: int, fixed: MemoryEstimate, footprints: list[int], owner,
                    nodes: int, building: int = 0) -> None:
    """Check that every node can hold all the domains it owns under ``limit`` besides its film
    and paths (``fixed``): in situ (``spec-insitu``) a node keeps its domains loaded, so the
    limit cannot be met by evicting. The extra holders of the domains crossed most
    (``ownership.insitu_holders``) never leave a node more than the node owning the most,
    so this check of the owners covers them.

    Parameters
    ----------
    footprints : (D,) bytes of each domain; owner : (D,) owning node of each domain.
    building : bytes the domain builds add at their peak (``domain_build_bytes``).

    Raises
    ------
    InputError
        Naming the node that needs the most, what it needs, and what to change.
    """
    held = [0] * nodes
    for size, node in zip(footprints, owner, strict=True):
        held[int(node)] += size
    worst = max(range(nodes), key=held.__getitem__)
    planned = fixed.total + LIMIT_BASE_MARGIN + building
    if planned + held[worst] > limit:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} is too small for "
                               f"--scheduler spec-insitu: node {worst} keeps its domains "
                               f"loaded, {gigabytes(held[worst])}, besides "
                               f"{gigabytes(planned)} for the rest of the process; raise it, "
                               "give more --nodes, or use --scheduler async (whose caches "
                               "evict)")


def _nearest_existing(path: Path) -> Path:
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_output_paths(image: str, png: str | None, report: str | None) -> list[Path]:
    """Check every output before any work: formats, folders in the way or missing (they are
    not created), writable places, and no two outputs on one path. Returns the paths in the
    order they will be written.

    Raises
    ------
    InputError
        Naming the path and the problem.
    """
    paths = [check_image_path(image, "-o")]
    if png is not None:
        if Path(png).suffix.lower() != ".png":
            raise InputError(png, "--png needs a file name ending in .png")
        paths.append(check_image_path(png, "--png"))
    if report is not None:
        if Path(report).is_dir():
            raise InputError(report, "--report is a folder; give a file name such as "
                                     f"{Path(report) / 'report.json'}")
        if Path(report).suffix.lower() != ".json":
            raise InputError(report, "--report writes JSON: give a file name ending in .json")
        paths.append(Path(report))
    resolved = [p.resolve() for p in paths]
    if len(set(resolved)) != len(resolved):
        raise InputError(None, "-o, --png and --report must name different files")
    options = ["-o", *["--png"] * (png is not None), *["--report"] * (report is not None)]
    for path, option in zip(paths, options, strict=True):
        check_writable_place(path, option)
    return paths


def check_writable_place(path: Path, option: str) -> None:
    """Refuse ``path`` (given as ``option``) where its folder is missing (never created: a typo
    would be), is a file, or cannot be written in.

    Raises
    ------
    InputError
        Naming the path and the problem.
    """
    parent = _nearest_existing(path.parent)
    if not parent.is_dir():
        raise InputError(path, f"cannot be written: {parent} is not a folder")
    if parent != path.parent.absolute():
        raise InputError(path, f"{option}'s folder {path.parent} does not exist (create "
                               f"it first, e.g. mkdir -p {path.parent})")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(path, f"cannot be written: no permission to write in {parent}")


def check_inputs_spared(outputs: list[Path], store: str | Path | None,
                        references: list[Path] = (), checkpoint: Path | None = None,
                        resume: str | Path | None = None) -> None:
    """Refuse, before any work, a render whose files would land on what it reads or keeps:
    an output or the checkpoint inside the store being rendered (a report written over its
    manifest left the store unreadable), an output on the image it is compared with
    (``--reference``), the checkpoint on an output or the reference (a checkpoint file is
    removed when the render ends), or the checkpoint over a file that is not a vastray
    checkpoint.

    Parameters
    ----------
    outputs : every file the render writes (image, PNG, report; an animation's every frame).
    store : the store rendered (None: the built-in scene).
    references : the reference images read (one a frame).
    checkpoint : where checkpoints would be written (None: none can be); ``resume``, the
        checkpoint resumed, may be that same file.

    Raises
    ------
    InputError
        Naming the file, what it would overwrite, and what to do.
    """
    from vastray.checkpoint import is_checkpoint

    store_dir = None if store is None else Path(store).resolve()
    compared = {Path(r).resolve() for r in references}
    written = [("output", p) for p in outputs]
    if checkpoint is not None:
        written.append(("checkpoint", Path(checkpoint)))
    for kind, path in written:
        where = path.resolve()
        if store_dir is not None and (where == store_dir or store_dir in where.parents):
            raise InputError(path, f"is inside the store being rendered ({store}): writing "
                                   f"the {kind} there would damage the store; write it "
                                   "elsewhere")
        if where in compared:
            raise InputError(path, f"is the --reference image the render is compared with: "
                                   f"the {kind} would replace it; write it elsewhere")
    if checkpoint is None:
        return
    check_writable_place(Path(checkpoint), "--checkpoint")
    where = Path(checkpoint).resolve()
    if where in {p.resolve() for p in outputs}:
        raise InputError(checkpoint, "--checkpoint names one of the render's outputs (-o, "
                                     "--png, --report): the checkpoint would be written over "
                                     "it and removed when the render ends; give another file")
    resumed = resume is not None and Path(resume).resolve() == where
    if where.exists() and not resumed and not is_checkpoint(where):
        raise InputError(checkpoint, "exists and is not a vastray checkpoint: a checkpoint "
                                     "written there would replace it, and be removed when the "
                                     "render ends; move it or give another --checkpoint")
