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
"""

from __future__ import annotations

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


@dataclass
class SceneConfig:
    """Parsed SCENE.toml (all fields optional; defaults are resolved against the store)."""

    camera: dict = field(default_factory=dict)
    lights: list[Light] | None = None
    default_material: Material = field(default_factory=Material.default)
    named_materials: dict[str, Material] = field(default_factory=dict)
    object_materials: dict[str, Material] = field(default_factory=dict)
    source: str | None = None  # the SCENE.toml this came from, named in errors
    text: str | None = None  # its TOML text (what a coordinator sends its nodes)

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
    """Parse SCENE.toml text; ``path`` names it in errors."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML ({exc})") from None
    unknown = set(doc) - {"camera", "light", "material", "materials", "object"}
    if unknown:
        raise InputError(path, f"unknown section(s) {sorted(unknown)}")
    cfg = SceneConfig(source=str(path), text=text)
    cam = doc.get("camera", {})
    _check_keys(path, "[camera]", cam, _CAMERA_KEYS)
    cfg.camera = {k: (_vec(path, f"camera.{k}", v) if k != "fov" else _number(path, "camera.fov", v))
                  for k, v in cam.items()}
    if not 0 < cfg.camera.get("fov", 35.0) < 180:
        raise InputError(path, f"camera.fov must lie between 0 and 180 degrees, got "
                               f"{cfg.camera['fov']}")
    if "light" in doc:
        cfg.lights = [_light(path, i, spec) for i, spec in enumerate(doc["light"])]
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


def _light(path, index, spec) -> Light:
    where = f"[[light]] #{index + 1}"
    kind = spec.get("type") if isinstance(spec, dict) else None
    if kind not in _LIGHT_KEYS:
        raise InputError(path, f"{where}: type must be one of {sorted(_LIGHT_KEYS)}, got {kind!r}")
    keys = _LIGHT_KEYS[kind]
    _check_keys(path, where, spec, set(keys) | {"type"})
    missing = set(keys) - set(spec)
    if missing:
        raise InputError(path, f"{where} ({kind}) needs {sorted(missing)}")
    values = {k: (_vec if t == "vec" else _rgb)(path, f"{where}.{k}", spec[k])
              for k, t in keys.items()}
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
