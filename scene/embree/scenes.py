"""Embree scenes of the store's arrays (zero copy), one mesh or instances of several, and
their queries.

``ctypes`` calls (``library``) build the scenes: the store's arrays (memory-mapped or not)
become the geometry's buffers in place with ``rtcSetSharedGeometryBuffer`` (no copy), the BVH
is built on Embree's own thread pool (the GIL is released while ``rtcCommitScene`` runs).
Ownership: every query leases its scene (``_SceneHandle._lease``: ``rtcRetainScene`` and a
reference to each array Embree reads in place, until the kernel returns).

Scene flags: robust
-------------------
Scenes are built with ``RTC_SCENE_FLAG_ROBUST``, as embreex builds its scenes. Embree's fast
triangle test (flags 0) is not watertight: of rays from inside closed meshes (icosphere, box)
aimed exactly at points of their shared edges, about 5 % slip through the cracks between
triangles with flags 0 and none with the robust flag (``tests/test_embree.py::
test_watertight``). Such rays leave a closed surface (light leaks), so correctness wins over the
faster test, which measured 15-40 % more rays/s (packets, one thread; most on coherent
occlusion). Even the robust test is not exact at *vertices*: a few in a thousand rays aimed
exactly at a vertex (to float32 rounding) from an off-centre inside point miss every triangle
around it (12 % with flags 0; embreex's results are the same, bit for bit); the test bounds
that rate.

With the same flag the results are bit-identical to embreex's ``run`` (primID, tfar, u, v, Ng
and occlusion; tested) except where a ray meets several triangles at exactly the same distance:
there the tie rule (``kernels._tie_filter``) picks the lowest primitive, where embreex keeps
whichever Embree met under its traversal order.

Every Embree scene made here also has ``RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS``
(``FILTER_FLAG``, whatever ``flags`` a ``Scene`` is given): closest hits pass the tie filter
in their query arguments, and Embree 4's manual (``rtcInitIntersectArguments``) requires the
flag on the scene queried and on every instanced scene. Embree 4.3/4.4's CPU 1-ray queries run
an argument filter whenever ``RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER`` is set, flag or not;
the flag decides which packet (4/8/16-wide) traversal a committed scene selects, the filtering
one or the one that never calls a filter (``Scene::accels_select``). So the 1-ray results are
the same with it, bit for bit, and the 8-ray packet queries (the default) run the filter.

Two levels
----------
``TopScene`` holds one instance (identity transform: the instanced triangles are met exactly
as by a query of their own scene) of each of several scenes: the in-core tracer queries every
resident domain at once through it. Instances are attached in ascending domain id, so the
filter's lowest instance is the lowest domain, as the per-domain queries' merge decides.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import threading

import numpy as np

from vastray.scene.embree.kernels import (
    filter_address,
    intersect_nearest,
    intersect_nearest8,
    occluded1,
    occluded8,
)
from vastray.scene.embree.launch import launch, rays
from vastray.scene.embree.library import (
    EMBREE_CONFIG_ENV,
    RTC_BUFFER_TYPE_INDEX,
    RTC_BUFFER_TYPE_VERTEX,
    RTC_BUILD_QUALITY_LOW,
    RTC_FORMAT_FLOAT3,
    RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR,
    RTC_FORMAT_UINT3,
    RTC_GEOMETRY_TYPE_INSTANCE,
    RTC_GEOMETRY_TYPE_TRIANGLE,
    RTC_SCENE_FLAG_COMPACT,
    RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS,
    RTC_SCENE_FLAG_NONE,
    RTC_SCENE_FLAG_ROBUST,
    Api,
    binding,
)

#: Scene flags of every scene built here (see the module docstring).
SCENE_FLAGS = RTC_SCENE_FLAG_ROBUST
#: ``VASTRAY_TRIANGLE_TEST=fast`` builds scenes with Embree's fast triangle test (flags 0,
#: ``RTC_SCENE_FLAG_NONE``, as Mitsuba 3 builds its scenes) instead of the watertight one. For
#: measurements only (``bench/peers.py``'s same-work ratio): rays through shared edges can
#: slip through the surface.
TRIANGLE_TEST_ENV = "VASTRAY_TRIANGLE_TEST"
#: Added to every scene's flags: the tie filter is passed in the query arguments.
FILTER_FLAG = RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS
#: ``VASTRAY_QUERIES=single`` traces one ray per Embree call instead of 8-ray packets (the
#: same answers, bit for bit): for measurements (``bench/throughput.py``) and comparisons. A
#: library that traces 8-ray packets ray by ray (no AVX: ``Api.packets``) always runs the
#: 1-ray kernels.
QUERIES_ENV = "VASTRAY_QUERIES"

_PAGE = mmap.PAGESIZE


def scene_flags() -> int:
    """The flags scenes are built with: ``SCENE_FLAGS`` (watertight), or none where
    ``VASTRAY_TRIANGLE_TEST`` says ``fast`` (measurements); any other value is refused."""
    test = os.environ.get(TRIANGLE_TEST_ENV, "").strip().lower()
    if test in ("", "watertight"):
        return SCENE_FLAGS
    if test == "fast":
        return RTC_SCENE_FLAG_NONE
    raise ValueError(f"{TRIANGLE_TEST_ENV}={test!r}: expected 'watertight' (the default) or "
                     f"'fast' (Embree's non-watertight test, for measurements)")


def query_kernels(packets: bool):
    """The (closest-hit, occlusion) kernels queries run: the 8-ray packet kernels where the
    library traces packets natively (``packets``, ``Api.packets``), else the 1-ray ones; the
    1-ray ones too where ``VASTRAY_QUERIES`` says ``single``. ``VASTRAY_QUERIES=packets`` on a
    library without native packets, or any other value, is refused."""
    mode = os.environ.get(QUERIES_ENV, "").strip().lower()
    if mode == "" or (mode == "packets" and packets):
        return (intersect_nearest8, occluded8) if packets else (intersect_nearest, occluded1)
    if mode == "single":
        return intersect_nearest, occluded1
    if mode == "packets":
        raise ValueError(f"{QUERIES_ENV}=packets: this Embree traces 8-ray packets ray by ray "
                         f"(no AVX here, or {EMBREE_CONFIG_ENV} lowers its ISA), and the "
                         f"packet kernels need them traced as one; unset {QUERIES_ENV}")
    raise ValueError(f"{QUERIES_ENV}={mode!r}: expected 'packets' (the default) or 'single' "
                     f"(one ray per Embree call, for measurements)")


def _padded(arr: np.ndarray, dtype, cols: int) -> np.ndarray:
    """``arr`` itself when it is C-contiguous ``dtype`` with readable bytes past its end;
    otherwise a copy into a buffer one row longer (the copy's extra row is never indexed).

    Embree loads a vertex with one 16-byte read, 4 bytes past the last one. Memory is readable
    page by page, so any array whose data does not end exactly on a page boundary has at least
    those 4 bytes (its ends are 4-byte aligned) in the page that holds its last element: only
    an array ending on a page boundary (or of another layout) is copied.
    """
    if (isinstance(arr, np.ndarray) and arr.dtype == dtype and arr.flags.c_contiguous
            and arr.ndim == 2 and arr.shape[1] == cols and arr.size
            and (arr.ctypes.data + arr.nbytes) % _PAGE != 0):
        return arr
    out = np.empty((len(arr) + 1, cols), dtype)
    out[:-1] = arr
    out[-1] = 0
    return out[:-1]


class _SceneHandle:
    """What each of our Embree scenes has: one owner of its handle, released once (on
    ``close`` or when collected), and leased by every query while it runs.

    A query takes a lease (``_lease``): under the scene's lock it checks the scene is open,
    retains the Embree scene (``rtcRetainScene``) and holds the arrays Embree reads in place;
    it gives both back when the kernel has returned. A ``close`` on another thread meanwhile
    drops only the owner's reference: the Embree scene and its buffers outlive every query
    that started before it, and a query that starts after it is refused.
    """

    handle = None
    _api: Api

    def _open(self, api: Api, flags: int) -> None:
        """Create the (empty) Embree scene with ``flags`` and ``FILTER_FLAG``."""
        self._api = api
        self._handle_lock = threading.Lock()
        self.handle = api.rtcNewScene(api.device)
        if not self.handle:
            api.check("rtcNewScene")
            raise RuntimeError("rtcNewScene failed")
        api.rtcSetSceneFlags(self.handle, flags | FILTER_FLAG)

    def _buffers_in_use(self) -> tuple:
        """The arrays Embree reads in place (held by a query's lease)."""
        return ()

    def _release(self) -> None:
        lock = getattr(self, "_handle_lock", None)
        if lock is None:  # __init__ failed before the scene was created
            return
        with lock:
            handle, self.handle = self.handle, None
        if handle:
            self._api.rtcReleaseScene(handle)

    def close(self) -> None:
        self._release()

    def __del__(self):
        self.close()

    @contextlib.contextmanager
    def _lease(self):
        """The scene handle, retained (with the arrays Embree reads) until the block ends."""
        with self._handle_lock:
            handle = self.handle
            if not handle:
                raise RuntimeError("the scene was closed")
            self._api.rtcRetainScene(handle)
            buffers = self._buffers_in_use()
        try:
            yield handle
        finally:
            self._api.rtcReleaseScene(handle)
            del buffers

    def occluded(self, origins, directions, t_far, threads: int = 1) -> np.ndarray:
        """Whether anything lies within ``t_far`` (for a top-level scene: anything of any
        instance; which one blocks does not matter): see ``DomainBVH.occluded``."""
        org, dirs, tf = rays(origins, directions, t_far)
        out = np.empty(len(org), np.bool_)
        if len(org):
            kernel = query_kernels(self._api.packets)[1]
            with self._lease() as handle:
                launch(kernel, threads, len(org), handle, org, dirs, tf, out)
        return out

    def intersect(self, origins, directions, t_far, threads: int = 1) -> dict[str, np.ndarray]:
        """Closest hits: see ``DomainBVH.intersect``. Of equally near hits the one of the
        lowest (instance, primitive) id wins (``_tie_filter``), whatever the order Embree
        meets them in; for a top-level scene the output also has ``id`` (n,) int64, the
        caller's id (``TopScene.ids``) of the scene hit, -1 for a miss."""
        org, dirs, tf = rays(origins, directions, t_far)
        n = len(org)
        out = {"primID": np.empty(n, np.int32), "tfar": np.empty(n, np.float32),
               "u": np.empty(n, np.float32), "v": np.empty(n, np.float32),
               "Ng": np.empty((n, 3), np.float32)}
        inst = np.empty(n, np.int32)
        if n:
            kernel = query_kernels(self._api.packets)[0]
            with self._lease() as handle:
                launch(kernel, threads, n, handle, filter_address(), org, dirs,
                        tf, out["primID"], out["tfar"], out["u"], out["v"], out["Ng"], inst)
        self._label_hits(out, inst)
        return out

    def _label_hits(self, out: dict, inst: np.ndarray) -> None:
        """Add what a subclass tells of each hit's instance (nothing for one mesh)."""


class Scene(_SceneHandle):
    """One Embree scene of one triangle mesh whose buffers are the given arrays (no copy).

    ``vertices`` (V, 3) float32 and ``indices`` (T, 3) uint32 are kept referenced as long as
    the scene lives: Embree reads them in place. ``close()`` (or garbage collection) releases
    the scene. ``flags``: Embree's scene flags, by default ``scene_flags()`` (watertight).
    ``build_quality``: the scene's ``RTCBuildQuality`` (None: Embree's default, MEDIUM; LOW: a
    two-level BVH over the one mesh). ``mesh_quality``: the mesh's (None: Embree's default;
    LOW: Embree's Morton builder, about 3x faster, whose BVH finds other hits than the default
    one where a ray passes within float rounding of a vertex); it implies a two-level BVH,
    the only one in which Embree reads it. ``compact``: Embree's compact layout
    (``RTC_SCENE_FLAG_COMPACT``): the leaves index ``vertices`` instead of copying them, about
    55 % of the scene's memory, queries 20-30 % slower; its triangle test rounds differently,
    so a ray within float rounding of an edge may take the neighbouring triangle (0-2 rays in
    50,000 aimed at vertices). ``piece_triangles``: the mesh is attached as several triangle
    geometries of that many consecutive triangles each (the last the rest), which Embree's
    two-level builder builds side by side (a single mesh's Morton build gained 5 % from a
    second thread for 50 % more CPU; in pieces a domain built in about half the time for a third
    less CPU on 2 cores, mostly because a piece's blocks come from the C heap and reuse the
    pages earlier builds freed, ``scene.heap``; queries are as fast); None: one geometry. The query
    kernels read a hit's (geomID, primID) as triangle ``geomID * kernels.PIECE_TRIANGLES +
    primID``, so a scene they query has pieces of exactly that size (the layout probe alone
    uses others). It needs ``mesh_quality`` (the two-level BVH). The BVH, so a ray passing
    within float rounding of a vertex, depends on the pieces: they are fixed by the triangle
    count alone, never by the machine.
    """

    def __init__(self, vertices: np.ndarray, indices: np.ndarray, flags: int | None = None,
                 api: Api | None = None, build_quality: int | None = None,
                 mesh_quality: int | None = None, compact: bool = False,
                 piece_triangles: int | None = None):
        if piece_triangles is not None and (piece_triangles < 1 or mesh_quality is None):
            raise ValueError("pieces need a positive size and a mesh_quality (a two-level BVH)")
        api = api or binding()
        if api is None:
            raise RuntimeError("the compiled Embree binding is unavailable")
        self.vertices = _padded(vertices, np.float32, 3)
        self.indices = _padded(indices, np.uint32, 3) if len(indices) else None
        flags = scene_flags() if flags is None else flags
        if compact:
            flags |= RTC_SCENE_FLAG_COMPACT
        self.flags = flags
        self._open(api, flags)
        self.geom_id = None
        if self.indices is not None:
            size = len(self.indices) if piece_triangles is None else piece_triangles
            for k, start in enumerate(range(0, len(self.indices), size)):
                got = self._attach_piece(api, self.indices[start:start + size], mesh_quality)
                if got != k:  # the kernels read geomID as the piece's index
                    raise RuntimeError(f"piece {k} was attached as geometry {got}")
            self.geom_id = 0
            self.pieces = k + 1
        else:
            self.pieces = 0
        if mesh_quality is not None:  # Embree reads it only in a two-level BVH
            build_quality = RTC_BUILD_QUALITY_LOW
        if build_quality is not None:  # Embree's default: RTC_BUILD_QUALITY_MEDIUM
            api.rtcSetSceneBuildQuality(self.handle, build_quality)
        api.rtcCommitScene(self.handle)  # builds the BVH (the GIL is released meanwhile)
        api.check("building a scene")

    def _attach_piece(self, api: Api, indices: np.ndarray, mesh_quality: int | None) -> int:
        """Attach one triangle geometry over ``indices`` (a run of ``self.indices``, read in
        place: the whole array stays referenced) and the whole vertex buffer; its id."""
        geom = api.rtcNewGeometry(api.device, RTC_GEOMETRY_TYPE_TRIANGLE)
        if not geom:
            api.check("rtcNewGeometry")
            raise RuntimeError("rtcNewGeometry failed")
        api.rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                       self.vertices.ctypes.data, 0, 12, len(self.vertices))
        api.rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                       indices.ctypes.data, 0, 12, len(indices))
        if mesh_quality is not None:
            api.rtcSetGeometryBuildQuality(geom, mesh_quality)
        api.rtcCommitGeometry(geom)
        geom_id = api.rtcAttachGeometry(self.handle, geom)
        api.rtcReleaseGeometry(geom)
        return geom_id

    def _buffers_in_use(self) -> tuple:
        return self.vertices, self.indices

    def close(self) -> None:
        """Release the Embree scene (and with it the BVH); the arrays are dropped too (a query
        in flight holds its own references to both)."""
        self._release()
        self.vertices = self.indices = None


class TopScene(_SceneHandle):
    """One Embree scene holding an instance of each given scene: a two-level BVH.

    Every instance has the identity transform, so a ray meets each instanced scene's
    triangles exactly as a query of that scene alone does (the transform of a point or
    vector by the identity is exact). Closest hits are found in one query per ray; of equally
    near hits in several instances the one of the lowest instance id wins (``_tie_filter``),
    as when the scenes are queried one by one and ties go to the lower id.

    Parameters
    ----------
    scenes : the instanced scenes (kept referenced: their buffers must outlive the instances).
    ids : (k,) the caller's id of each scene (e.g. its domain), returned with each hit.
    """

    def __init__(self, scenes: list[Scene], ids, api: Api | None = None):
        api = api or binding()
        if api is None:
            raise RuntimeError("the compiled Embree binding is unavailable")
        self.scenes = list(scenes)
        # Embree keeps each instanced scene alive (reference counted), but not the arrays it
        # reads in place: hold them even if a scene is closed meanwhile.
        self._buffers = [(scene.vertices, scene.indices) for scene in self.scenes]
        self.ids = np.asarray(ids, np.int64)
        if len(self.ids) != len(self.scenes):
            raise ValueError("one id per scene")
        self._open(api, scene_flags())
        identity = np.zeros((4, 3), np.float32)  # column major 3x4: columns x, y, z, p
        identity[0, 0] = identity[1, 1] = identity[2, 2] = 1.0
        for k, scene in enumerate(self.scenes):
            geom = api.rtcNewGeometry(api.device, RTC_GEOMETRY_TYPE_INSTANCE)
            if not geom:
                api.check("rtcNewGeometry")
                raise RuntimeError("rtcNewGeometry failed")
            with scene._lease() as handle:  # Embree retains the instanced scene itself
                api.rtcSetGeometryInstancedScene(geom, handle)
            api.rtcSetGeometryTransform(geom, 0, RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR,
                                        identity.ctypes.data)
            api.rtcCommitGeometry(geom)
            got = api.rtcAttachGeometry(self.handle, geom)
            api.rtcReleaseGeometry(geom)
            if got != k:
                raise RuntimeError(f"instance {k} was attached as geometry {got}")
        api.rtcCommitScene(self.handle)
        api.check("building a top-level scene")

    def _buffers_in_use(self) -> tuple:
        return self.scenes, self._buffers

    def close(self) -> None:
        """Release the top-level scene and drop the instanced scenes (a query in flight holds
        its own references to them)."""
        self._release()
        self.scenes = []
        self._buffers = []

    def _label_hits(self, out: dict, inst: np.ndarray) -> None:
        """``id`` (n,) int64: the caller's id (``ids``) of the scene each ray hit, -1 for a
        miss."""
        out["id"] = np.where(inst >= 0, self.ids[np.maximum(inst, 0)], -1)
