"""The built-in default scene: a generated Richtmyer-Meshkov mixing layer, made on first use,
coloured by how far the mixing has carried each point of the interface."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from vastray.render.scene_config import SceneConfig, parse_scene_config
from vastray.scene.generate import generate

log = logging.getLogger(__name__)

#: Parameters of the default scene; part of its cache folder's name, so a change regenerates it.
DEFAULT_SCENE = {"scene": "rm", "resolution": 160, "grid": (2, 2, 2), "seed": 0, "version": 3}

#: Camera and lights of the default scene: a low oblique view across the folded sheet (z up),
#: a warm key light from above and a dim sky.
DEFAULT_SCENE_TOML = """\
[camera]
position = [1.55, -0.62, 1.12]
look_at = [0.5, 0.5, 0.47]
up = [0, 0, 1]
fov = 38

[[light]]
type = "directional"
direction = [-0.35, 0.55, -1.0]
irradiance = [2.6, 2.45, 2.2]

[[light]]
type = "ambient"
radiance = [0.22, 0.25, 0.3]

[material]
diffuse = 0.8
specular = 0.04
shininess = 20
"""


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
    path = (cache_dir() / f"default-{p['scene']}-{p['resolution']}-{grid}-seed{p['seed']}"
                          f"-v{p['version']}.store")
    if not (path / "manifest.json").is_file():
        log.info("generating the default scene into %s", path)
        generate(p["scene"], path, p["resolution"], grid=p["grid"], seed=p["seed"],
                 overwrite=True, progress=not quiet)
    return path


def default_scene_config() -> SceneConfig:
    """Camera, lights and material of the default scene."""
    return parse_scene_config(DEFAULT_SCENE_TOML, "the built-in scene")
