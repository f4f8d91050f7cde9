"""Checks made before a render starts, so that a run that cannot finish fails in a second with a
one-line error instead of after the whole frame: output paths, and the memory the film, the
paths in flight and the outputs will take against the memory this machine has free."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from vastray.render.film import FILM_BYTES_PER_PIXEL
from vastray.render.imageio import check_image_path
from vastray.scene.errors import InputError

#: Bytes per pixel while the outputs are made: the float32 image, depth and normal layers, the
#: float64 mean they are computed from, and the encoder's copy.
OUTPUT_BYTES_PER_PIXEL = 28 + 24 + 28

#: Bytes of path state (pixel, sample, throughput, radiance, first hit) per path in flight.
PATH_BYTES = 96

#: Bytes of one ray in a batch: origin, direction, t_max, keys, throughput, carried radiance,
#: plus the hit record and the temporaries of shading it.
RAY_BYTES = 160


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a render will hold at its peak, by part (all on one machine)."""

    film: int
    paths: int
    outputs: int

    @property
    def total(self) -> int:
        return self.film + self.paths + self.outputs


def estimate_memory(width: int, height: int, paths_in_flight: int, shadow_rays_per_hit: int,
                    processes: int = 1) -> MemoryEstimate:
    """The memory of a render at its peak.

    Parameters
    ----------
    width, height : image size.
    paths_in_flight : paths traced at once over all processes (batch x workers, or tiles).
    shadow_rays_per_hit : shadow rays one hit spawns (lights x shadow samples, AO rays).
    processes : films held at once: one per node process plus the coordinator's.
    """
    pixels = int(width) * int(height)
    per_path = PATH_BYTES + (2 + int(shadow_rays_per_hit)) * RAY_BYTES
    return MemoryEstimate(film=pixels * FILM_BYTES_PER_PIXEL * int(processes),
                          paths=int(paths_in_flight) * per_path,
                          outputs=pixels * OUTPUT_BYTES_PER_PIXEL)


def available_memory() -> int | None:
    """Bytes the kernel says can be allocated without swapping (``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def gigabytes(n: int) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.0f} MB"


def check_memory(estimate: MemoryEstimate, width: int, height: int,
                 available: int | None = None) -> None:
    """Refuse a render whose estimate exceeds the available memory.

    Raises
    ------
    InputError
        Naming the sizes and what to lower.
    """
    available = available_memory() if available is None else available
    if available is None or estimate.total <= available:
        return
    raise InputError(None, f"a {width}x{height} render needs about "
                           f"{gigabytes(estimate.total)} (film {gigabytes(estimate.film)}, paths "
                           f"in flight {gigabytes(estimate.paths)}, outputs "
                           f"{gigabytes(estimate.outputs)}) but only {gigabytes(available)} "
                           "is available; lower --width/--height, --batch-size or "
                           "--max-samples-in-flight, or use fewer --nodes")


#: Bytes a loaded domain holds per triangle besides its arrays: Embree's copy of the mesh and
#: its BVH (the estimate ``DomainBVH.nbytes`` reports).
BVH_BYTES_PER_TRIANGLE = 36 + 12 + 64


def parse_size(text: str) -> int:
    """``"8G"``, ``"512M"``, ``"1.5G"``, ``"100000"`` -> bytes (powers of 1024)."""
    units = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
    text = text.strip().upper().removesuffix("B").removesuffix("I")
    number, unit = (text[:-1], text[-1]) if text[-1:] in units and text[-1:] else (text, "")
    try:
        value = float(number) * units[unit]
    except (ValueError, KeyError):
        raise ValueError(f"expected a size such as 8G, 512M or 100000, got {text!r}") from None
    if not value > 0:
        raise ValueError(f"a size must be positive, got {text!r}")
    return int(value)


def domain_footprints(domains) -> list[int]:
    """Bytes each domain holds once loaded: its arrays plus Embree's mesh and BVH."""
    return [int(d.nbytes) + int(d.n_triangles) * BVH_BYTES_PER_TRIANGLE for d in domains]


def cache_within(limit: int, fixed: MemoryEstimate, footprints: list[int], width: int,
                 height: int) -> int:
    """The most domains a process can hold under ``limit`` besides its film, paths and
    outputs (``fixed``): counted with the largest domains, so any choice of that many fits.

    Raises
    ------
    InputError
        When even the film and paths, or those plus the largest domain, exceed the limit.
    """
    room = limit - fixed.total
    if room <= 0:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} is too small: a "
                               f"{width}x{height} render needs {gigabytes(fixed.total)} for "
                               "its film and paths in flight before any domain; raise it, or "
                               "lower --width/--height or --max-samples-in-flight")
    held, count = 0, 0
    for size in sorted(footprints, reverse=True):
        if held + size > room:
            break
        held, count = held + size, count + 1
    if count == 0:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} leaves {gigabytes(room)} "
                               f"for domains, but the largest needs "
                               f"{gigabytes(max(footprints))}; raise it or partition finer")
    return count


def check_owned_fit(limit: int, fixed: MemoryEstimate, footprints: list[int], owner,
                    nodes: int) -> None:
    """Check that every node can hold all the domains it owns under ``limit`` besides its film
    and paths (``fixed``): in situ (``spec-insitu``) a node keeps its domains loaded, so the
    limit cannot be met by evicting.

    Parameters
    ----------
    footprints : (D,) bytes of each domain; owner : (D,) owning node of each domain.

    Raises
    ------
    InputError
        Naming the node that needs the most, what it needs, and what to change.
    """
    held = [0] * nodes
    for size, node in zip(footprints, owner, strict=True):
        held[int(node)] += size
    worst = max(range(nodes), key=held.__getitem__)
    if fixed.total + held[worst] > limit:
        raise InputError(None, f"--memory-limit {gigabytes(limit)} is too small for "
                               f"--scheduler spec-insitu: node {worst} keeps its domains "
                               f"loaded, {gigabytes(held[worst])}, besides "
                               f"{gigabytes(fixed.total)} for its film and paths; raise it, "
                               "give more --nodes, or use --scheduler async (whose caches "
                               "evict)")


def _nearest_existing(path: Path) -> Path:
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_output_paths(image: str, png: str | None, report: str | None) -> list[Path]:
    """Check every output before any work: formats, folders in the way, writable places,
    and no two outputs on one path. Returns the paths in the order they will be written.

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
        paths.append(Path(report))
    resolved = [p.resolve() for p in paths]
    if len(set(resolved)) != len(resolved):
        raise InputError(None, "-o, --png and --report must name different files")
    for path in paths:
        parent = _nearest_existing(path.parent)
        if not parent.is_dir():
            raise InputError(path, f"cannot be written: {parent} is not a folder")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(path, f"cannot be written: no permission to write in {parent}")
    return paths
