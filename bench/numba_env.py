"""The environment for child processes whose numba kernels must really be bounds-checked.

numba's on-disk cache does not key on ``NUMBA_BOUNDSCHECK``: with the flag set, a process
still loads the unchecked kernels an earlier run cached, and an index out of range then
corrupts memory (a segfault, in one check of session 34) instead of raising ``IndexError``.
``.ci/run`` gives its bounds-checked tests a fresh ``NUMBA_CACHE_DIR``; the benches that run
``vastray`` processes do the same through ``checked_env``.
"""

from __future__ import annotations

import tempfile

_fresh_cache: str | None = None  # one per script run: its processes share the checked kernels


def checked_env(env: dict[str, str]) -> dict[str, str]:
    """``env`` itself, or, where it asks for bounds checks (``NUMBA_BOUNDSCHECK=1``) and names
    no numba cache folder, a copy with a fresh one (made once per process), so that every
    kernel is compiled checked."""
    global _fresh_cache
    if env.get("NUMBA_BOUNDSCHECK", "").strip() != "1" or env.get("NUMBA_CACHE_DIR"):
        return env
    if _fresh_cache is None:
        _fresh_cache = tempfile.mkdtemp(prefix="vastray-checked-numba-")
    return dict(env, NUMBA_CACHE_DIR=_fresh_cache)
