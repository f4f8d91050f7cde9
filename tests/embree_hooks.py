"""Probes of the compiled Embree binding's state for the tests: not production code."""

from __future__ import annotations

import ctypes
import gc

from numba.core.dispatcher import Dispatcher

from vastray.scene.embree.library import RTC_BUFFER_TYPE_INDEX, RTC_BUFFER_TYPE_VERTEX
from vastray.scene.embree.scenes import Scene, _SceneHandle


def live_scenes() -> int:
    """How many scenes built by the binding are not released yet: open scenes, reachable or
    waiting to be collected (eviction and ``close`` must release them)."""
    return sum(1 for obj in gc.get_objects()
               if issubclass(type(obj), _SceneHandle) and obj.handle)


def buffer_pointer(scene: Scene, vertex: bool = True) -> int:
    """Address of the vertex (or index) buffer Embree uses for ``scene``'s mesh (zero copy:
    it is the array's own)."""
    p = ctypes.c_void_p
    get_geometry, get_data = scene._api.lib.rtcGetGeometry, scene._api.lib.rtcGetGeometryBufferData
    get_geometry.restype, get_geometry.argtypes = p, [p, ctypes.c_uint32]
    get_data.restype, get_data.argtypes = p, [p, ctypes.c_int, ctypes.c_uint32]
    kind = RTC_BUFFER_TYPE_VERTEX if vertex else RTC_BUFFER_TYPE_INDEX
    with scene._lease() as handle:
        return get_data(get_geometry(handle, scene.geom_id), kind, 0) or 0


def compiled_functions(module) -> list[Dispatcher]:
    """The numba-compiled functions a module defines (kernels and their inlined helpers)."""
    return [f for f in vars(module).values() if isinstance(f, Dispatcher)]
