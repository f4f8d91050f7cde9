"""Finding, loading and checking the Embree 4 library; its functions called through ctypes.

The library is the one the ``embreex`` wheel ships (``embreex.libs/libembree4-*.so.4``); embreex
stays the dependency that brings the binary, and the fallback when this binding cannot be used.
It is loaded with global symbols, and into LLVM's process symbol table, when the binding is
first used (``binding()``): the compiled kernels (``kernels``) call it by name.

Fallback
--------
When the library cannot be found or loaded, its version is not a tested one (Embree 4.3 or 4.4:
the layouts and constants here are checked against their headers), or the layouts the kernels
hard-code do not match what the library actually reads and writes (``probe.check_layouts``,
run once at load: e.g. a build with ``RTC_MAX_INSTANCE_LEVEL_COUNT > 1``, which no device
property reports), ``binding()`` returns None after one ``EmbreeFallbackWarning`` (one line
naming the problem) and ``DomainBVH`` uses embreex's ``run`` as before. ``VASTRAY_EMBREEX=1``
in the environment chooses embreex's ``run`` on purpose (no warning), e.g. to compare the two.

Packets
-------
The kernels trace 8-ray packets (``rtcIntersect8``, ``rtcOccluded8``), native wherever Embree
runs its AVX, AVX2 or AVX-512 kernels (``RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED``). A packet
width the library does not trace natively is traced ray by ray, the filter called with one
lane (``N`` 1) at a time, so the tie filter's per-lane records would be read at the wrong lane:
there (an SSE-only CPU, or ``max_isa=sse4.2``) ``Api.packets`` is False and queries run the
1-ray kernels, which give the same answers. (The kernels traced 16-ray packets until
2026-12-04; native only with AVX-512, so on an AVX2 CPU, what most users have, the load-time
probe refused the library and every query went through embreex's ``run``.)

``VASTRAY_EMBREE_CONFIG`` is passed to ``rtcNewDevice`` as Embree's device configuration
string, e.g. ``max_isa=avx2`` (trace as on a CPU without AVX-512; ``sse4.2``: without AVX,
the 1-ray path) or ``verbose=1`` (Embree prints the ISA it selected); ``threads=N`` (Embree's
build threads) is added unless it names its own, N the CPUs the process may use
(``device_config``).
"""

from __future__ import annotations

import ctypes
import glob
import importlib.util
import os
import threading
import warnings
from pathlib import Path

# Embree 4 constants (include/embree4/rtcore_*.h)
RTC_DEVICE_PROPERTY_VERSION = 0
RTC_DEVICE_PROPERTY_VERSION_MAJOR = 1
RTC_DEVICE_PROPERTY_VERSION_MINOR = 2
RTC_DEVICE_PROPERTY_VERSION_PATCH = 3
#: Whether rtcIntersect8/rtcOccluded8 trace a packet as one (AVX and up) or ray by ray.
RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED = 33
RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX = 0
RTC_BUFFER_TYPE_VERTEX = 1
RTC_FORMAT_UINT3 = 0x5003
RTC_FORMAT_FLOAT3 = 0x9003
#: ``RTCBuildQuality`` (rtcore_common.h): LOW builds faster, a worse tree for tracing.
RTC_BUILD_QUALITY_LOW = 0
RTC_BUILD_QUALITY_MEDIUM = 1
RTC_SCENE_FLAG_NONE = 0
#: Embree's compact layout: leaves index the mesh's own vertex buffer instead of holding copies
#: of the vertices (Triangle4i rather than Triangle4v): about 55 % of the scene's memory, and
#: queries read that buffer, so it must outlive every query (``scenes.Scene``'s lease).
RTC_SCENE_FLAG_COMPACT = 2
RTC_SCENE_FLAG_ROBUST = 4
#: Required on every scene a query with an argument filter traverses, instanced ones included
#: (rtcInitIntersectArguments' manual).
RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS = 8
RTC_INVALID_GEOMETRY_ID = 0xFFFFFFFF
RTC_GEOMETRY_TYPE_INSTANCE = 121
RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR = 0x9234

#: (major, minor) versions of Embree whose headers the layouts and constants here were checked
#: against (``pyproject.toml`` pins embreex to the same: ``>=4.3,<4.5``).
TESTED_VERSIONS = ((4, 3), (4, 4))
#: Embree's device configuration string (``rtcNewDevice``'s argument), e.g. ``max_isa=avx2``.
EMBREE_CONFIG_ENV = "VASTRAY_EMBREE_CONFIG"


def device_config() -> str:
    """``rtcNewDevice``'s configuration: ``VASTRAY_EMBREE_CONFIG``, and ``threads=N`` for
    Embree's build threads unless that names its own, N the CPUs this process may use
    (``scene.cpus.available_cpus``: the affinity mask lowered to the cgroup CPU quota, as for
    the render threads). Left to itself Embree builds on a thread per CPU of the affinity
    mask, which in a container held to a quota of fewer CPUs spends the quota on several
    cores at once and is then throttled for the rest of the period."""
    config = os.environ.get(EMBREE_CONFIG_ENV, "").strip()
    named = {part.split("=", 1)[0].strip() for part in config.split(",") if "=" in part}
    if "threads" not in named:
        from vastray.scene.cpus import available_cpus

        config = ",".join(part for part in (config, f"threads={available_cpus()}") if part)
    return config


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


class Api:
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
            "rtcGetSceneFlags": (i32, [p]),
            "rtcSetSceneBuildQuality": (None, [p, i32]),
            "rtcSetGeometryBuildQuality": (None, [p, i32]),
            "rtcCommitScene": (None, [p]),
            "rtcRetainScene": (None, [p]),
            "rtcReleaseScene": (None, [p]),
            "rtcNewGeometry": (p, [p, i32]),
            "rtcSetSharedGeometryBuffer": (None, [p, i32, u32, i32, p, sz, sz, sz]),
            "rtcCommitGeometry": (None, [p]),
            "rtcAttachGeometry": (u32, [p, p]),
            "rtcReleaseGeometry": (None, [p]),
            "rtcSetGeometryInstancedScene": (None, [p, p]),
            "rtcSetGeometryTransform": (None, [p, u32, i32, p]),
            # (the layout probe's queries; the kernels call these by name)
            "rtcIntersect1": (None, [p, p, p]),
            "rtcOccluded1": (None, [p, p, p]),
            "rtcIntersect8": (None, [p, p, p, p]),
            "rtcOccluded8": (None, [p, p, p, p]),
        }
        for name, (res, args) in sigs.items():
            fn = getattr(self.lib, name)
            fn.restype, fn.argtypes = res, args
            setattr(self, name, fn)
        config = device_config()
        self.device = self.rtcNewDevice(config.encode() or None)
        if not self.device:
            asked = os.environ.get(EMBREE_CONFIG_ENV, "").strip()
            raise OSError(f"rtcNewDevice failed with the configuration {config!r}"
                          + (f" ({EMBREE_CONFIG_ENV}={asked!r})" if asked else ""))
        self.version = int(self.rtcGetDeviceProperty(self.device, RTC_DEVICE_PROPERTY_VERSION))
        self.major = int(self.rtcGetDeviceProperty(self.device, RTC_DEVICE_PROPERTY_VERSION_MAJOR))
        self.minor = int(self.rtcGetDeviceProperty(self.device, RTC_DEVICE_PROPERTY_VERSION_MINOR))
        if self.major != 4:
            self.close()
            raise OSError(f"{path.name} is Embree {self.version}, not Embree 4")
        if (self.major, self.minor) not in TESTED_VERSIONS:
            self.close()
            tested = ", ".join(f"{a}.{b}" for a, b in TESTED_VERSIONS)
            raise OSError(f"{path.name} is Embree {self.version}, not a tested version "
                          f"({tested}) whose layouts the kernels use")
        #: 8-ray packets traced as packets (AVX and up); else the kernels query ray by ray
        self.packets = bool(self.rtcGetDeviceProperty(
            self.device, RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED))

    def close(self) -> None:
        """Release the device (only when the library is refused: no scene of it is left)."""
        device, self.device = self.device, None
        if device:
            self.rtcReleaseDevice(device)

    def check(self, what: str) -> None:
        code = self.rtcGetDeviceError(self.device)
        if code:
            raise RuntimeError(f"Embree error {code} in {what}")


def _load_library() -> Api:
    """Find, load and check the library: its version, then the layouts the kernels use,
    against what it reads and writes (``probe.check_layouts``). Tests replace this, or the
    probe's expectations, to exercise the fallback."""
    from vastray.scene.embree.probe import check_layouts

    api = Api(find_library())
    try:
        check_layouts(api)
    except BaseException:
        api.close()
        raise
    return api


_api: Api | None = None
_api_tried = False
_api_lock = threading.Lock()


def binding() -> Api | None:
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


def description() -> dict | None:
    """How this process queries Embree, for a render's report: ``binding`` ("compiled", or
    "embreex" where the fallback runs), and for the compiled binding Embree's ``version``
    and ``queries`` ("8-ray packets", or "1 ray a call" where packets are not native or
    ``VASTRAY_QUERIES=single``); None where this process has not loaded the library (it is
    not loaded for a report). A coordinator describes its own process (its memory estimate
    loads the library); each node logs its own when its kernels are warm."""
    if not _api_tried:
        return None
    if _api is None:
        return {"binding": "embreex"}
    # the choice the queries made (loaded with the library: no import for a report)
    from vastray.scene.embree.kernels import intersect_nearest8
    from vastray.scene.embree.scenes import query_kernels

    packets = query_kernels(_api.packets)[0] is intersect_nearest8
    version = f"{_api.major}.{_api.minor}.{_api.version % 100}"
    return {"binding": "compiled", "version": version,
            "queries": "8-ray packets" if packets else "1 ray a call"}
