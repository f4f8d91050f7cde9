"""The Python API: ``vastray.render`` for scripts and notebooks.

It runs ``vastray render``'s own code path without its command line: the keyword arguments
become a ``RenderRequest`` (each value checked by the option's own converter, the others at
their defaults: the request's), then ``planning.plan_render`` and ``finish_render`` refuse,
plan and report exactly as the CLI does. A
refusal is raised as ``VastrayError`` (an ``InputError``, or a ``NodeFailure`` with
``nodes``) with the message the CLI prints.
"""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import io
import os
import sys
from collections.abc import Mapping
from functools import partial
from pathlib import Path

import numpy as np

from vastray.actors.results import closing_lines
from vastray.planning import finish_render, plan_render
from vastray.preflight import check_writable_place
from vastray.render.camera import Camera
from vastray.render.imageio import atomic_path, check_image_path, to_srgb8, write_image
from vastray.request import OPTIONS, RenderRequest, converted
from vastray.scene.errors import InputError
from vastray.scene.store import Store
from vastray.worker import run_in_thread, run_in_thread_async

#: Options of ``vastray render`` that have no place in a call: files it writes (the result
#: holds the image and report), animations, and coordinators that wait for remote nodes.
NOT_IN_API = {
    "output": "the result's .image; write it with .save(path)",
    "png": "write a PNG with .to_png(path) (exposure=...)",
    "exposure": "give it to .to_png(path, exposure=...) or .srgb(exposure=...)",
    "report": "the result's .report; write it with json.dump",
    "frames": "render frame by frame with your own camera per call",
    "first_frame": "render frame by frame with your own camera per call",
    "listen": "use `vastray render --listen` for nodes started elsewhere",
    "rendezvous": "use `vastray render --listen --rendezvous`",
    "keys": "use `vastray render --listen --keys`",
    "quiet": "give progress=False",
    "checkpoint_every": "checkpoints are `vastray render`'s (the API returns the image)",
    "checkpoint": "checkpoints are `vastray render`'s (the API returns the image)",
    "resume": "use `vastray render --resume`",
}


@dataclasses.dataclass(frozen=True, repr=False, eq=False)
class RenderOutput:
    """A finished render (what ``vastray.render`` returns).

    Attributes
    ----------
    image : (H, W, 3) float32
        Linear RGB radiance, row 0 at the top of the image.
    depth : (H, W) float32
        Distance from the camera to the first hit along each pixel's rays (the ``depth.Z``
        layer of an EXR).
    normal : (H, W, 3) float32
        Shading normal at the first hit (``normal.X/Y/Z``).
    report : dict
        What ``vastray render --report`` writes: timings (``seconds``), counters, settings,
        scheduler and options, and ``error`` against ``reference`` when one was given.
    camera : Camera
        The camera rendered with, in world coordinates; give it back as ``camera=`` (e.g.
        ``dataclasses.replace(out.camera, fov=20)``) to render the same view again.
    """

    image: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    report: dict
    camera: Camera

    @property
    def seconds(self) -> float:
        """The render's wall time in seconds."""
        return float(self.report["seconds"]["total"])

    def srgb(self, exposure: float = 1.0) -> np.ndarray:
        """(H, W, 3) uint8 clamped sRGB, as in a PNG (for ``matplotlib.pyplot.imshow``)."""
        return to_srgb8(self.image, exposure)

    def save(self, path: str | os.PathLike, exposure: float = 1.0) -> Path:
        """Write the image in the format the extension names: ``.exr`` (RGB plus the depth
        and normal layers), ``.pfm``, ``.hdr`` or ``.png`` (clamped sRGB times ``exposure``);
        written whole or not at all. Returns the path.

        Raises
        ------
        VastrayError
            For an unknown extension or a folder in the way.
        """
        path = check_image_path(path, "path")
        check_writable_place(path, "save()")  # a missing folder is never created
        with atomic_path(path) as tmp:
            write_image(tmp, self.image, self.depth, self.normal, exposure)
        return path

    def to_png(self, path: str | os.PathLike, exposure: float = 1.0) -> Path:
        """Write a clamped sRGB PNG preview (``path`` must end in ``.png``). Returns the path."""
        if Path(path).suffix.lower() != ".png":
            raise InputError(path, "to_png needs a file name ending in .png (save() writes "
                                   "the other formats)")
        return self.save(path, exposure)

    def _repr_png_(self) -> bytes:  # Jupyter shows the result as its image
        from PIL import Image

        buffer = io.BytesIO()
        Image.fromarray(self.srgb(), mode="RGB").save(buffer, format="PNG")
        return buffer.getvalue()

    def __repr__(self) -> str:
        settings = self.report["settings"]
        return (f"<RenderOutput {settings['width']}x{settings['height']}, {settings['spp']} spp "
                f"{settings['integrator']}, {self.report['scheduler']}, {self.seconds:.2f} s>")


def render(store: str | os.PathLike | Store | None = None, *,
           camera: Mapping | Camera | None = None, scene: str | os.PathLike | None = None,
           width: int | None = None, height: int | None = None, spp: int | None = None,
           integrator: str = "pt", bounces: int | None = None,
           shadow_samples: int | None = None, ao_distance: float | None = None, seed: int = 0,
           scheduler: str = "auto", nodes: int | None = None, cache: int | str | None = None,
           threads: int | None = None, memory_limit: int | str | None = None,
           reference: str | os.PathLike | np.ndarray | None = None, progress: bool = True,
           **options) -> RenderOutput:
    """Render a store as ``vastray render`` does, and return the image and its report.

    Works from a plain script and from inside a running asyncio event loop (a Jupyter cell):
    there the render runs on a thread of its own, and an interrupt (Ctrl-C, the notebook's
    stop button) stops it and its node processes before ``KeyboardInterrupt`` reaches you.
    In an ``async def``, ``await vastray.render_async(...)`` does not block the loop.

    Parameters
    ----------
    store : a store folder (``vastray generate`` / ``partition``), an opened ``Store``, or
        None for the built-in scene.
    camera : the view, replacing the scene's ``[camera]``: a dict with any of ``position``,
        ``look_at``, ``up`` ((3,) numbers, world coordinates) and ``fov`` (vertical, degrees),
        the rest framing the store as in SCENE.toml; or a ``Camera`` (such as a result's
        ``.camera``), whose width and height are the defaults of ``width`` and ``height``.
    scene : a SCENE.toml with camera, lights and materials (``--scene``).
    width, height, spp, integrator, bounces, shadow_samples, ao_distance, seed : the image
        and its sampling, as ``vastray render --help`` describes them (default: 320x240, 4
        spp, 3 bounces for a store; the built-in scene's own).
    scheduler : ``"auto"``, ``"reference"``, ``"image"``, ``"spec-ooc"``; with ``nodes``
        also ``"domain"``, ``"async"``, ``"dynamic"``, ``"spec-insitu"``, ``"temporal"``.
    nodes : render with this many node processes on this machine (ZeroMQ over loopback),
        started and stopped by the call; None: in this process.
    cache : most domains in memory: a count, or a percentage such as ``"25%"``.
    threads : threads per process (default: all cores; shared among ``nodes``).
    memory_limit : bytes, or a size such as ``"8G"``, each process may use.
    reference : an image file (.exr/.pfm/.npy) or an (H, W, 3) array: ``report["error"]``
        gets MSE, PSNR and relative MSE against it.
    progress : the CLI's progress bar on stderr (for renders over two seconds).
    **options : any other option of ``vastray render`` by its long name with underscores,
        e.g. ``history_depth=2``, ``max_samples_in_flight=4096``, ``no_preload=True``,
        ``load_bandwidth=200``, ``simplified="portal"``, ``node_timeout=60``.

    Returns
    -------
    RenderOutput
        ``.image`` ((H, W, 3) float32 radiance), ``.depth``, ``.normal``, ``.report`` (the
        dict ``--report`` writes), ``.camera``; ``.save(path)``, ``.to_png(path)``.

    Raises
    ------
    VastrayError
        For every refusal ``vastray render`` prints (bad store or scene, an option that does
        not apply, a render that cannot fit in memory), with the same message, and for a node
        that failed.
    KeyboardInterrupt
        When interrupted, once the node processes are stopped.
    """
    job = _job(store, dict(
        camera=camera, scene=scene, width=width, height=height, spp=spp, integrator=integrator,
        bounces=bounces, shadow_samples=shadow_samples, ao_distance=ao_distance, seed=seed,
        scheduler=scheduler, nodes=nodes, cache=cache, threads=threads,
        memory_limit=memory_limit, reference=reference, progress=progress, **options))
    if _loop_running():
        return run_in_thread(job)
    return job()


async def render_async(store: str | os.PathLike | Store | None = None,
                       **kwargs) -> RenderOutput:
    """``vastray.render`` for ``async`` code: the same keyword arguments, the render on a thread
    of its own so the event loop goes on; cancelling the task stops the render (and its node
    processes) before the cancellation goes on.

    Raises
    ------
    VastrayError
        As ``vastray.render``.
    """
    return await run_in_thread_async(_job(store, kwargs))


def _loop_running() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def _job(store, kwargs: dict):
    """The render as a call without arguments, its arguments checked now (in the caller's
    thread, so a refusal needs no thread)."""
    request, opened, call = render_request(store, kwargs)
    return partial(_run, request, opened, call)


def render_request(store, kwargs: dict) -> tuple[RenderRequest, Store | None, str]:
    """``vastray.render``'s arguments as the ``RenderRequest`` they ask for (its values
    checked and converted as the command line's), the ``Store`` given opened (or None), and
    the call as the report's ``command``.

    Raises
    ------
    VastrayError
        Naming the argument: unknown, not for the API, or a bad value; or an option given
        where it changes nothing (``RenderRequest.refuse_inapplicable``).
    """
    kwargs = dict(kwargs)
    camera = kwargs.pop("camera", None)
    progress = kwargs.pop("progress", True)
    if not isinstance(progress, bool):
        raise InputError(None, f"progress must be True or False, got {progress!r}")
    if isinstance(camera, Camera):
        kwargs["width"] = kwargs.get("width") or camera.width
        kwargs["height"] = kwargs.get("height") or camera.height
    if not (store is None or isinstance(store, (str, os.PathLike, Store))):
        raise InputError(None, f"store must be a store folder's path, a Store or None (the "
                               f"built-in scene), got {type(store).__name__}")
    opened = store if isinstance(store, Store) else None
    kwargs["store"] = None if store is None else os.fspath(store.path if opened else store)
    reference = kwargs.get("reference")
    if reference is not None and not isinstance(reference, (str, os.PathLike)):
        kwargs["reference"] = _reference_array(reference)
    values = {}
    for key, value in kwargs.items():
        if key in NOT_IN_API:
            raise InputError(None, f"vastray.render takes no {key}=: {NOT_IN_API[key]}")
        if key not in OPTIONS:
            raise InputError(None, f"vastray.render got an unknown argument {key}=; it takes "
                                   "the options of `vastray render --help` by their long "
                                   "names with underscores")
        values[key] = converted(key, value)
    request = RenderRequest(**values, quiet=not progress, camera=camera)
    return request, opened, _call_text(store, kwargs)


def _reference_array(reference) -> np.ndarray:
    array = np.asarray(reference)
    if array.ndim != 3 or array.shape[2] != 3 or not np.issubdtype(array.dtype, np.number):
        raise InputError("reference", f"must be an (H, W, 3) array of numbers, got shape "
                                      f"{array.shape} of {array.dtype}")
    return array.astype(np.float32)


def _call_text(store, kwargs: dict) -> str:
    """The call as its report's ``command`` (a path, not the array, for a reference)."""
    defaults = {name: p.default for name, p in inspect.signature(render).parameters.items()}
    shown = [repr(None if store is None else os.fspath(getattr(store, "path", store)))]
    for key, value in kwargs.items():
        if key == "store" or value is None or (not isinstance(value, np.ndarray)
                                                and defaults.get(key, None) == value):
            continue
        text = "<array>" if isinstance(value, np.ndarray) else repr(value)
        shown.append(f"{key}={text}")
    return f"vastray.render({', '.join(shown)})"


def _run(request: RenderRequest, store: Store | None, call: str) -> RenderOutput:
    """The render itself, as ``vastray.execute.run`` does it, to memory."""
    plan = plan_render(request, store=store)
    request = plan.request  # its defaults filled in
    result = plan.render_one(plan.config, plan.settings, progression=plan.progression())
    reference = None
    if plan.reference is not None:
        reference = request.reference if isinstance(request.reference, str) else "<array>"
    image, _, report = finish_render(plan, result, "vastray.render", reference)
    report["command"] = call
    if not request.quiet:
        for line in closing_lines(result.counters, result.seconds):
            print(line, file=sys.stderr)
    world_camera = plan.config.resolve_camera(*plan.store.world_bounds, request.width,
                                              request.height)
    return RenderOutput(image=np.asarray(image, np.float32),
                        depth=np.asarray(result.film.depth_image(), np.float32),
                        normal=np.asarray(result.film.normal_image(), np.float32),
                        report=report, camera=world_camera)
