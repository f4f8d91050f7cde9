"""Probes of the compiled Embree binding's state for the tests: not production code."""

from __future__ import annotations

import gc

from numba.core.dispatcher import Dispatcher

from vastray.scene import embree


def live_scenes() -> int:
    """How many scenes built by the binding are not released yet: open scenes, reachable or
    waiting to be collected (eviction and ``close`` must release them)."""
    return sum(1 for obj in gc.get_objects()
               if issubclass(type(obj), embree._SceneHandle) and obj.handle)


def buffer_pointer(scene: embree.Scene, vertex: bool = True) -> int:
    """Address of the vertex (or index) buffer Embree uses for ``scene``'s mesh (zero copy:
    it is the array's own)."""
    api = scene._api
    kind = embree.RTC_BUFFER_TYPE_VERTEX if vertex else embree.RTC_BUFFER_TYPE_INDEX
    with scene._lease() as handle:
        return api.rtcGetGeometryBufferData(api.rtcGetGeometry(handle, scene.geom_id), kind, 0) or 0


def compiled_functions(module) -> list[Dispatcher]:
    """The numba-compiled functions a module defines (kernels and their inlined helpers)."""
    return [f for f in vars(module).values() if isinstance(f, Dispatcher)]
