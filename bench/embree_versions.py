"""The same camera rays through the same 8-ray kernel, on Embree 4.4 (embreex's library, what
vastray loads) and on Embree 3.13 (the library Mitsuba 3 ships): is the gap to Mitsuba's camera
query the library, the triangle test, the tie filter, or what is around the kernel?

Each side traces one thread of ``rtcIntersect8`` packets (incoherent, 8 consecutive rays a
packet, the layout of ``scene/embree/kernels.py``) over Mitsuba's own camera rays of
``bench/peers.py``'s scene (pixel-major, 16 jittered samples a pixel, 256 x 256), on one BVH
of the scan built with each triangle test (``robust``: Embree's watertight test, vastray's;
``fast``: Embree's default, Mitsuba's), the best of 7 runs. Embree 4 runs with and without
vastray's tie filter; Embree 3 has none. ``vastray Scene.intersect`` is the product's call on
the same rays in the renderer's batches (``RenderSettings.batch_size``: its kernel plus its
inputs' checks, the outputs it allocates and every hit field it copies out), and ``Mitsuba
ray_intersect_preliminary`` Mitsuba's own call (its LLVM kernels' 16-ray packets, one thread:
``dr.set_thread_count(1)``).

Prints ns a ray of each, then each factor between Mitsuba's call and vastray's:
``embree4_over_embree3=`` (the library, robust and fast, no filter), ``tie_filter_cost=``,
``watertight_cost=``, ``around_kernel_cost=`` (what ``Scene.intersect`` adds to its kernel) and
``product_over_mitsuba=``. Needs Mitsuba 3 (``pip install mitsuba``) for its library
and rays; its Embree 3 functions are in the C++ namespace ``mitsuba``.

    python bench/embree_versions.py [--scan meshes/turbine_blade_199k.ply]
"""

from __future__ import annotations

import argparse
import ctypes
import sys
import time
from pathlib import Path

import numpy as np
import peers
from numba import njit

from vastray.render.integrators import RenderSettings
from vastray.scene.embree.intrinsics import _external4, rtc_intersect8
from vastray.scene.embree.kernels import (
    _INVALID,
    PACKET,
    RAYHIT_PRIM,
    RAYHIT_TFAR,
    _aligned,
    _fresh_records,
    _no_hits,
    _packet_buffers,
    _packet_constants,
    _packet_rays,
    _query_buffers,
    _query_set_up,
    filter_address,
)
from vastray.scene.embree.library import RTC_SCENE_FLAG_ROBUST
from vastray.scene.embree.scenes import FILTER_FLAG, Scene

#: Embree 3's API in Mitsuba's library (``RTC_NAMESPACE mitsuba``), by mangled name.
E3 = {
    "device": "_ZN7mitsuba12rtcNewDeviceEPKc",
    "scene": "_ZN7mitsuba11rtcNewSceneEPNS_11RTCDeviceTyE",
    "flags": "_ZN7mitsuba16rtcSetSceneFlagsEPNS_10RTCSceneTyENS_13RTCSceneFlagsE",
    "geometry": "_ZN7mitsuba14rtcNewGeometryEPNS_11RTCDeviceTyENS_15RTCGeometryTypeE",
    "buffer": ("_ZN7mitsuba26rtcSetSharedGeometryBufferEPNS_13RTCGeometryTyENS_13RTCBufferType"
               "EjNS_9RTCFormatEPKvmmm"),
    "commit_geometry": "_ZN7mitsuba17rtcCommitGeometryEPNS_13RTCGeometryTyE",
    "attach": "_ZN7mitsuba17rtcAttachGeometryEPNS_10RTCSceneTyEPNS_13RTCGeometryTyE",
    "commit": "_ZN7mitsuba14rtcCommitSceneEPNS_10RTCSceneTyE",
    "release": "_ZN7mitsuba15rtcReleaseSceneEPNS_10RTCSceneTyE",
    "intersect8": ("_ZN7mitsuba13rtcIntersect8EPKiPNS_10RTCSceneTyEPNS_19RTCIntersectContext"
                   "EPNS_10RTCRayHit8E"),
}
#: rtcIntersect8(valid, scene, context, rayhit): Embree 3's argument order.
e3_intersect8 = _external4(E3["intersect8"])


@njit(nogil=True)
def embree3_nearest8(scene, org, dirs, tfar_in, prim, tfar):
    """Closest hits through Embree 3's ``rtcIntersect8``, the packets filled as vastray's
    kernel fills them; the context as ``rtcInitIntersectContext`` makes it (incoherent, no
    filter, instID[0] invalid)."""
    n = org.shape[0]
    f, i32, valid = _packet_buffers()
    raw = np.zeros(16, np.int32)
    context = _aligned(raw, 4, 8)  # flags (4 bytes), pad, filter (8), instID[1] (at 16)
    _packet_constants(f, i32)
    for start in range(0, n, PACKET):
        m = min(PACKET, n - start)
        context[0] = 0
        context[2] = 0
        context[3] = 0
        context[4] = _INVALID
        _packet_rays(f, valid, org, dirs, tfar_in, start, m)
        _no_hits(i32, m)
        e3_intersect8(valid.ctypes.data, scene, context.ctypes.data, f.ctypes.data)
        for lane in range(m):
            prim[start + lane] = i32[RAYHIT_PRIM * PACKET + lane]
            tfar[start + lane] = f[RAYHIT_TFAR * PACKET + lane]


@njit(nogil=True)
def embree4_nearest8(scene, filt, flags, org, dirs, tfar_in, prim, tfar):
    """``kernels.intersect_nearest8``'s loop (query ``flags``: 2 invokes the tie filter
    ``filt``, 0 none), copying out the primitive and distance only, as the Embree 3 side."""
    n = org.shape[0]
    f, i32, valid = _packet_buffers()
    context, cf, arguments, a32 = _query_buffers()
    _packet_constants(f, i32)
    for start in range(0, n, PACKET):
        m = min(PACKET, n - start)
        _query_set_up(arguments, a32, context, filt, flags)
        _packet_rays(f, valid, org, dirs, tfar_in, start, m)
        _no_hits(i32, m)
        _fresh_records(context, cf, tfar_in, start, m)
        rtc_intersect8(valid.ctypes.data, scene, f.ctypes.data, arguments.ctypes.data)
        for lane in range(m):
            prim[start + lane] = i32[RAYHIT_PRIM * PACKET + lane]
            tfar[start + lane] = f[RAYHIT_TFAR * PACKET + lane]


class Embree3:
    """Mitsuba's Embree 3 library, loaded where numba's compiled code finds its symbols."""

    def __init__(self, path: Path):
        import llvmlite.binding as llvm

        self.lib = ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        llvm.load_library_permanently(str(path))
        vp, u32, size = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_size_t
        self.new_device = self._fn("device", vp, ctypes.c_char_p)
        self.new_scene = self._fn("scene", vp, vp)
        self.set_flags = self._fn("flags", None, vp, ctypes.c_int)
        self.new_geometry = self._fn("geometry", vp, vp, ctypes.c_int)
        self.set_buffer = self._fn("buffer", None, vp, ctypes.c_int, u32, ctypes.c_int, vp,
                                   size, size, size)
        self.commit_geometry = self._fn("commit_geometry", None, vp)
        self.attach = self._fn("attach", u32, vp, vp)
        self.commit = self._fn("commit", None, vp)
        self.release = self._fn("release", None, vp)
        self.device = self.new_device(None)

    def _fn(self, key: str, result, *args):
        fn = getattr(self.lib, E3[key])
        fn.restype, fn.argtypes = result, list(args)
        return fn

    def scene(self, vertices: np.ndarray, indices: np.ndarray, flags: int) -> int:
        """A committed scene of one triangle mesh (the arrays must outlive it; ``vertices``
        has a spare row: Embree reads 16 bytes a vertex)."""
        scene = self.new_scene(self.device)
        self.set_flags(scene, flags)
        geometry = self.new_geometry(self.device, 0)  # RTC_GEOMETRY_TYPE_TRIANGLE
        self.set_buffer(geometry, 1, 0, 0x9003, vertices.ctypes.data, 0, 12,
                        len(vertices) - 1)  # RTC_BUFFER_TYPE_VERTEX, RTC_FORMAT_FLOAT3
        self.set_buffer(geometry, 0, 0, 0x5003, indices.ctypes.data, 0, 12,
                        len(indices))  # RTC_BUFFER_TYPE_INDEX, RTC_FORMAT_UINT3
        self.commit_geometry(geometry)
        self.attach(scene, geometry)
        self.commit(scene)
        return scene


def _batched(scene: Scene, org, dirs, t_far) -> None:
    """``scene.intersect`` over the rays in the renderer's batches, one thread (one call of a
    million rays would fault in 36 MB of fresh outputs each time, which a render never does)."""
    size = RenderSettings.batch_size
    for start in range(0, len(org), size):
        scene.intersect(org[start:start + size], dirs[start:start + size],
                        t_far[start:start + size], 1)


def best(run, repeat: int = 7) -> float:
    run()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scan", default="meshes/turbine_blade_199k.ply",
                        help="a mesh, or a volume and its iso value as FILE:ISO, as "
                             "bench/peers.py --scan (default: the turbine blade)")
    args = parser.parse_args()
    try:
        import drjit as dr
        import mitsuba
    except ImportError:
        print("needs Mitsuba 3: pip install mitsuba", file=sys.stderr)
        return 2
    library = Path(mitsuba.__file__).parent / "libembree3.so"
    if not library.is_file():
        print(f"no Embree 3 library in this Mitsuba ({library})", file=sys.stderr)
        return 2
    reason = peers.try_llvm()
    if reason is not None:  # its rays and its call come from the LLVM variant
        print(f"Mitsuba's llvm_ad_rgb does not run here ({reason}); bench/README.md#peerspy "
              "says what it needs (a libLLVM Dr.Jit accepts)", file=sys.stderr)
        return 2
    embree3 = Embree3(library)
    store, label = peers.scan_store(args.scan)
    camera, light_pos, intensity = peers.setup(store)
    dom = store.load_domain(0, mmap=False)
    vertices = np.zeros((len(dom.vertices) + 1, 3), np.float32)
    vertices[:-1] = dom.vertices
    indices = np.ascontiguousarray(dom.indices, np.uint32)
    ply = peers.CACHE / "embree_versions.ply"
    peers.write_ply(ply, vertices[:-1], indices)
    peer = peers.MitsubaRenderer("llvm_ad_rgb", ply, camera, light_pos, intensity, 1, 1)
    mi, spp = peer.mi, 16
    n = peers.WIDTH * peers.HEIGHT * spp
    pixel = dr.arange(mi.UInt32, n) // spp
    jitter = np.random.default_rng(7).random((2, n), dtype=np.float32)
    position = mi.Point2f((mi.Float(pixel % peers.WIDTH) + mi.Float(jitter[0])) / peers.WIDTH,
                          (mi.Float(pixel // peers.WIDTH) + mi.Float(jitter[1])) / peers.HEIGHT)
    ray, _ = peer.scene.sensors()[0].sample_ray(0.0, 0.5, position, mi.Point2f(0.5, 0.5))
    dr.eval(ray)
    org = np.ascontiguousarray(np.array(ray.o).T, np.float32)
    dirs = np.ascontiguousarray(np.array(ray.d).T, np.float32)
    t_far = np.full(n, np.inf, np.float32)
    prim, tfar = np.empty(n, np.int32), np.empty(n, np.float32)
    mitsuba_s = best(lambda: dr.eval(peer.scene.ray_intersect_preliminary(ray).t))
    print(f"{label}: {n:,} camera rays of Mitsuba's camera, one thread each, best of 7")
    print(f"  Mitsuba ray_intersect_preliminary (its fast test, 16-ray packets): "
          f"{mitsuba_s / n * 1e9:.1f} ns a ray")
    ns = {}
    for test, flags in (("robust", RTC_SCENE_FLAG_ROBUST), ("fast", 0)):
        scene3 = embree3.scene(vertices, indices, flags)
        ns[test, "embree3"] = best(lambda s=scene3: embree3_nearest8(s, org, dirs, t_far, prim,
                                                                tfar)) / n * 1e9
        hits3 = prim.copy()
        embree3.release(scene3)
        scene4 = Scene(vertices[:-1], indices, flags=flags | FILTER_FLAG)
        try:
            with scene4._lease() as handle:
                for name, query in (("embree4", 0), ("embree4_tie_filter", 2)):
                    ns[test, name] = best(lambda q=query: embree4_nearest8(
                        handle, filter_address(), q, org, dirs, t_far, prim, tfar)) / n * 1e9
                    same = float(np.mean(prim == hits3))
                    print(f"  {test:6s} {name:19s} {ns[test, name]:6.1f} ns a ray "
                          f"(the same triangle as Embree 3 for {same:.5f} of the rays)")
            ns[test, "product"] = best(lambda s=scene4: _batched(s, org, dirs, t_far)) / n * 1e9
        finally:
            scene4.close()
        print(f"  {test:6s} {'embree3':19s} {ns[test, 'embree3']:6.1f} ns a ray")
        print(f"  {test:6s} {'vastray Scene.intersect':19s} {ns[test, 'product']:6.1f} ns a ray")
    print("embree4_over_embree3=" + ",".join(
        f"{test}:{ns[test, 'embree4'] / ns[test, 'embree3']:.3f}" for test in ("robust", "fast")))
    print(f"tie_filter_cost={ns['robust', 'embree4_tie_filter'] / ns['robust', 'embree4']:.3f}")
    print(f"watertight_cost={ns['robust', 'embree4'] / ns['fast', 'embree4']:.3f}")
    print(f"around_kernel_cost={ns['robust', 'product'] / ns['robust', 'embree4_tie_filter']:.3f}")
    print(f"product_over_mitsuba={ns['robust', 'product'] / (mitsuba_s / n * 1e9):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
