"""SCENE.toml: camera, lights and materials of a render.

Example::

    [camera]
    position = [0, 0, 5]
    look_at = [0, 0, 0]
    up = [0, 1, 0]
    fov = 40                       # vertical, degrees

    [[light]]
    type = "directional"           # point | directional | quad | ambient
    direction = [-1, -1, -1]
    irradiance = 3.0               # a number or [r, g, b]

    [material]                     # default for every object
    diffuse = 0.7
    specular = 0.2
    shininess = 40

    [materials.red]
    diffuse = [0.6, 0.05, 0.05]

    [[object]]                     # per input file given to `vastray partition`
    file = "wall.obj"
    material = "red"

Without a file (or without ``[[light]]``) the scene gets one directional light plus ambient.

Animation (``vastray render --frames N``): the camera and the lights may move per frame::

    [[camera.key]]                 # keyframes: any of position, look_at, up, fov
    frame = 0
    position = [0, 0, 5]
    [[camera.key]]
    frame = 24
    position = [5, 0, 0]           # linear in between; held before the first key and
                                   # after the last; a key's value replaces [camera]'s

    [camera.orbit]                 # or: turn the frame-0 camera about an axis
    degrees_per_frame = 5          # default 1
    axis = [0, 1, 0]               # default [0, 1, 0]
    center = [0, 0, 0]             # default: the camera's look_at

    [[light]]
    type = "point"
    position = [2, 3, 1]
    intensity = 12
    move = [0.1, 0, 0]             # per frame (point and quad lights), or [[light.key]]
                                   # entries with frame = INT and any of the light's vectors

A config's ``camera`` and ``lights`` are those of frame 0; ``SceneConfig.at_frame`` gives any
frame's as a static config.
"""

from __future__ import annotations

import bisect
import dataclasses
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vastray.render.camera import Camera
from vastray.render.lights import AmbientLight, DirectionalLight, Light, PointLight, QuadLight
from vastray.render.materials import Material, MaterialTable
from vastray.scene.errors import InputError

_LIGHT_KEYS = {
    "point": {"position": "vec", "intensity": "rgb"},
    "directional": {"direction": "vec", "irradiance": "rgb"},
    "quad": {"corner": "vec", "edge1": "vec", "edge2": "vec", "radiance": "rgb"},
    "ambient": {"radiance": "rgb"},
}
_MATERIAL_KEYS = {"diffuse", "specular", "shininess"}
_CAMERA_KEYS = {"position", "look_at", "up", "fov"}
_ORBIT_KEYS = {"degrees_per_frame", "axis", "center"}


@dataclass(frozen=True)
class Track:
    """Keyframed values of one attribute, linearly interpolated between keys and held
    constant before the first key and after the last.

    Attributes
    ----------
    frames : increasing frame numbers of the keys.
    values : one value per key: (3,) float64 vectors or floats.
    """

    frames: tuple[int, ...]
    values: tuple

    def at(self, frame: int):
        """The value at ``frame`` (exactly a key's value on its frame)."""
        i = bisect.bisect_right(self.frames, frame) - 1
        if i < 0:
            return self.values[0]
        if i == len(self.frames) - 1 or self.frames[i] == frame:
            return self.values[i]
        t = (frame - self.frames[i]) / (self.frames[i + 1] - self.frames[i])
        return (1.0 - t) * self.values[i] + t * self.values[i + 1]


@dataclass(frozen=True)
class Orbit:
    """``[camera.orbit]``: frame f turns the frame-0 camera's position and up vector by
    ``f * degrees_per_frame`` about ``axis`` through ``center`` (default: the camera's
    look_at), right-handed; the camera keeps looking at its look_at."""

    degrees_per_frame: float = 1.0
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    center: np.ndarray | None = None


@dataclass(frozen=True)
class LightMotion:
    """How one ``[[light]]`` moves: its frame-0 values with keyframe tracks over them, or a
    translation ``move`` (3,) per frame of its position or corner."""

    kind: str
    values: dict
    tracks: dict[str, Track] = field(default_factory=dict)
    move: np.ndarray | None = None


@dataclass
class SceneConfig:
    """Parsed SCENE.toml (all fields optional; defaults are resolved against the store).

    ``camera`` and ``lights`` are frame 0's; ``camera_keys``, ``orbit`` and ``light_motion``
    say how they change over an animation (see ``at_frame``).
    """

    camera: dict = field(default_factory=dict)
    lights: list[Light] | None = None
    default_material: Material = field(default_factory=Material.default)
    named_materials: dict[str, Material] = field(default_factory=dict)
    object_materials: dict[str, Material] = field(default_factory=dict)
    source: str | None = None  # the SCENE.toml this came from, named in errors
    text: str | None = None  # its TOML text (what a coordinator sends its nodes)
    camera_keys: dict[str, Track] = field(default_factory=dict)  # attribute -> its keys
    orbit: Orbit | None = None
    light_motion: list[LightMotion | None] | None = None  # one per light (None: fixed)
    frame: int = 0  # the frame ``at_frame`` resolved this config for (nodes re-resolve at it)

    @property
    def animated(self) -> bool:
        """Whether the camera or any light moves from frame to frame."""
        return bool(self.camera_keys) or self.orbit is not None or any(
            motion is not None for motion in self.light_motion or [])

    def at_frame(self, frame: int, lo: np.ndarray, hi: np.ndarray, width: int,
                 height: int) -> SceneConfig:
        """The static config of one frame: camera and lights resolved for ``frame``.

        Parameters
        ----------
        frame : the frame number (>= 0).
        lo, hi : (3,) the store's bounds, which the default camera frames (an orbit of a
            camera without position or look_at turns that default camera).
        width, height : the image size (the default camera's aspect).

        Returns
        -------
        SceneConfig
            Not animated, with the same materials, ``source`` and ``text``, and ``frame``
            set. For a config that is not animated, the same camera and lights.

        Raises
        ------
        InputError
            When a light's interpolated values are degenerate at that frame.
        """
        if not self.animated:
            return dataclasses.replace(self, frame=frame)
        camera = dict(self.camera)
        for key, track in self.camera_keys.items():
            camera[key] = track.at(frame)
        if self.orbit is not None:
            camera = self._orbit_camera(frame, lo, hi, width, height)
        lights = self.lights
        if self.light_motion is not None:
            lights = [light if motion is None else _moved_light(self.source, i, motion, frame)
                      for i, (light, motion) in enumerate(zip(self.lights, self.light_motion,
                                                              strict=True))]
        return dataclasses.replace(self, camera=camera, lights=lights, camera_keys={},
                                   orbit=None, light_motion=None, frame=frame)

    def _orbit_camera(self, frame: int, lo, hi, width: int, height: int) -> dict:
        base = Camera.framing(np.asarray(lo, np.float64), np.asarray(hi, np.float64), width,
                              height, fov=float(self.camera.get("fov", 35.0)))
        position = np.asarray(self.camera.get("position", base.position), np.float64)
        look_at = np.asarray(self.camera.get("look_at", base.look_at), np.float64)
        up = np.asarray(self.camera.get("up", base.up), np.float64)
        center = look_at if self.orbit.center is None else self.orbit.center
        angle = np.radians(frame * self.orbit.degrees_per_frame)
        camera = dict(self.camera, position=center + _rotate(position - center,
                                                             self.orbit.axis, angle),
                      look_at=look_at, up=_rotate(up, self.orbit.axis, angle))
        return camera

    def resolve_camera(self, lo: np.ndarray, hi: np.ndarray, width: int, height: int) -> Camera:
        """The configured camera, with defaults that frame the box ``[lo, hi]``.

        Raises
        ------
        InputError
            When the camera sits on its target or looks along its up vector.
        """
        base = Camera.framing(lo, hi, width, height, fov=float(self.camera.get("fov", 35.0)))
        camera = Camera(
            position=np.asarray(self.camera.get("position", base.position), np.float64),
            look_at=np.asarray(self.camera.get("look_at", base.look_at), np.float64),
            up=np.asarray(self.camera.get("up", base.up), np.float64),
            fov=base.fov, width=width, height=height,
        )
        where = self.source or "camera"
        if np.array_equal(camera.position, camera.look_at):
            raise InputError(where, f"[camera] position {camera.position.tolist()} equals "
                                    "look_at: the camera has no view direction")
        forward = camera.look_at - camera.position
        if np.linalg.norm(np.cross(forward / np.linalg.norm(forward), camera.up)) < 1e-9:
            raise InputError(where, f"[camera] up {camera.up.tolist()} is parallel to the view "
                                    "direction; pick an up vector across it")
        return camera

    def check_objects(self, objects: list[dict]) -> None:
        """Refuse ``[[object]]`` entries that name no object of the store.

        Raises
        ------
        InputError
            Naming the unmatched file names and the store's objects.
        """
        names = {o.get("name", "") for o in objects}
        unmatched = sorted(set(self.object_materials) - names)
        if unmatched:
            raise InputError(self.source, f"[[object]] file(s) {unmatched} match no object "
                                          f"of the store; its objects are {sorted(names)}")

    def resolve_lights(self) -> list[Light]:
        """Configured lights, or the default key light plus ambient."""
        if self.lights is not None:
            return self.lights
        return [
            DirectionalLight(np.array([-0.4, -1.0, -0.6]), np.full(3, 2.4)),
            AmbientLight(np.full(3, 0.25)),
        ]

    def material_table(self, objects: list[dict]) -> MaterialTable:
        """One material per store object, by the object's file name (or the default)."""
        mats = [self.object_materials.get(o.get("name", ""), self.default_material)
                for o in objects] or [self.default_material]
        return MaterialTable(mats)


def load_scene_config(path: str | os.PathLike | None) -> SceneConfig:
    """Read SCENE.toml; ``None`` gives the defaults.

    Raises
    ------
    InputError
        Naming the file and the offending key.
    """
    if path is None:
        return SceneConfig(text="")
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "scene file not found")
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not valid TOML ({exc})") from None
    return parse_scene_config(text, path)


def parse_scene_config(text: str, path: str | os.PathLike) -> SceneConfig:
    """Parse SCENE.toml text; ``path`` names it in errors.

    Raises
    ------
    InputError
        Naming the file and the offending key.
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML ({exc})") from None
    unknown = set(doc) - {"camera", "light", "material", "materials", "object"}
    if unknown:
        raise InputError(path, f"unknown section(s) {sorted(unknown)}")
    cfg = SceneConfig(source=str(path), text=text)
    cam = doc.get("camera", {})
    _check_keys(path, "[camera]", cam, _CAMERA_KEYS | {"key", "orbit"})
    cfg.camera = {k: _camera_value(path, f"camera.{k}", k, v) for k, v in cam.items()
                  if k in _CAMERA_KEYS}
    if "key" in cam:
        cfg.camera_keys = _tracks(path, "[[camera.key]]", cam["key"],
                                  {k: "camera" for k in _CAMERA_KEYS})
        cfg.camera.update({k: track.at(0) for k, track in cfg.camera_keys.items()})
    if "orbit" in cam:
        if "key" in cam:
            raise InputError(path, "[camera] holds both [[camera.key]] and [camera.orbit]; "
                                   "give one of them")
        cfg.orbit = _orbit(path, cam["orbit"])
    if "light" in doc:
        if not isinstance(doc["light"], list):
            raise InputError(path, "[[light]] must be an array of tables")
        parsed = [_light(path, i, spec) for i, spec in enumerate(doc["light"])]
        cfg.lights = [light for light, _ in parsed]
        if any(motion is not None for _, motion in parsed):
            cfg.light_motion = [motion for _, motion in parsed]
    if "material" in doc:
        cfg.default_material = _material(path, "[material]", doc["material"], Material.default())
    for name, spec in doc.get("materials", {}).items():
        cfg.named_materials[name] = _material(path, f"[materials.{name}]", spec,
                                              cfg.default_material)
    for i, obj in enumerate(doc.get("object", [])):
        where = f"[[object]] #{i + 1}"
        _check_keys(path, where, obj, {"file", "material"})
        if "file" not in obj:
            raise InputError(path, f"{where} needs `file`")
        mat = obj.get("material")
        if isinstance(mat, str):
            if mat not in cfg.named_materials:
                raise InputError(path, f"{where} names unknown material {mat!r}")
            material = cfg.named_materials[mat]
        else:
            material = _material(path, where, mat or {}, cfg.default_material)
        cfg.object_materials[Path(obj["file"]).name] = material
    return cfg


def _camera_value(path, key, name, value):
    if name != "fov":
        return _vec(path, key, value)
    fov = _number(path, key, value)
    if not 0 < fov < 180:
        raise InputError(path, f"{key} must lie between 0 and 180 degrees, got {fov}")
    return fov


def _tracks(path, where, keys, kinds: dict[str, str]) -> dict[str, Track]:
    """Parse ``[[... .key]]`` entries into one track per attribute they set.

    ``kinds`` maps each attribute a key may set to how its value is read: ``"camera"``
    (vectors and the fov) or ``"vec"``.
    """
    if not isinstance(keys, list) or not keys:
        raise InputError(path, f"{where} must be one or more tables")
    per_key: dict[str, tuple[list, list]] = {}
    last = None
    for i, key in enumerate(keys):
        at = f"{where} #{i + 1}"
        _check_keys(path, at, key, set(kinds) | {"frame"})
        frame = key.get("frame")
        if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
            raise InputError(path, f"{at} needs `frame = N`, a whole number >= 0, got "
                                   f"{frame!r}")
        if last is not None and frame <= last:
            raise InputError(path, f"{at}: frames must increase from key to key; frame "
                                   f"{frame} follows frame {last}")
        last = frame
        if len(key) == 1:
            raise InputError(path, f"{at} sets nothing besides its frame; give any of "
                                   f"{sorted(kinds)}")
        for name, value in key.items():
            if name == "frame":
                continue
            read = (_camera_value(path, f"{at}.{name}", name, value) if kinds[name] == "camera"
                    else _vec(path, f"{at}.{name}", value))
            frames, values = per_key.setdefault(name, ([], []))
            frames.append(frame)
            values.append(read)
    return {name: Track(tuple(frames), tuple(values))
            for name, (frames, values) in per_key.items()}


def _orbit(path, spec) -> Orbit:
    where = "[camera.orbit]"
    _check_keys(path, where, spec, _ORBIT_KEYS)
    degrees = _number(path, f"{where}.degrees_per_frame", spec.get("degrees_per_frame", 1.0))
    if abs(degrees) > 360:  # a turn or more a frame; and frame * 1e308 overflows to NaN cameras
        raise InputError(path, f"{where}.degrees_per_frame must be within -360..360 (a whole "
                               f"turn a frame at most), got {degrees:g}")
    axis = _vec(path, f"{where}.axis", spec.get("axis", [0.0, 1.0, 0.0]))
    if not np.any(axis):
        raise InputError(path, f"{where}.axis must not be zero")
    center = _vec(path, f"{where}.center", spec["center"]) if "center" in spec else None
    return Orbit(degrees, axis / np.linalg.norm(axis), center)


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``v`` (3,) turned by ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    cos, sin = np.cos(angle), np.sin(angle)
    return v * cos + np.cross(axis, v) * sin + axis * float(axis @ v) * (1.0 - cos)


def _check_keys(path, where, table, allowed):
    if not isinstance(table, dict):
        raise InputError(path, f"{where} must be a table")
    extra = set(table) - set(allowed)
    if extra:
        raise InputError(path, f"{where}: unknown key(s) {sorted(extra)}; allowed {sorted(allowed)}")


def _number(path, key, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise InputError(path, f"{key} must be a finite number, got {value!r}")
    return float(value)


def _vec(path, key, value) -> np.ndarray:
    arr = np.asarray(value, dtype=object)
    if arr.shape != (3,):
        raise InputError(path, f"{key} must be a list of 3 numbers, got {value!r}")
    return np.array([_number(path, key, v) for v in value], dtype=np.float64)


def _rgb(path, key, value) -> np.ndarray:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    rgb = _vec(path, key, value)
    if np.any(rgb < 0):
        raise InputError(path, f"{key} must not be negative")
    return rgb


def _light(path, index, spec) -> tuple[Light, LightMotion | None]:
    """One ``[[light]]``: the light at frame 0, and how it moves (None: it does not)."""
    where = f"[[light]] #{index + 1}"
    kind = spec.get("type") if isinstance(spec, dict) else None
    if kind not in _LIGHT_KEYS:
        raise InputError(path, f"{where}: type must be one of {sorted(_LIGHT_KEYS)}, got {kind!r}")
    keys = _LIGHT_KEYS[kind]
    vectors = {k: "vec" for k, t in keys.items() if t == "vec"}
    _check_keys(path, where, spec, set(keys) | {"type", "key", "move"})
    tracks = {}
    if "key" in spec:
        if not vectors:
            raise InputError(path, f"{where}: an {kind} light has nothing to keyframe")
        tracks = _tracks(path, f"{where} [[light.key]]", spec["key"], vectors)
    missing = set(keys) - set(spec) - set(tracks)
    if missing:
        raise InputError(path, f"{where} ({kind}) needs {sorted(missing)}")
    values = {k: (_vec if t == "vec" else _rgb)(path, f"{where}.{k}", spec[k])
              for k, t in keys.items() if k in spec}
    values.update({k: track.at(0) for k, track in tracks.items()})
    move = None
    if "move" in spec:
        if kind not in ("point", "quad"):
            raise InputError(path, f"{where}: move translates a point light's position or a "
                                   f"quad light's corner; a {kind} light has neither")
        if tracks:
            raise InputError(path, f"{where} holds both move and [[light.key]]; give one")
        move = _vec(path, f"{where}.move", spec["move"])
    motion = LightMotion(kind, values, tracks, move) if tracks or move is not None else None
    return _make_light(path, where, kind, values), motion


def _moved_light(path, index, motion: LightMotion, frame: int) -> Light:
    """Light ``index`` (0-based) at ``frame``."""
    values = dict(motion.values)
    values.update({k: track.at(frame) for k, track in motion.tracks.items()})
    if motion.move is not None:
        key = "position" if motion.kind == "point" else "corner"
        values[key] = values[key] + frame * motion.move
    return _make_light(path, f"[[light]] #{index + 1} at frame {frame}", motion.kind, values)


def _make_light(path, where, kind, values) -> Light:
    if kind == "point":
        return PointLight(values["position"], values["intensity"])
    if kind == "directional":
        if not np.any(values["direction"]):
            raise InputError(path, f"{where}.direction must not be zero")
        return DirectionalLight(values["direction"], values["irradiance"])
    if kind == "quad":
        light = QuadLight(values["corner"], values["edge1"], values["edge2"], values["radiance"])
        if np.linalg.norm(light.area_normal) == 0:
            raise InputError(path, f"{where}: edge1 and edge2 span no area")
        return light
    return AmbientLight(values["radiance"])


def _material(path, where, spec, base: Material) -> Material:
    _check_keys(path, where, spec, _MATERIAL_KEYS)
    diffuse = _rgb(path, f"{where}.diffuse", spec["diffuse"]) if "diffuse" in spec else base.diffuse
    specular = (_rgb(path, f"{where}.specular", spec["specular"]) if "specular" in spec
                else base.specular)
    shininess = (_number(path, f"{where}.shininess", spec["shininess"]) if "shininess" in spec
                 else base.shininess)
    if np.any(diffuse + specular > 1.0 + 1e-6):
        raise InputError(path, f"{where}: diffuse + specular exceeds 1 (the surface would "
                               "reflect more light than it receives)")
    return Material(diffuse, specular, shininess)
