"""vastray: out-of-core and distributed path tracing of triangle data too large for one
machine's memory.

The Python API (see README, "Python API")::

    import vastray
    out = vastray.render("rm.store", width=64, height=48, spp=4)
    out.image          # (48, 64, 3) float32 radiance
    out.report         # what `vastray render --report` writes
    out.to_png("rm.png")

Its names are imported on first use, so ``import vastray`` (and every ``vastray.*`` module a
node process imports) stays light.
"""

from __future__ import annotations

__all__ = ["Camera", "RenderOutput", "VastrayError", "render", "render_async"]

_WHERE = {
    # vastray.render is the package vastray/render, callable as vastray.api.render
    "render": None, "render_async": "vastray.api", "RenderOutput": "vastray.api",
    "VastrayError": "vastray.scene.errors", "Camera": "vastray.render.camera",
}


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'vastray' has no attribute {name!r}")
    import importlib

    if _WHERE[name] is None:
        return importlib.import_module(f"vastray.{name}")
    return getattr(importlib.import_module(_WHERE[name]), name)


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
