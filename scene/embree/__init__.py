"""Our binding of Embree 4's C API: zero-copy scenes from numpy arrays, traced by numba kernels.

Modules
-------
- ``library``: finding and loading the library (the one the embreex wheel ships), its
  functions called through ctypes, Embree's constants, ``binding()`` and the fallback to
  embreex's ``run``.
- ``probe``: the layouts the kernels hard-code (RTCRayHit, the ray query context, the filter's
  arguments) checked against the library loaded, by tracing known rays into sentinel-padded
  buffers, before the binding is used.
- ``intrinsics``: Embree's query functions called by name, and raw memory access, from
  numba-compiled code (so the kernels are cached on disk).
- ``kernels``: the serial ``nogil`` query kernels, 8-ray packets (and 1-ray twins), and the tie filter
  that makes closest hits independent of traversal order.
- ``launch``: a query's ray arrays checked, its rays split over threads.
- ``scenes``: ``Scene`` (one mesh, zero copy) and ``TopScene`` (instances of several), their
  ownership and queries.

Callers import from the module that defines a name; this package re-exports nothing.
"""
