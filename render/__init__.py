"""Rendering: cameras, films, integrators, lights, tracers and image files.

This package is also the Python API's entry point: calling it, ``vastray.render(store,
...)``, calls ``vastray.api.render`` (see its docstring), so a notebook writes the short name
while ``vastray.render.camera`` and the other modules stay where they are.
"""

import sys
import types


class _CallableModule(types.ModuleType):
    def __call__(self, *args, **kwargs):
        from vastray.api import render

        return render(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
