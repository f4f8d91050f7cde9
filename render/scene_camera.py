"""A scene with its camera replaced by one given in code (the Python API's ``camera=``).

The result is a ``SceneConfig`` read from TOML text like any other, so the camera is checked
by the same parser as a SCENE.toml's ``[camera]`` and reaches node processes (which receive
the scene's text) unchanged.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping

import numpy as np

from vastray.render.camera import Camera
from vastray.render.scene_config import SceneConfig, parse_scene_config
from vastray.scene.errors import InputError

#: How a camera given in code is named in errors.
CAMERA_SOURCE = "camera"


def camera_table(camera: Mapping | Camera) -> dict:
    """The ``[camera]`` table of ``camera``: a ``Camera`` (its position, look_at, up and fov;
    its size is the render's business) or a mapping with any of those keys (those left out
    frame the store, as in SCENE.toml), as plain Python values."""
    if isinstance(camera, Camera):
        camera = {"position": camera.position, "look_at": camera.look_at, "up": camera.up,
                  "fov": camera.fov}
    if not isinstance(camera, Mapping):
        raise InputError(CAMERA_SOURCE, "must be a dict with position, look_at, up and fov "
                                        f"(any of them), or a Camera; got "
                                        f"{type(camera).__name__}")
    return {str(key): _plain(value) for key, value in camera.items()}


def with_camera(config: SceneConfig, camera: Mapping | Camera) -> SceneConfig:
    """``config`` with its ``[camera]`` table (keys, orbit and all) replaced by ``camera``
    (see ``camera_table``); lights and materials unchanged.

    Raises
    ------
    InputError
        For an unknown key or a bad value, named as in SCENE.toml (``camera.fov``).
    """
    table = camera_table(camera)
    try:
        parse_scene_config(to_toml({"camera": table}), CAMERA_SOURCE)  # the camera's own errors
        doc = tomllib.loads(config.text) if config.text else {}
        doc["camera"] = table
        text = to_toml(doc)
    except TypeError as exc:
        raise InputError(CAMERA_SOURCE, str(exc)) from None
    return parse_scene_config(text, config.source or CAMERA_SOURCE)


def to_toml(doc: dict) -> str:
    """TOML text of a parsed document (every table inline: what ``tomllib`` reads back as
    ``doc``).

    Raises
    ------
    TypeError
        For a value TOML cannot hold as the scene files use it (a date, None, an object).
    """
    return "".join(f"{_key(key)} = {_value(key, value)}\n" for key, value in doc.items())


def _key(key: str) -> str:
    return json.dumps(str(key), ensure_ascii=False)


def _value(key: str, value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)  # also TOML's: 0.1, 1e-05, inf, -inf, nan
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list):
        return "[" + ", ".join(_value(key, v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(k, v)}" for k, v in value.items()) + "}"
    raise TypeError(f"{key} must be numbers (or lists of them), got {value!r}")


def _plain(value):
    """numpy scalars and arrays as Python numbers and lists; anything else as it is."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
