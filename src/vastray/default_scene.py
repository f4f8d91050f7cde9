"""The built-in default scene: a generated Richtmyer-Meshkov mixing layer, made on first use."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from vastray.scene.generate import generate

log = logging.getLogger(__name__)

#: Parameters of the default scene; part of its cache folder's name, so a change regenerates it.
DEFAULT_SCENE = {"scene": "rm", "resolution": 128, "grid": (2, 2, 2), "seed": 0}


def cache_dir() -> Path:
    """``$VASTRAY_CACHE``, else ``$XDG_CACHE_HOME/vastray``, else ``~/.cache/vastray``."""
    if os.environ.get("VASTRAY_CACHE"):
        return Path(os.environ["VASTRAY_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "vastray"


def default_store(quiet: bool = False) -> Path:
    """Path of the default scene's store, generating it the first time."""
    p = DEFAULT_SCENE
    grid = "x".join(map(str, p["grid"]))
    path = cache_dir() / f"default-{p['scene']}-{p['resolution']}-{grid}-seed{p['seed']}.store"
    if not (path / "manifest.json").is_file():
        log.info("generating the default scene into %s", path)
        generate(p["scene"], path, p["resolution"], grid=p["grid"], seed=p["seed"],
                 overwrite=True, progress=not quiet)
    return path
