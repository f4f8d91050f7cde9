"""The render progress bar, honest about the first run after an install: numba then compiles
the ray kernels (tens of seconds, once; later runs load them from numba's cache), and a bar
that took that time for render speed would show an ETA of minutes for a render of seconds."""

from __future__ import annotations

import os

from vastray.scene.progressbar import Bar

#: What the bar says in place of the ETA until the compiled kernels have done their first work.
COMPILING = "compiling kernels (first run only)"


def kernels_compiled() -> bool:
    """Whether numba's cache holds the kernels every render runs (camera rays, hit points,
    film sums): False on the first run after an install or an upgrade.

    The kernels only some renders run (AO or path shading, box walks, Embree calls) compile on
    their first use too, in seconds each; a cache numba cannot be asked about counts as
    compiled (nothing is said then).
    """
    from numba.core.registry import CPUDispatcher

    from vastray.render import kernels

    for name in ("camera_rays", "hit_points", "film_add"):
        kernel = getattr(kernels, name, None)
        if not isinstance(kernel, CPUDispatcher):
            continue
        index = getattr(getattr(kernel._cache, "_cache_file", None), "_index_path", None)
        if index is not None and not os.path.exists(index):
            return False
    return True


class RenderBar(Bar):
    """``tqdm`` over a render's paths which, while the kernels compile (``compiled`` False),
    shows at once that it is compiling instead of an ETA, and restarts its rate at the first
    paths done, so that the ETA it then shows counts no compile time.

    Parameters
    ----------
    compiled : whether the kernels are in numba's cache (default: ``kernels_compiled()``,
        asked only when the bar is shown).
    **kwargs : as ``tqdm``'s.
    """

    def __init__(self, *args, compiled: bool | None = None, **kwargs):
        self.compiling = self.rate_pending = False
        if not kwargs.get("disable") and not (kernels_compiled() if compiled is None
                                              else compiled):
            self.compiling = True
            kwargs["delay"] = 0  # say so now: the compile is the long wait
            kwargs["bar_format"] = ("{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
                                    f"[{{elapsed}}, {COMPILING}]")
        super().__init__(*args, **kwargs)

    def update(self, n: float = 1) -> bool | None:
        if self.compiling:  # the first paths are done: their kernels are compiled
            self.compiling, self.rate_pending = False, True
            done, start = self.n + n, self.start_t
            self.reset()  # forget the rate of the compile, and show none until the next paths
            self.start_t = start  # but not the time elapsed
            self.bar_format = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}]"
            self.n = self.last_print_n = done
            self.refresh()
            return True
        if self.rate_pending:  # paths done since the compile: a rate worth showing
            self.rate_pending, self.bar_format = False, None
        return super().update(n)
