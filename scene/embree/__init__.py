"""Our binding of Embree 4's C API: zero-copy scenes from numpy arrays, traced by numba kernels.

The library is the one the ``embreex`` wheel ships (``embreex.libs/libembree4-*.so.4``); embreex
stays the dependency that brings the binary, and the fallback when this binding cannot be used.

Pieces
------
- ``ctypes`` calls build scenes: the store's arrays (memory-mapped or not) become the geometry's
  buffers in place with ``rtcSetSharedGeometryBuffer`` (no copy), the BVH is built on Embree's
  own thread pool (the GIL is released while ``rtcCommitScene`` runs).
- ``@njit(nogil=True, cache=True)`` serial kernels trace structure-of-arrays batches without
  the GIL, calling Embree through ``@intrinsic`` declarations of the functions *by name*: the
  library is loaded into LLVM's process symbol table (with its version check) when the binding
  is first used, so the compiled kernels hold no raw addresses and numba caches them on disk
  (``__pycache__``). A warm process loads them instead of compiling (about 2-3 s per process
  before).
- Threads: a query of several threads splits its rays into contiguous parts, each traced by the
  serial kernel on a thread of one process-wide pool (``_launch``); render workers that trace on
  one thread each run their kernels side by side. No kernel is ``parallel=True``: numba's
  threading layer, whose default (workqueue) is not safe to enter from two Python threads at
  once, is never used (issue 20: heap corruption under load was reported only with two
  threads in compiled code; with no kernel sharing native state, that class is ruled out).
- Ownership: every query leases its scene (``_SceneHandle._lease``: ``rtcRetainScene`` and a
  reference to each array Embree reads in place, until the kernel returns); every buffer a
  kernel hands Embree (ray, hit, context, arguments) is that call's own, aligned as Embree's
  headers declare.

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
there the tie rule below picks the lowest primitive, where embreex keeps whichever Embree met
under its traversal order.

Queries: one ray at a time
--------------------------
Closest hits use ``rtcIntersect1`` with an argument filter (``_tie_filter``) that keeps, of
equally near hits, the lowest (instance, primitive) id: the hit of a ray does not depend on the
order Embree meets tied candidates in, so a domain queried directly and the same domain met as
an instance of a top-level scene give the same hit (without it, rays through a shared edge kept
different triangles on the two paths: issue 20). Occlusion uses ``rtcOccluded1``: 16-ray
occlusion packets through a top-level scene's instances, from two threads at once, corrupted
the heap (``bench/README.md``, session 4), the pattern of issue 20's crashes. With the robust
flag, 1-ray and 16-ray packet queries measured the same speed (1.7 M-triangle isosurface, one
thread: closest hit 1.70 vs 1.71 Mrays/s incoherent, 3.21 vs 3.23 coherent; occlusion 1.76 vs
1.80 incoherent, 3.70 vs 3.54 coherent), so neither choice gives up packet speed.

Two levels
----------
``TopScene`` holds one instance (identity transform: the instanced triangles are met exactly
as by a query of their own scene) of each of several scenes: the in-core tracer queries every
resident domain at once through it. Instances are attached in ascending domain id, so the
filter's lowest instance is the lowest domain, as the per-domain queries' merge decides.

Fallback
--------
When the library cannot be found or loaded, or its major version is not 4 (the layouts and
constants here are Embree 4's), ``binding()`` returns None after one ``EmbreeFallbackWarning``
and ``DomainBVH`` uses embreex's ``run`` as before. ``VASTRAY_EMBREEX=1`` in the environment
chooses embreex's ``run`` on purpose (no warning), e.g. to compare the two.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import importlib.util
import mmap
import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

# Embree 4 constants (include/embree4/rtcore_*.h)
RTC_DEVICE_PROPERTY_VERSION = 0
RTC_DEVICE_PROPERTY_VERSION_MAJOR = 1
RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX = 0
RTC_BUFFER_TYPE_VERTEX = 1
RTC_FORMAT_UINT3 = 0x5003
RTC_FORMAT_FLOAT3 = 0x9003
RTC_SCENE_FLAG_NONE = 0
RTC_SCENE_FLAG_ROBUST = 4
RTC_INVALID_GEOMETRY_ID = 0xFFFFFFFF
RTC_GEOMETRY_TYPE_INSTANCE = 121
RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR = 0x9234
RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER = 1 << 1

#: Scene flags of every scene built here (see the module docstring).
SCENE_FLAGS = RTC_SCENE_FLAG_ROBUST

_PAGE = mmap.PAGESIZE


class EmbreeFallbackWarning(RuntimeWarning):
    """The compiled Embree binding is unusable; embreex's ``run`` is used instead."""


def find_library() -> Path:
    """The Embree 4 shared library shipped in the embreex wheel."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or not spec.submodule_search_locations:
        raise OSError("embreex is not installed")
    for folder in spec.submodule_search_locations:
        libs = Path(folder).parent / "embreex.libs"
        found = sorted(glob.glob(str(libs / "libembree4*.so*")))
        if found:
            return Path(found[0])
    raise OSError("no libembree4*.so in embreex.libs/ next to the embreex package")


class _Api:
    """The library's functions called from Python (ctypes releases the GIL during each call)."""

    def __init__(self, path: Path):
        from llvmlite import binding as llvm

        # Global symbols: numba's compiled kernels resolve rtcIntersect1 etc. by name through
        # LLVM's process symbol table.
        self.lib = ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        llvm.load_library_permanently(str(path))
        self.path = path
        p, u32, i32, sz = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_size_t
        sigs = {
            "rtcNewDevice": (p, [ctypes.c_char_p]),
            "rtcReleaseDevice": (None, [p]),
            "rtcGetDeviceProperty": (ctypes.c_ssize_t, [p, i32]),
            "rtcGetDeviceError": (i32, [p]),
            "rtcNewScene": (p, [p]),
            "rtcSetSceneFlags": (None, [p, i32]),
            "rtcCommitScene": (None, [p]),
            "rtcRetainScene": (None, [p]),
            "rtcReleaseScene": (None, [p]),
            "rtcNewGeometry": (p, [p, i32]),
            "rtcSetSharedGeometryBuffer": (None, [p, i32, u32, i32, p, sz, sz, sz]),
            "rtcCommitGeometry": (None, [p]),
            "rtcAttachGeometry": (u32, [p, p]),
            "rtcReleaseGeometry": (None, [p]),
            "rtcGetGeometry": (p, [p, u32]),
            "rtcGetGeometryBufferData": (p, [p, i32, u32]),
            "rtcSetGeometryInstancedScene": (None, [p, p]),
            "rtcSetGeometryTransform": (None, [p, u32, i32, p]),
        }
        for name, (res, args) in sigs.items():
            fn = getattr(self.lib, name)
            fn.restype, fn.argtypes = res, args
            setattr(self, name, fn)
        self.device = self.rtcNewDevice(None)
        if not self.device:
            raise OSError("rtcNewDevice failed")
        self.version = int(self.rtcGetDeviceProperty(self.device, RTC_DEVICE_PROPERTY_VERSION))
        self.major = int(self.rtcGetDeviceProperty(self.device, RTC_DEVICE_PROPERTY_VERSION_MAJOR))
        if self.major != 4:
            self.rtcReleaseDevice(self.device)
            raise OSError(f"{path.name} is Embree {self.version}, not Embree 4")

    def check(self, what: str) -> None:
        code = self.rtcGetDeviceError(self.device)
        if code:
            raise RuntimeError(f"Embree error {code} in {what}")


def _load_library() -> _Api:
    """Find, load and check the library (tests replace this to exercise the fallback)."""
    return _Api(find_library())


_api: _Api | None = None
_api_tried = False
_api_lock = threading.Lock()


def binding() -> _Api | None:
    """The loaded library, or None (after one ``EmbreeFallbackWarning``) when unusable or
    disabled (``VASTRAY_EMBREEX``)."""
    global _api, _api_tried
    if _api_tried:
        return _api
    with _api_lock:
        if not _api_tried:
            try:
                _api = None if os.environ.get("VASTRAY_EMBREEX") else _load_library()
            except Exception as exc:  # noqa: BLE001 - any failure means: use embreex
                _api = None
                warnings.warn(f"vastray: compiled Embree binding unavailable ({exc}); "
                              f"using embreex's run()", EmbreeFallbackWarning, stacklevel=3)
            _api_tried = True
    return _api


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
    _api: _Api

    def _open(self, api: _Api, flags: int) -> None:
        """Create the (empty) Embree scene with ``flags``."""
        self._api = api
        self._handle_lock = threading.Lock()
        self.handle = api.rtcNewScene(api.device)
        if not self.handle:
            api.check("rtcNewScene")
            raise RuntimeError("rtcNewScene failed")
        api.rtcSetSceneFlags(self.handle, flags)

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
        org, dirs, tf = _rays(origins, directions, t_far)
        out = np.empty(len(org), np.bool_)
        if len(org):
            with self._lease() as handle:
                _launch(_occluded1, threads, len(org), handle, org, dirs, tf, out)
        return out

    def intersect(self, origins, directions, t_far, threads: int = 1) -> dict[str, np.ndarray]:
        """Closest hits: see ``DomainBVH.intersect``. Of equally near hits the one of the
        lowest (instance, primitive) id wins (``_tie_filter``), whatever the order Embree
        meets them in; for a top-level scene the output also has ``id`` (n,) int64, the
        caller's id (``TopScene.ids``) of the scene hit, -1 for a miss."""
        org, dirs, tf = _rays(origins, directions, t_far)
        n = len(org)
        out = {"primID": np.empty(n, np.int32), "tfar": np.empty(n, np.float32),
               "u": np.empty(n, np.float32), "v": np.empty(n, np.float32),
               "Ng": np.empty((n, 3), np.float32)}
        inst = np.empty(n, np.int32)
        if n:
            with self._lease() as handle:
                _launch(_intersect_nearest, threads, n, handle, _filter_address(), org, dirs,
                        tf, out["primID"], out["tfar"], out["u"], out["v"], out["Ng"], inst)
        self._label_hits(out, inst)
        return out

    def _label_hits(self, out: dict, inst: np.ndarray) -> None:
        """Add what a subclass tells of each hit's instance (nothing for one mesh)."""


class Scene(_SceneHandle):
    """One Embree scene of one triangle mesh whose buffers are the given arrays (no copy).

    ``vertices`` (V, 3) float32 and ``indices`` (T, 3) uint32 are kept referenced as long as
    the scene lives: Embree reads them in place. ``close()`` (or garbage collection) releases
    the scene.
    """

    def __init__(self, vertices: np.ndarray, indices: np.ndarray, flags: int = SCENE_FLAGS,
                 api: _Api | None = None):
        api = api or binding()
        if api is None:
            raise RuntimeError("the compiled Embree binding is unavailable")
        self.vertices = _padded(vertices, np.float32, 3)
        self.indices = _padded(indices, np.uint32, 3) if len(indices) else None
        self.flags = flags
        self._open(api, flags)
        self.geom_id = None
        if self.indices is not None:
            geom = api.rtcNewGeometry(api.device, RTC_GEOMETRY_TYPE_TRIANGLE)
            if not geom:
                api.check("rtcNewGeometry")
                raise RuntimeError("rtcNewGeometry failed")
            api.rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                           self.vertices.ctypes.data, 0, 12, len(self.vertices))
            api.rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                           self.indices.ctypes.data, 0, 12, len(self.indices))
            api.rtcCommitGeometry(geom)
            self.geom_id = api.rtcAttachGeometry(self.handle, geom)
            api.rtcReleaseGeometry(geom)
        api.rtcCommitScene(self.handle)  # builds the BVH (the GIL is released meanwhile)
        api.check("building a scene")

    def _buffers_in_use(self) -> tuple:
        return self.vertices, self.indices

    def close(self) -> None:
        """Release the Embree scene (and with it the BVH); the arrays are dropped too (a query
        in flight holds its own references to both)."""
        self._release()
        self.vertices = self.indices = None


def _rays(origins, directions, t_far) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' inputs: C-contiguous, writable float32 (n, 3), (n, 3), (n,), checked (the
    kernels do not check bounds)."""
    org, dirs, tf = (_writable(np.ascontiguousarray(a, dtype=np.float32))
                     for a in (origins, directions, t_far))
    n = len(org)
    if org.shape != (n, 3) or dirs.shape != (n, 3) or tf.shape != (n,):
        raise ValueError(f"rays must be (n, 3), (n, 3), (n,): got {org.shape}, {dirs.shape}, "
                         f"{tf.shape}")
    return org, dirs, tf


def _writable(a: np.ndarray) -> np.ndarray:
    # One kernel signature only (numba types read-only arrays apart: another compilation).
    return a if a.flags.writeable else a.copy()


# ---------------------------------------------------------------------------------------------
# numba kernels
# ---------------------------------------------------------------------------------------------

#: Fewest rays per part when a query is split over several threads.
_SPLIT_MIN = 4096
_splitter: ThreadPoolExecutor | None = None
_splitter_lock = threading.Lock()


def _split_pool(threads: int) -> ThreadPoolExecutor:
    """The process's pool that runs the parts of split queries (grown on demand)."""
    global _splitter
    with _splitter_lock:
        if _splitter is None or _splitter._max_workers < threads:
            old, _splitter = _splitter, ThreadPoolExecutor(threads,
                                                           thread_name_prefix="embree-part")
            if old is not None:
                old.shutdown(wait=False)
        return _splitter


def _launch(kernel, threads: int, n: int, *args) -> None:
    """Run the serial ``kernel`` on ``n`` rays, split into at most ``threads`` contiguous
    parts that run side by side on ``_split_pool`` (one part: on the calling thread).

    Every kernel here is serial and releases the GIL: numba's threading layer (whose default,
    workqueue, must not be entered by two Python threads at once) is never used, so any number
    of Python threads may query at the same time. Each part writes only its own rows of the
    outputs (array arguments are sliced along their first axis; the others, such as the scene
    handle, are passed whole); the caller holds every array until all parts have returned.
    """
    parts = max(1, min(int(threads), n // _SPLIT_MIN))
    if parts == 1:
        kernel(*args)
        return
    bounds = np.linspace(0, n, parts + 1).astype(np.int64)

    def run(k: int) -> None:
        lo, hi = bounds[k], bounds[k + 1]
        kernel(*(a[lo:hi] if isinstance(a, np.ndarray) else a for a in args))

    for future in [_split_pool(parts).submit(run, k) for k in range(parts)]:
        future.result()


#: float32 words of RTCRayHit (the hit's instPrimID included: 96 bytes, 16-byte aligned).
_RAYHIT1_WORDS = 24
_INVALID = -1  # RTC_INVALID_GEOMETRY_ID as int32


def _codegen(name: str, nargs: int):
    """Code calling the library's ``void name(void*, ...)`` by symbol name, its pointer
    arguments given as integers (addresses)."""

    def codegen(context, builder, signature, values):
        ptr = cgutils.voidptr_t
        fnty = cgutils.ir.FunctionType(cgutils.ir.VoidType(), [ptr] * nargs)
        fn = cgutils.get_or_insert_function(builder.module, fnty, name)
        builder.call(fn, [builder.inttoptr(v, ptr) for v in values])
        return context.get_dummy_value()

    return codegen


def _external3(name: str):
    @intrinsic
    def call(typingctx, a, b, c):
        if all(isinstance(x, types.Integer) for x in (a, b, c)):
            return types.void(a, b, c), _codegen(name, 3)
        return None

    return call


_rtcIntersect1 = _external3("rtcIntersect1")  # (scene, rayhit, args)
_rtcOccluded1 = _external3("rtcOccluded1")  # (scene, ray, args)


@njit(inline="always")
def _aligned(raw, align_words, n_words):
    """A view of ``n_words`` words of ``raw`` starting on an ``align_words`` x itemsize byte
    boundary (``raw`` has ``align_words`` spare words)."""
    size = raw.itemsize
    addr = raw.ctypes.data
    mis = (addr // size) % align_words
    off = (align_words - mis) % align_words
    return raw[off:off + n_words]


@njit(inline="always")
def _set_ray1(f, i32, org, dirs, tfar, i):
    # RTCRay: org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar, mask, id, flags
    f[0] = org[i, 0]
    f[1] = org[i, 1]
    f[2] = org[i, 2]
    f[3] = 0.0
    f[4] = dirs[i, 0]
    f[5] = dirs[i, 1]
    f[6] = dirs[i, 2]
    f[7] = 0.0
    f[8] = tfar[i]
    i32[9] = -1
    i32[10] = 0
    i32[11] = 0


@njit(nogil=True, cache=True)
def _occluded1(scene, org, dirs, tfar_in, out):
    """Occlusion of rays ``org + t dirs``, ``0 <= t <= tfar_in``, one ``rtcOccluded1`` per ray;
    ``out`` (n,) bool.

    One ray at a time, not 16-ray packets: occlusion through a top-level scene's instances in
    ``rtcOccluded16`` packets from two threads at once corrupted the heap (bench/README.md,
    session 4: ``malloc(): unaligned tcache chunk detected`` within 12 renders), the pattern of
    the crashes reported in issue 20 (in core, two render workers, the top-level scene); with
    the robust flag 1-ray and packet occlusion measured the same speed. The ray buffer is a
    whole RTCRayHit (96 bytes, 16-byte aligned), though Embree reads and writes only its
    RTCRay part.
    """
    n = org.shape[0]
    raw = np.empty(_RAYHIT1_WORDS + 4, np.float32)
    f = _aligned(raw, 4, _RAYHIT1_WORDS)
    i32 = f.view(np.int32)
    for i in range(n):
        _set_ray1(f, i32, org, dirs, tfar_in, i)
        _rtcOccluded1(scene, f.ctypes.data, 0)
        out[i] = f[8] < 0  # Embree sets tfar to -inf on a hit


# ---------------------------------------------------------------------------------------------
# Closest hits: 1-ray queries whose ties an argument filter breaks by id
# ---------------------------------------------------------------------------------------------

def _memory(width: int, kind: str):
    """Intrinsics loading (``kind="load"``) or storing a ``width``-bit word at an address
    given as an integer: the filter below reads Embree's structures through them."""
    is_float = width == 32 and kind.endswith("f")

    def llvm_type():
        return cgutils.ir.FloatType() if is_float else cgutils.ir.IntType(width)

    value_type = types.float32 if is_float else types.int32 if width == 32 else types.int64
    if kind.startswith("load"):
        @intrinsic
        def load(typingctx, addr):
            if isinstance(addr, types.Integer):
                def codegen(context, builder, signature, values):
                    ptr = builder.inttoptr(values[0], cgutils.ir.PointerType(llvm_type()))
                    return builder.load(ptr)

                return value_type(addr), codegen
            return None

        return load

    @intrinsic
    def store(typingctx, addr, value):
        if isinstance(addr, types.Integer):
            def codegen(context, builder, signature, values):
                ptr = builder.inttoptr(values[0], cgutils.ir.PointerType(llvm_type()))
                v = context.cast(builder, values[1], signature.args[1], value_type)
                builder.store(v, ptr)
                return context.get_dummy_value()

            return types.void(addr, value), codegen
        return None

    return store


_load_i64 = _memory(64, "load")
_load_i32 = _memory(32, "load")
_load_f32 = _memory(32, "loadf")
_store_i32 = _memory(32, "store")
_store_f32 = _memory(32, "storef")

#: Byte offset, in the ray query context, of our per-lane records (best t: float32, its
#: instance: int32, its primitive: int32, padding): past ``RTCRayQueryContext``'s instID[1]
#: (and instPrimID[1] where the library has instance arrays), with room to spare.
_CTX_RECORD = 16
_RECORD_BYTES = 16
#: int32 words of the context buffer: Embree's 16 bytes, then one record per lane of the
#: widest call Embree can make (16), whatever lane a call uses.
_CTX_WORDS = (_CTX_RECORD + 16 * _RECORD_BYTES) // 4
#: int64 words of RTCIntersectArguments: flags and feature_mask, context, filter, intersect,
#: (minWidthDistanceFactor where built with it), spare.
_ARGS_WORDS = 6
_NO_ID = np.int32(0x7FFFFFFF)


def _tie_filter(args):
    """Embree filter (``RTCFilterFunctionN``) that makes the closest hit independent of the
    order in which Embree meets equally near candidates.

    Embree accepts a triangle hit when ``t <= tfar`` (inclusive), so of equally near hits the
    one kept depends on the traversal: the leaf order, and, inside a leaf, whether a filter
    runs (without one, the first of the leaf's tied lanes; with one, every tied lane is offered
    in turn). A direct query of a domain and the same domain met as an instance of a top-level
    scene could thus keep different triangles (issue 20: one pixel in 65,536 differed). This
    filter accepts a candidate only if it is nearer than the best so far, or as near with a
    lower (instance, primitive) id, so the same ray always ends with the same hit: the lowest
    domain (instances are attached in ascending domain id; a direct query has no instance,
    id -1) and, within it, the lowest primitive id among the nearest.

    ``args`` is the address of ``RTCFilterFunctionNArguments``: valid (int*), geometryUserPtr,
    context, ray (RTCRayN*), hit (RTCHitN*), N (unsigned int). The candidate's distance is in
    the ray's tfar, its primitive in the hit's primID, its instance in instID[0]. The best so
    far is kept per lane in our part of the ray query context (16 records, one per possible
    lane: no lane indexes past it).
    """
    valid = _load_i64(args)
    ctx = _load_i64(args + 16)
    ray = _load_i64(args + 24)
    hit = _load_i64(args + 32)
    n = min(_load_i32(args + 40), 16)
    for lane in range(n):
        if _load_i32(valid + 4 * lane) == 0:
            continue
        t = _load_f32(ray + 4 * (8 * n + lane))
        prim = _load_i32(hit + 4 * (5 * n + lane))
        inst = _load_i32(hit + 4 * (7 * n + lane))
        record = ctx + _CTX_RECORD + _RECORD_BYTES * lane
        best_t = _load_f32(record)
        best_inst = _load_i32(record + 4)
        best_prim = _load_i32(record + 8)
        if t < best_t or (t == best_t and (inst < best_inst or (
                inst == best_inst and prim < best_prim))):
            _store_f32(record, t)
            _store_i32(record + 4, inst)
            _store_i32(record + 8, prim)
        else:
            _store_i32(valid + 4 * lane, 0)


_filter_cfunc = None
_filter_lock = threading.Lock()


def _filter_address() -> int:
    """Address of the compiled ``_tie_filter`` (compiled, or loaded from numba's cache, on
    first use; the cfunc object is kept for the life of the process, so the address stays
    valid)."""
    global _filter_cfunc
    with _filter_lock:
        if _filter_cfunc is None:
            _filter_cfunc = numba.cfunc(types.void(types.int64), nogil=True, cache=True)(
                _tie_filter)
        return _filter_cfunc.address


@njit(inline="always")
def _store_hit(f, i32, prim, tfar, u, v, ng, i):
    """Copy ray ``i``'s hit out of an RTCRayHit buffer: tfar at word 8, then the hit's Ng_x,
    Ng_y, Ng_z, u, v, primID at words 12-17. A miss reads as primID -1, zero u, v and Ng."""
    p = i32[17]
    tfar[i] = f[8]
    if p == _INVALID:
        prim[i] = -1
        u[i] = 0.0
        v[i] = 0.0
        ng[i, 0] = 0.0
        ng[i, 1] = 0.0
        ng[i, 2] = 0.0
    else:
        prim[i] = p
        ng[i, 0] = f[12]
        ng[i, 1] = f[13]
        ng[i, 2] = f[14]
        u[i] = f[15]
        v[i] = f[16]


@njit(nogil=True, cache=True)
def _intersect_nearest(scene, filt, org, dirs, tfar_in, prim, tfar, u, v, ng, inst):
    """Closest hits, one ``rtcIntersect1`` per ray with the tie filter ``filt``: the outputs
    are (n,) each (``ng`` (n, 3)); ``inst`` receives the instance (top-level geometry id) of
    each hit, -1 for a miss or a scene without instances.

    The ray, the context and the arguments Embree reads live in this call's own buffers,
    aligned as Embree's headers declare them (RTCRayHit, RTCRayQueryContext and
    RTCIntersectArguments: 16 bytes).
    """
    n = org.shape[0]
    raw = np.empty(_RAYHIT1_WORDS + 4, np.float32)
    f = _aligned(raw, 4, _RAYHIT1_WORDS)
    i32 = f.view(np.int32)
    raw_context = np.zeros(_CTX_WORDS + 4, np.int32)
    context = _aligned(raw_context, 4, _CTX_WORDS)
    cf = context.view(np.float32)
    raw_arguments = np.zeros(_ARGS_WORDS + 2, np.int64)
    arguments = _aligned(raw_arguments, 2, _ARGS_WORDS)
    a32 = arguments.view(np.int32)
    for i in range(n):
        # (set in the loop, so the buffers Embree reads stay referenced through it)
        a32[0] = RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER  # flags (incoherent)
        a32[1] = -1  # feature_mask: RTC_FEATURE_FLAG_ALL
        arguments[1] = context.ctypes.data
        arguments[2] = filt
        _set_ray1(f, i32, org, dirs, tfar_in, i)
        i32[17] = _INVALID  # primID
        i32[18] = _INVALID  # geomID
        i32[19] = _INVALID  # instID[0]
        context[0] = _INVALID  # instID[0]
        context[1] = _INVALID  # instPrimID[0] (where present)
        cf[_CTX_RECORD // 4] = tfar_in[i]  # lane 0's record: a 1-ray call has one lane
        context[_CTX_RECORD // 4 + 1] = _NO_ID
        context[_CTX_RECORD // 4 + 2] = _NO_ID
        _rtcIntersect1(scene, f.ctypes.data, arguments.ctypes.data)
        _store_hit(f, i32, prim, tfar, u, v, ng, i)
        inst[i] = i32[19] if prim[i] >= 0 else -1


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

    def __init__(self, scenes: list[Scene], ids, api: _Api | None = None):
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
        self._open(api, SCENE_FLAGS)
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
