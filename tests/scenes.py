"""Small scenes built in code for the render tests: meshes -> partitioned stores on disk."""

from __future__ import annotations

import contextlib
import dataclasses
import re
from pathlib import Path

import numpy as np
import trimesh

from vastray.render.integrators import RenderSettings
from vastray.render.lights import AmbientLight, PointLight, QuadLight
from vastray.render.scene_config import SceneConfig
from vastray.scene.partition import partition_grid, partition_kd
from vastray.scene.store import DomainArrays, Store, StoreWriter, relative_to


def rm_store(path: Path, size: int, grid) -> Store:
    """The generated Richtmyer-Meshkov isosurface at ``size``^3 cut into ``grid`` domains,
    written to ``path``."""
    from vastray.scene.generate import generate

    generate("rm", path, size, grid=grid)
    return Store(path)


def mesh_arrays(mesh: trimesh.Trimesh, flip: bool = False) -> DomainArrays:
    """A trimesh as store arrays; ``flip`` reverses the winding (normals point inward)."""
    faces = mesh.faces[:, ::-1] if flip else mesh.faces
    return DomainArrays(np.asarray(mesh.vertices, np.float32), np.asarray(faces, np.uint32))


def write_store(path: Path, mesh: DomainArrays, grid=None, kd: int | None = None) -> Store:
    """Write ``mesh`` as one domain, a uniform ``grid`` of domains, or ``kd`` balanced domains."""
    if grid is not None:
        domains = partition_grid(mesh, grid).domains
    elif kd is not None:
        domains = partition_kd(mesh, kd).domains
    else:
        domains = [mesh]
    with StoreWriter(path) as writer:
        for dom in domains:
            writer.add_domain(dom)
    return Store(path)


def bumpy_scene(seed: int = 3) -> DomainArrays:
    """A displaced sphere resting on a ground plane: self-shadowing, several depths."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=4)
    bump = 1.0 + 0.15 * np.sin(4 * sphere.vertices[:, 0]) * np.cos(5 * sphere.vertices[:, 1])
    sphere.vertices *= bump[:, None]
    boxes = [trimesh.creation.box(extents=rng.uniform(0.2, 0.6, 3)) for _ in range(6)]
    for box in boxes:
        box.apply_translation([rng.uniform(-2, 2), -1.0, rng.uniform(-2, 2)])
    ground = trimesh.creation.box(extents=[6.0, 0.1, 6.0])
    ground.apply_translation([0, -1.3, 0])
    return mesh_arrays(trimesh.util.concatenate([sphere, ground, *boxes]))


def camera_config(position, look_at, fov=40.0, up=(0.0, 1.0, 0.0), **kw) -> SceneConfig:
    return SceneConfig(camera={"position": np.asarray(position, float),
                               "look_at": np.asarray(look_at, float),
                               "up": np.asarray(up, float), "fov": fov}, **kw)


def settings(**kw) -> RenderSettings:
    base = dict(width=48, height=36, spp=2, bounces=2, shadow_samples=4, seed=7)
    base.update(kw)
    return RenderSettings(**base)


#: A camera on ``bumpy_scene``, a point light and a dim sky (the distributed tests' scene).
POINT_AND_SKY_TOML = """
[camera]
position = [3.0, 2.2, 4.5]
look_at = [0.0, -0.5, 0.0]
[[light]]
type = "point"
position = [2.0, 3.0, 1.0]
intensity = 12.0
[[light]]
type = "ambient"
radiance = 0.2
"""


def terrain_scene(n: int = 48, size: float = 4.0, seed: int = 5) -> DomainArrays:
    """A rolling heightfield of ``2 n^2`` triangles under a bumpy sphere and a few boxes: it
    fills its box sideways, so fine grid and k-d partitions leave a thousand or more domains
    non-empty, and its boxes overlap where triangles cross cell boundaries."""
    x = np.linspace(-size / 2, size / 2, n + 1)
    gx, gz = np.meshgrid(x, x, indexing="ij")
    gy = 0.25 * np.sin(2.1 * gx) * np.cos(1.7 * gz) + 0.1 * np.sin(5 * gx + 3 * gz) - 0.6
    corner = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    faces = np.concatenate([np.stack([corner, corner + 1, corner + n + 1], axis=1),
                            np.stack([corner + 1, corner + n + 2, corner + n + 1], axis=1)])
    ground = trimesh.Trimesh(np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1), faces,
                             process=False)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.7)
    bump = 1.0 + 0.12 * np.sin(5 * sphere.vertices[:, 0]) * np.cos(4 * sphere.vertices[:, 2])
    sphere.vertices *= bump[:, None]
    sphere.apply_translation([0.2, 0.3, -0.1])
    rng = np.random.default_rng(seed)
    boxes = [trimesh.creation.box(extents=rng.uniform(0.2, 0.5, 3)) for _ in range(4)]
    for box in boxes:
        box.apply_translation([rng.uniform(-1.5, 1.5), -0.3, rng.uniform(-1.5, 1.5)])
    return mesh_arrays(trimesh.util.concatenate([ground, sphere, *boxes]))


@contextlib.contextmanager
def member_actors(size: int, domains: int = 8, keys=None):
    """``size`` management actors of one job in a fresh asyncio context (real sockets), each
    told its job as the coordinator tells it; all closed on exit. Without ``keys``: the PLAIN
    join secret of a job without keys; with a key folder made by ``vastray keys`` holding
    node keys ``n0`` ... : CURVE, node r with key ``nR``.

    Yields
    ------
    (context, coordinator ROUTER, the context's Gate, actors by rank).
    """
    import zmq
    import zmq.asyncio

    from vastray.actors.attempt import pair_tokens
    from vastray.actors.management import ManagementActor
    from vastray.transport.join_secret import new_secret
    from vastray.transport.keys import load_coordinator_keys, load_node_keys
    from vastray.transport.security import Credentials, Gate, serve

    ctx = zmq.asyncio.Context()
    if keys is None:
        secret = new_secret()
        served = [Credentials(secret=secret)] * (size + 1)
        gate = Gate(ctx, secret=secret, what="test")
    else:  # the gate admits the job's keys once a node has its job
        served = [Credentials(keys=load_coordinator_keys(keys)),
                  *(Credentials(keys=load_node_keys(keys, f"n{r}")) for r in range(size))]
        gate = Gate(ctx, what="test")
    coordinator = ctx.socket(zmq.ROUTER)
    serve(coordinator, served[0])
    port = coordinator.bind_to_random_port("tcp://127.0.0.1")
    nodes = [ManagementActor(ctx, f"tcp://127.0.0.1:{port}", "127.0.0.1", "127.0.0.1", 10.0,
                             served[1 + r], gate) for r in range(size)]
    tokens = pair_tokens(size)
    publics = [] if keys is None else [c.keys.public for c in served[1:]]
    try:
        for rank, node in enumerate(nodes):
            node.join(b"job-token-0123456", {"rank": rank, "size": size, "domains": domains,
                                             "units": [[None, 0, 1], [None, 1, 2]],
                                             "endpoints": [n.endpoint for n in nodes],
                                             "peer_tokens": tokens[rank], "keys": publics})
        yield ctx, coordinator, gate, nodes
    finally:
        for node in nodes:
            node.close()
        coordinator.close(linger=0)
        gate.close()
        ctx.destroy(linger=0)


async def allreduce_over_sockets(arrays: list[dict], ops: dict[str, str]):
    """Run ``TreeReduceActor.allreduce`` on ``len(arrays)`` management actors talking over real
    ZeroMQ sockets in one event loop (rank r contributes ``arrays[r]``).

    Returns
    -------
    (results, actors): every rank's result, and the actors (``steps`` each waited on).
    """
    import asyncio

    from vastray.actors.tree_reduce import TreeReduceActor

    size = len(arrays)
    with member_actors(size) as (_, _, _, nodes):
        actors = [TreeReduceActor(nodes[r], r, size) for r in range(size)]
        results = await asyncio.gather(*[actors[r].allreduce(arrays[r], ops)
                                         for r in range(size)])
    return results, actors


def bumpy_config() -> SceneConfig:
    """The camera and lights (point, quad, ambient) the renders of ``bumpy_scene`` use."""
    return camera_config(
        position=[3.0, 2.2, 4.5], look_at=[0.0, -0.5, 0.0], fov=45,
        lights=[PointLight(np.array([2.0, 3.0, 1.0]), np.full(3, 12.0)),
                QuadLight(np.array([-1.0, 3.0, -1.0]), np.array([0.0, 0.0, 0.8]),
                          np.array([0.8, 0.0, 0.0]), np.full(3, 4.0)),
                AmbientLight(np.full(3, 0.2))])


# --- far from the origin (issue 20; tests/test_numerics.py, bench/numerics.py) ---------------

#: Where the far scene's camera looks from (a unit direction) and at.
FAR_VIEW = np.array([0.55, 0.45, 1.0]) / np.linalg.norm([0.55, 0.45, 1.0])
FAR_TARGET = np.array([0.0, -0.2, 0.0])


def far_mesh(shift: float, scale: float = 1.0) -> DomainArrays:
    """A bumpy sphere, six boxes and a ground slab (about 5,200 triangles, 2.6 units across)
    scaled by ``scale`` and moved by ``shift`` along (1, 1, 1): positions in float64, stored
    relative to their centre (``relative_to``), as a reader does."""
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    bump = 1.0 + 0.15 * np.sin(8 * sphere.vertices[:, 0]) * np.cos(10 * sphere.vertices[:, 1])
    sphere.vertices *= bump[:, None]
    boxes = []
    for _ in range(6):
        box = trimesh.creation.box(extents=rng.uniform(0.1, 0.3, 3))
        box.apply_translation([rng.uniform(-1, 1), -0.5, rng.uniform(-1, 1)])
        boxes.append(box)
    ground = trimesh.creation.box(extents=[2.6, 0.05, 2.6])
    ground.apply_translation([0, -0.65, 0])
    mesh = trimesh.util.concatenate([sphere, ground, *boxes])
    framed = relative_to(np.asarray(mesh.vertices, np.float64) * scale + shift)
    return dataclasses.replace(framed, indices=np.asarray(mesh.faces, np.uint32))


def far_store(path: Path, shift: float, grid=(2, 2, 2), scale: float = 1.0) -> Store:
    """``far_mesh(shift, scale)`` written as a ``grid`` of domains."""
    return write_store(path, far_mesh(shift, scale), grid=grid)


def far_config(shift: float = 0.0, distance: float = 4.0, power: float = 6.0,
               scale: float = 1.0) -> SceneConfig:
    """The far scene's camera ``distance`` from its target along ``FAR_VIEW`` (the field of
    view keeps the framing of a camera 4 units away), a point light of intensity ``power``
    and a sky, all scaled by ``scale`` (the light's intensity by its square, so the image
    stays the same) and moved by ``shift`` along (1, 1, 1)."""
    offset = np.full(3, shift)
    fov = float(np.degrees(2 * np.arctan(np.tan(np.radians(20.0)) * 4.0 / distance)))
    lights = [PointLight(np.array([0.8, 2.0, 0.6]) * scale + offset,
                         np.full(3, power * scale * scale)),
              AmbientLight(np.full(3, 0.15))]
    return SceneConfig(camera={"position": FAR_TARGET * scale + offset + FAR_VIEW * distance * scale,
                               "look_at": FAR_TARGET * scale + offset,
                               "up": np.array([0.0, 1.0, 0.0]), "fov": fov}, lights=lights)


def far_settings(spp: int = 8, seed: int = 1) -> RenderSettings:
    """Path tracing, one bounce, 64 x 48."""
    return RenderSettings(width=64, height=48, spp=spp, integrator="pt", bounces=1,
                          shadow_samples=2, seed=seed)


def compare(image: np.ndarray, reference: np.ndarray) -> dict:
    """Relative change of the mean and energy-normalised relative MSE (``rel_mse_global``:
    MSE / mean(reference^2), as the render reports name it; not the per-pixel ``rel_mse``) of
    ``image`` against ``reference`` (non-finite pixels counted apart, as 0)."""
    finite = np.isfinite(image)
    clean = np.where(finite, image, 0.0)
    return {"mean": float(clean.mean() / reference.mean() - 1.0),
            "rel_mse_global": float(np.mean((clean - reference) ** 2)
                                    / np.mean(reference ** 2)),
            "nonfinite": int(np.count_nonzero(~finite))}


def reap(procs, timeout: float = 120) -> None:
    """Wait for each process of ``procs`` up to ``timeout`` seconds, then kill what is left."""
    import subprocess

    for proc in procs:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def forget_binding() -> None:
    """Forget the loaded Embree library, so the next ``binding()`` loads (and checks, or
    fails) again."""
    from vastray.scene.embree import library

    with library._api_lock:
        library._api, library._api_tried = None, False


def child_pids(pid: int) -> list[int]:
    """The pids of ``pid``'s children (Linux ``/proc``), over every thread of it; a thread that
    ends while it is read is skipped (its children are re-parented to the process)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except FileNotFoundError:
            continue
    return found


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


#: A progress bar as ``tqdm`` draws it: "render:  75%|███▌  | 1.15k/1.54k [00:02<00:00, 636path/s]".
PROGRESS_BAR = re.compile(r"[^\r\n|]*?: *\d+%\|[^|\r\n]*\|[^\[\r\n]*\[[^\]\r\n]*\]")


def said_lines(stderr: str) -> list[str]:
    """What a command said on ``stderr``, its progress bars left out: a render shows its bar
    after 2 s, which a tiny render on a busy machine takes, and a line printed while a bar is
    up follows the bar on the same line."""
    text = PROGRESS_BAR.sub("", stderr)
    return [line.strip() for line in text.splitlines() if line.strip()]
