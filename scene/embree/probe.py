"""The layouts the kernels hard-code, checked against the Embree library actually loaded.

The kernels (``kernels``) read and write Embree's structures at fixed offsets: ``RTCRayHit``
(the ray, then the hit's primID, geomID, instID[0]), ``RTCRayQueryContext`` (Embree's instance
stack, then our tie-filter records at ``CTX_RECORD``), ``RTCFilterFunctionNArguments`` and the
``RTCRayN``/``RTCHitN`` lanes a filter sees. They are Embree 4.3/4.4's public headers for a
library built with ``RTC_MAX_INSTANCE_LEVEL_COUNT`` 1: a build with more instance levels widens
``instID[]`` (and ``instPrimID[]``), writes past a 96-byte ``RTCRayHit`` and puts an
``instStackSize`` word first in the context. No device property tells (Embree 4.3/4.4's
``RTCDeviceProperty`` reports the version, native packet sizes, feature and geometry support
and the tasking system, not the instance levels nor instance arrays), so ``check_layouts``
asks the library itself: it traces known rays through a tiny two-level scene with the
structures padded by sentinel words and checks exactly which words Embree wrote, and what a
filter given our context sees. The 8-ray packets (``RTCRayHit8``: field k of lane i at word
``8 k + i``) are checked the same way, one lane of a packet at a time, where the library
traces 8-ray packets natively (``Api.packets``; elsewhere the kernels never call them). Any
difference raises ``LayoutMismatch``, one line naming it; ``library.binding()`` then falls back
to embreex.

The checks read the expected offsets from ``kernels`` at call time (tests change them to
simulate a mismatching library).
"""

from __future__ import annotations

import ctypes
import math

import numpy as np

from vastray.scene.embree import kernels
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW, Api

#: What Embree must leave alone: every word of our buffers it has no business writing.
SENTINEL = 0xA5A5A5A5
_INVALID = 0xFFFFFFFF
_NO_ID = 0x7FFFFFFF
#: 32-bit words of each padded probe buffer (far past anything a wider build could write).
_WORDS = 64
_FILTER = ctypes.CFUNCTYPE(None, ctypes.c_void_p)


class LayoutMismatch(OSError):
    """The library loaded does not read or write Embree's structures where the kernels do."""


def _buffer(words: int = _WORDS) -> np.ndarray:
    """``words`` uint32 words, 64-byte aligned, all ``SENTINEL``."""
    raw = np.full(words + 16, SENTINEL, np.uint32)
    skip = (-raw.ctypes.data % 64) // 4
    return raw[skip:skip + words]


def _ray(org, direction) -> np.ndarray:
    """A padded RTCRayHit buffer holding one ray, set as ``kernels._set_ray1`` and
    ``kernels.intersect_nearest`` set theirs."""
    buf = _buffer()
    f = buf.view(np.float32)
    f[0:3] = org
    f[3] = 0.0  # tnear
    f[4:7] = direction
    f[7] = 0.0  # time
    f[kernels.RAYHIT_TFAR] = np.inf
    buf[9] = _INVALID  # mask
    buf[10] = 0  # id
    buf[11] = 0  # flags
    buf[kernels.RAYHIT_PRIM] = buf[kernels.RAYHIT_GEOM] = buf[kernels.RAYHIT_INST] = _INVALID
    return buf


def _context(lane: int = 0) -> np.ndarray:
    """A padded context buffer set as the kernels set their own (instID[0] and
    instPrimID[0] invalid, ``lane``'s record: t_far, no instance, no primitive)."""
    ctx = _buffer()
    ctx[0] = ctx[1] = _INVALID
    r = (kernels.CTX_RECORD + 16 * lane) // 4  # 16 bytes (kernels._RECORD_BYTES) a lane
    ctx[r:r + 1].view(np.float32)[0] = np.inf
    ctx[r + 1] = ctx[r + 2] = _NO_ID
    return ctx


def _recording_filter(seen: list, lane: int, ctx: np.ndarray):
    """A filter (Python, through ctypes) that appends to ``seen`` what ``_tie_filter`` would
    read of its arguments: N, the valid words of the call's lanes, the context's address, and
    lane ``lane``'s candidate distance, primitive, geometry and instance; and the context's
    words."""

    def filt(args):
        try:
            u64 = ctypes.c_uint64.from_address
            u32 = ctypes.c_uint32.from_address
            n = u32(args + kernels.ARG_N).value
            lane_ray, lane_hit = u64(args + kernels.ARG_RAY).value, u64(args + kernels.ARG_HIT).value
            valid_at = u64(args + kernels.ARG_VALID).value
            seen.append({
                "N": n,
                "valid": [ctypes.c_int32.from_address(valid_at + 4 * k).value
                          for k in range(min(n, kernels.PACKET))],
                "context": u64(args + kernels.ARG_CONTEXT).value,
                "t": ctypes.c_float.from_address(lane_ray + 4 * (kernels.RAYN_TFAR * n + lane)).value,
                "prim": u32(lane_hit + 4 * (kernels.HITN_PRIM * n + lane)).value,
                "geom": u32(lane_hit + 4 * (kernels.HITN_GEOM * n + lane)).value,
                "inst": u32(lane_hit + 4 * (kernels.HITN_INST * n + lane)).value,
                "ctx": ctx.copy(),
            })
        except Exception as exc:  # noqa: BLE001 - reported by the probe, never raised into Embree
            seen.append({"error": repr(exc)})

    return filt


def _diff(name: str, got: np.ndarray, want: np.ndarray, allowed: dict | None = None) -> str:
    """The first word where ``got`` differs from ``want`` (unless its value is in
    ``allowed[word]``), as one phrase; '' if none."""
    for k in np.flatnonzero(got != want):
        if allowed and int(got[k]) in allowed.get(int(k), ()):
            continue
        return f"{name} word {k} is 0x{int(got[k]):08x}, expected 0x{int(want[k]):08x}"
    return ""


def _near(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-5 * max(1.0, abs(b))


def _check_hit(ray: np.ndarray, before: np.ndarray, prim: int, geom: int, inst: int) -> str:
    """'' if the RTCRayHit buffer ``ray`` holds exactly the expected hit of the probe's ray
    (t 1, u = v = 0.25, Ng along z; the given ids) and nothing else changed since ``before``;
    else the first difference. The word after instID[0] may hold instPrimID[0] (where the
    library has instance arrays: 0 for a plain instance, the context's invalid id for none)
    or be left alone (its padding)."""
    f = ray.view(np.float32)
    floats = {"tfar": (kernels.RAYHIT_TFAR, 1.0), "Ng_x": (kernels.RAYHIT_NG, 0.0),
              "Ng_y": (kernels.RAYHIT_NG + 1, 0.0), "u": (kernels.RAYHIT_U, 0.25),
              "v": (kernels.RAYHIT_V, 0.25)}
    for name, (k, value) in floats.items():
        if not _near(float(f[k]), value):
            return f"RTCRayHit's {name} (word {k}) is {float(f[k])!r}, expected {value}"
    if not 0.0 < abs(float(f[kernels.RAYHIT_NG + 2])) < math.inf:
        return f"RTCRayHit's Ng_z (word {kernels.RAYHIT_NG + 2}) is {float(f[kernels.RAYHIT_NG + 2])!r}"
    want = before.copy()
    for k, _ in floats.values():
        want[k] = ray[k]
    want[kernels.RAYHIT_NG + 2] = ray[kernels.RAYHIT_NG + 2]
    want[kernels.RAYHIT_PRIM] = prim
    want[kernels.RAYHIT_GEOM] = geom
    want[kernels.RAYHIT_INST] = inst
    allowed = {kernels.RAYHIT_INST + 1: (0 if inst != _INVALID else _INVALID, SENTINEL)}
    problem = _diff("RTCRayHit", ray, want, allowed)
    if problem:
        return problem + (" (RTCHit laid out otherwise, e.g. instID[] wider: "
                          "RTC_MAX_INSTANCE_LEVEL_COUNT > 1?)")
    return ""


def check_layouts(api: Api) -> None:
    """Raise ``LayoutMismatch`` unless ``api``'s library reads and writes RTCRayHit, the ray
    query context and the filter's arguments where the kernels do (see the module docstring).
    A few milliseconds: three triangles, five rays."""
    from vastray.scene.embree.scenes import Scene, TopScene

    try:
        problem = _probe(api, Scene, TopScene)
    except LayoutMismatch:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of the probe refuses the library
        problem = f"the probe failed: {exc}"
    if problem:
        raise LayoutMismatch(f"{api.path.name} (Embree {api.version}) does not match the "
                             f"layouts the kernels use: {problem}")


def _probe(api: Api, Scene, TopScene) -> str:
    # Scene ``near``: triangle 1 in z = 0 under the ray, triangle 0 off it, each its own piece
    # (geometry 1, primitive 0: where Embree writes and the filter reads geomID shows); scene
    # ``far``: one triangle off the ray. Top-level scene: instance 0 of ``far``, instance 1 of
    # ``near``.
    pad = np.zeros((7, 3), np.float32)
    pad[:6] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0], [6, 5, 0], [5, 6, 0]]
    near = Scene(pad[:6], np.array([[3, 4, 5], [0, 1, 2]], np.uint32), api=api,
                 mesh_quality=RTC_BUILD_QUALITY_LOW, piece_triangles=1)
    far = Scene(pad[3:6], np.array([[0, 1, 2]], np.uint32), api=api)
    top = TopScene([far, near], [0, 1], api=api)
    try:
        for scene, inst in ((top, 1), (near, _INVALID)):
            problem = _probe_intersect(api, scene, inst) or (
                _probe_packet(api, scene, inst) if api.packets else "")
            if problem:
                return problem
        return _probe_occluded(api, top) or (
            _probe_occluded_packet(api, top) if api.packets else "")
    finally:
        for scene in (top, near, far):
            scene.close()


def _arguments(ctx: np.ndarray, callback) -> np.ndarray:
    """RTCIntersectArguments as ``kernels.intersect_nearest`` sets its own: the argument
    filter invoked, every feature, the context ``ctx`` and the filter ``callback`` (kept
    alive by the caller through the query)."""
    args = _buffer(16).view(np.int64)
    args[:] = 0
    a32 = args.view(np.int32)
    a32[0] = kernels.RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER
    a32[1] = -1  # RTC_FEATURE_FLAG_ALL
    args[1] = ctx.ctypes.data
    args[2] = ctypes.cast(callback, ctypes.c_void_p).value
    return args


def _probe_intersect(api: Api, scene, inst: int) -> str:
    """One ``rtcIntersect1`` with a filter reading its arguments where ``_tie_filter`` does."""
    where = "through an instance" if inst != _INVALID else "of a scene"
    ray = _ray([0.25, 0.25, -1.0], [0.0, 0.0, 1.0])
    before = ray.copy()
    ctx = _context()
    ctx_before = ctx.copy()
    seen = []
    filt = _recording_filter(seen, 0, ctx)
    callback = _FILTER(filt)
    args = _arguments(ctx, callback)
    with scene._lease() as handle:
        api.rtcIntersect1(handle, ray.ctypes.data, args.ctypes.data)
    api.check("the layout probe")

    if not seen:
        return (f"no hit {where} reached the filter (RTCRayQueryContext not instID[0] first, "
                f"or instances dropped: RTC_MAX_INSTANCE_LEVEL_COUNT > 1?)")
    got = seen[0]
    if "error" in got:
        return f"the filter could not read its arguments ({got['error']})"
    if got["N"] != 1 or got["valid"] != [-1] or got["context"] != ctx.ctypes.data:
        return (f"RTCFilterFunctionNArguments not as expected (N {got['N']}, valid "
                f"{got['valid']}, context 0x{got['context']:x} for 0x{ctx.ctypes.data:x})")
    if not _near(got["t"], 1.0) or (got["prim"], got["geom"], got["inst"]) != (0, 1, inst):
        return (f"the filter read t {got['t']}, primID {got['prim']}, geomID {got['geom']}, "
                f"instID {got['inst']} {where}, expected 1.0, 0, 1, {inst} (RTCRayN/RTCHitN "
                f"lanes elsewhere)")
    # During the query Embree's instance stack holds the instance: instID[0] (and instPrimID[0]
    # 0 where built with instance arrays) in the words before our record, which it never
    # touches.
    want_ctx = ctx_before.copy()
    want_ctx[0] = inst
    problem = _diff("RTCRayQueryContext (in the filter)", got["ctx"], want_ctx,
                    {1: (0, _INVALID)} if inst != _INVALID else None)
    if problem:
        return problem + " (Embree's part larger than instID[1], instPrimID[1]?)"
    # After it, the stack is popped: every word as we left it.
    problem = _diff("RTCRayQueryContext (after the query)", ctx, ctx_before)
    if problem:
        return problem
    return _check_hit(ray, before, 0, 1, inst)


def _probe_occluded(api: Api, scene) -> str:
    """One ``rtcOccluded1``: Embree writes tfar (-inf, a hit) and nothing else."""
    ray = _ray([0.25, 0.25, -1.0], [0.0, 0.0, 1.0])
    want = ray.copy()
    want.view(np.float32)[kernels.RAYHIT_TFAR] = -np.inf
    with scene._lease() as handle:
        api.rtcOccluded1(handle, ray.ctypes.data, None)
    api.check("the layout probe")
    return _diff("RTCRay (occlusion)", ray, want)


#: The packet lane the packet probes trace (not lane 0: a layout that ignores lanes shows).
_LANE = 5


def _packet_words() -> int:
    return kernels.PACKET_FIELDS * kernels.PACKET


def _packet(ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A padded RTCRayHit8 buffer holding the 1-ray buffer ``ray``'s fields in lane
    ``_LANE`` (every other lane left at the sentinel) and its ``valid`` mask (that lane
    only), set as ``kernels.intersect_nearest8`` sets its own."""
    buf = _buffer(_packet_words() + 64)
    for field in range(kernels.PACKET_FIELDS):
        buf[field * kernels.PACKET + _LANE] = ray[field]
    valid = _buffer(kernels.PACKET).view(np.int32)
    valid[:] = 0
    valid[_LANE] = -1
    return buf, valid


def _probe_packet(api: Api, scene, inst: int) -> str:
    """One ``rtcIntersect8`` with one lane valid: the filter sees 8 lanes and that lane's
    candidate where ``_tie_filter`` reads them, and Embree writes that lane's hit and nothing
    else (the other lanes and the padding keep their sentinels)."""
    where = "through an instance" if inst != _INVALID else "of a scene"
    single = _ray([0.25, 0.25, -1.0], [0.0, 0.0, 1.0])
    ray, valid = _packet(single)
    before = ray.copy()
    ctx = _context(_LANE)
    seen = []
    filt = _recording_filter(seen, _LANE, ctx)
    callback = _FILTER(filt)
    args = _arguments(ctx, callback)
    with scene._lease() as handle:
        api.rtcIntersect8(valid.ctypes.data, handle, ray.ctypes.data, args.ctypes.data)
    api.check("the packet layout probe")
    if not seen:
        return f"no hit {where} of an 8-ray packet reached the filter"
    got = seen[0]
    if "error" in got:
        return f"the filter of an 8-ray packet could not read its arguments ({got['error']})"
    want_valid = [-1 if k == _LANE else 0 for k in range(kernels.PACKET)]
    if got["N"] != kernels.PACKET or got["valid"] != want_valid:
        return (f"an 8-ray packet's filter saw N {got['N']} and valid {got['valid']}, expected "
                f"N {kernels.PACKET} and lane {_LANE} only")
    if not _near(got["t"], 1.0) or (got["prim"], got["geom"], got["inst"]) != (0, 1, inst):
        return (f"the filter of an 8-ray packet read t {got['t']}, primID {got['prim']}, "
                f"geomID {got['geom']}, instID {got['inst']} in lane {_LANE} {where}, "
                f"expected 1.0, 0, 1, {inst}")
    # the lane's fields, read as a 1-ray buffer, must hold the hit the 1-ray probe checks
    pad = np.full(_WORDS - kernels.PACKET_FIELDS, SENTINEL, np.uint32)
    lane = np.concatenate([ray[_LANE:_packet_words():kernels.PACKET], pad])
    lane_before = np.concatenate([before[_LANE:_packet_words():kernels.PACKET], pad])
    problem = _check_hit(lane, lane_before, 0, 1, inst)
    if problem:
        return f"8-ray packet lane {_LANE}: {problem}"
    others = np.ones(len(ray), bool)
    others[_LANE:_packet_words():kernels.PACKET] = False
    problem = _diff("RTCRayHit8 (other lanes and padding)", ray[others], before[others])
    return problem and problem + " (RTCRayHit8 laid out otherwise?)"


def _probe_occluded_packet(api: Api, scene) -> str:
    """One ``rtcOccluded8`` with one lane valid: Embree writes that lane's tfar (-inf, a hit)
    and nothing else."""
    ray, valid = _packet(_ray([0.25, 0.25, -1.0], [0.0, 0.0, 1.0]))
    want = ray.copy()
    want.view(np.float32)[kernels.RAYHIT_TFAR * kernels.PACKET + _LANE] = -np.inf
    with scene._lease() as handle:
        api.rtcOccluded8(valid.ctypes.data, handle, ray.ctypes.data, None)
    api.check("the packet layout probe")
    return _diff("RTCRay8 (occlusion)", ray, want)
