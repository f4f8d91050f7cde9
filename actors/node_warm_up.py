"""A node's first use, paid as it starts rather than in its first frame.

A fresh process pays twice before its traces run at speed: numba's set-up (its registries,
``render.kernels.warm_up``, 0.5-0.8 s of CPU) and the first call of every compiled kernel
and code path a render runs (each kernel's machine code loaded from numba's cache, Embree's
device, first allocations). Measured on the turbine-blade scan on one node (session 31,
bench/README): a fresh node's first ten activations cost 49 ms (``image``) to 83 ms
(``async``) more CPU than the same activations later; 8 nodes sharing 2 cores pay it
serially inside the job's busy span.

``warm_node`` pays both before the node's first hello: numba's set-up, then a few-pixel
render of a tiny store written to a temporary folder, twice (``WARM_RENDERS``: each
integrator and each sort-first schedule once), which calls the kernels every scheduler's
activations call (the domain-decomposition runtimes' tracing, shading and queries are the
same kernels; a test checks that a render of every scheduler finds none left to load).
It also imports the modules a scheduler's runtime imports on first use
(``FIRST_USE_MODULES``): ``temporal``'s, about 20 ms of a node's first frame on 8 nodes
sharing 2 cores where Python compiles them (no bytecode cache written), which its busy span
paid and no other scheduler's did.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from vastray.render.kernels import warm_up

log = logging.getLogger(__name__)

#: The tiny store's quads per side of each of its square domains: enough triangles that each
#: domain gets an occupancy mask (``scene.occupancy``), so its query kernel runs too.
QUADS_PER_SIDE = 16
#: The warm-up renders' pixels per side and bounces (two: a bounce's shading and its
#: shadow rays, whose speculative copies spec-ooc keeps in its own kernels).
WARM_PIXELS = 16
WARM_BOUNCES = 2
#: (schedule, integrator) of the warm-up renders: each integrator once, each sort-first
#: schedule once (the pairs' other two add no kernel: the test's check).
WARM_RENDERS = (("spec-ooc", "pt"), ("image", "ao"))
#: Modules a runtime imports only when a job asks for it (``actors.decomposition`` imports
#: the temporal frames for ``temporal`` jobs alone); a test checks no render imports more.
FIRST_USE_MODULES = ("vastray.actors.temporal",)


def warm_node() -> float:
    """Pay a fresh process's first use of the render kernels now (see the module docstring).

    Returns
    -------
    float
        The seconds it took. A folder for the tiny store that cannot be written (a
        read-only temporary folder) only logs a warning: the node then pays the kernels'
        first calls in its first frame, as it did before.
    """
    start = time.perf_counter()
    for module in FIRST_USE_MODULES:
        importlib.import_module(module)
    warm_up()
    try:
        with tempfile.TemporaryDirectory(prefix="vastray-warm-up-") as folder:
            _render_tiny(_tiny_store(Path(folder) / "warm-up.store"))
    except OSError as exc:
        log.warning("could not warm the render kernels in a temporary folder (%s); this "
                    "node's first frame pays their first calls", exc)
    return time.perf_counter() - start


def _tiny_store(path: Path):
    """A floor in two domains and a wall in a third, each a grid of ``QUADS_PER_SIDE``²
    quads with holes: rays cross domains, bounce, and cast shadow rays through other domains.
    Its vertices carry a scalar, so hits are coloured (``kernels.scalar_colors``)."""
    from vastray.scene.store import DomainArrays, Store, StoreWriter

    n = QUADS_PER_SIDE
    u, v = np.meshgrid(np.linspace(0.0, 1.0, n + 1), np.linspace(0.0, 1.0, n + 1),
                       indexing="ij")
    corner = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    quads = np.stack([corner, corner + n + 1, corner + n + 2, corner + 1], axis=1)
    # a checkerboard of 4 x 4 quad blocks left out: holes, so the masks have empty cells
    # to skip rays by
    block = (np.arange(n)[:, None] // 4 + np.arange(n)[None, :] // 4) % 2
    quads = quads[block.ravel() == 1]
    indices = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.uint32)
    u, v = u.ravel(), v.ravel()
    zero = np.zeros_like(u)
    sheets = [np.stack([u - 1.0, zero, v - 0.5], axis=1),   # floor, left half
              np.stack([u, zero, v - 0.5], axis=1),         # floor, right half
              np.stack([2.0 * u - 1.0, v, zero - 0.5], axis=1)]  # the wall behind
    with StoreWriter(path) as writer:
        for vertices in sheets:  # with a scalar per vertex: the colour kernel is warmed too
            writer.add_domain(DomainArrays(vertices=vertices.astype(np.float32),
                                           indices=indices, scalars=u.astype(np.float32)))
    return Store(path)


#: The loggers of what the warm-up renders run (loads, schedules, the one-process runtime):
#: held at WARNING while it runs, so a waiting node's log says only that it is warm. A
#: node waiting for its coordinator logs through none of them.
QUIET_LOGGERS = ("vastray.scene", "vastray.render", "vastray.schedule",
                 "vastray.actors.preloader", "vastray.actors.local",
                 "vastray.actors.sort_first", "vastray.actors.domain_loop",
                 "vastray.actors.render_setup")


@contextlib.contextmanager
def _quiet():
    """``QUIET_LOGGERS`` at WARNING or above for the block, then as they were."""
    loggers = [logging.getLogger(name) for name in QUIET_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(max(logger.getEffectiveLevel(), logging.WARNING))
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


def _render_tiny(store) -> None:
    """A few pixels of ``store``, once for each of ``WARM_RENDERS``, quietly."""
    with _quiet():
        _render_each(store)


def _render_each(store) -> None:
    from vastray.actors.job_options import JobOptions
    from vastray.actors.local import render_out_of_core
    from vastray.actors.render_setup import RenderSetup
    from vastray.render.driver import path_context
    from vastray.render.integrators import RenderSettings, camera_rays
    from vastray.render.scene_config import SceneConfig

    for scheduler, integrator in WARM_RENDERS:
        settings = RenderSettings(width=WARM_PIXELS, height=WARM_PIXELS, spp=1,
                                  integrator=integrator, bounces=WARM_BOUNCES)
        render_out_of_core(store, SceneConfig(), settings,
                           JobOptions(scheduler=scheduler, threads=1, cache=1),
                           progress=False)
    # The renders above make only the camera rays of covered pixels
    # (``integrators.launched_camera_rays``); ``spec-insitu`` makes every path's.
    setup = RenderSetup.of(store, SceneConfig(), settings)
    camera_rays(setup.camera, path_context(setup.shading, settings, 0, 1, setup.ao_distance))
