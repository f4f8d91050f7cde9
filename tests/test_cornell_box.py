"""Agreement with an independent renderer: the Cornell box against Mitsuba 3 references."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from vastray.cli import main
from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.progressive import Progression, StopRules
from vastray.render.scene_config import load_scene_config
from vastray.scene.store import Store

pytestmark = pytest.mark.shared_data


def _vec(v):
    return "[" + ", ".join(repr(float(x)) for x in v) + "]"


def cornell_scene_toml(root, path):
    """Transcribe ``scene.json`` into a SCENE.toml: camera, materials per part, the area light.

    The luminaire becomes a one-sided quad light (sampled by area, seen by camera rays); the
    ceiling 0.5 mm above it takes its place as a reflector.
    """
    spec = json.loads((root / "scene.json").read_text())
    cam = spec["camera"]
    lines = ["[camera]", f"position = {_vec(cam['origin'])}", f"look_at = {_vec(cam['target'])}",
             f"up = {_vec(cam['up'])}", f"fov = {cam['fov_degrees']}", ""]
    for name, mat in spec["materials"].items():
        lines += [f"[materials.{name}]", f"diffuse = {_vec(mat['reflectance_rgb'])}", ""]
    parts = []
    for shape in spec["shapes"]:
        if "emitter" in shape:
            mesh = trimesh.load(root / shape["file"], force="mesh", process=False)
            v = np.asarray(mesh.vertices) + np.asarray(shape.get("translate", [0, 0, 0]))
            corner, e1, e2 = v[0], v[1] - v[0], v[3] - v[0]
            if np.cross(e1, e2) @ np.array([0.0, -1.0, 0.0]) < 0:  # emit downward
                e1, e2 = e2, e1
            lines += ["[[light]]", 'type = "quad"', f"corner = {_vec(corner)}",
                      f"edge1 = {_vec(e1)}", f"edge2 = {_vec(e2)}",
                      f"radiance = {_vec(shape['emitter']['radiance_rgb'])}", ""]
            continue
        parts.append(root / shape["file"])
        lines += ["[[object]]", f'file = "{(root / shape["file"]).name}"',
                  f'material = "{shape["material"]}"', ""]
    path.write_text("\n".join(lines))
    return parts


@pytest.fixture(scope="module")
def cornell(shared_data, tmp_path_factory):
    root = shared_data / "cornell_box"
    tmp = tmp_path_factory.mktemp("cbox")
    parts = cornell_scene_toml(root, tmp / "scene.toml")
    assert main(["partition", *map(str, parts), "-o", str(tmp / "store"), "--grid", "2x2x2",
                 "--quiet"]) == 0
    return root, Store(tmp / "store"), load_scene_config(tmp / "scene.toml")


class SampleSquares(Progression):
    """Passes of one sample each, whose squares it sums: each pixel's sample variance."""

    def add_pass(self, index, pass_film, **kw):
        sample = pass_film.sum / np.maximum(pass_film.count, 1)[:, None]
        self.squares = getattr(self, "squares", 0.0) + sample ** 2
        return super().add_pass(index, pass_film, **kw)

    def variance_of_mean(self):
        """(H, W, 3) each pixel's sample variance / n."""
        n = self.film.count[:, None].astype(np.float64)
        mean = self.film.sum / n
        var = (self.squares / n - mean ** 2) * n / (n - 1) / n
        return var.reshape(self.height, self.width, 3)


@pytest.mark.parametrize("depth,spp", [(2, 64), (6, 64)])
def test_cornell_box_agrees_with_mitsuba(cornell, depth, spp):
    root, store, config = cornell
    ref_spp = {2: 4096, 6: 8192}[depth]
    reference = np.load(root / "reference" / f"cbox_rgb_depth{depth}_{ref_spp}spp.npy")
    # Render at half resolution; a 2x2 box average of the reference is the same estimator.
    reference = reference.reshape(128, 2, 128, 2, 3).mean(axis=(1, 3))
    # Mitsuba's max_depth counts the segment that reaches the light: bounces = depth - 2.
    settings = RenderSettings(width=128, height=128, spp=spp, integrator="pt",
                              bounces=depth - 2, shadow_samples=1, seed=1)
    progression = SampleSquares(128, 128, StopRules(spp, max_pass_spp=1))
    result = render(store, config, settings, progress=False, progression=progression)
    image = result.film.image().astype(np.float64)

    # Per-channel means within 1 %.
    ratio = image.mean(axis=(0, 1)) / reference.mean(axis=(0, 1))
    assert np.all(np.abs(ratio - 1) < 0.01), ratio

    # Monte Carlo consistency: 16x16-pixel block means differ by no more than their noise,
    # the sample variance of each pixel (63 degrees of freedom: the film's own two-halves
    # estimate has one per pixel, too few where a few bright samples dominate a block).
    var = progression.variance_of_mean()
    ref_var = var * spp / (4 * ref_spp)  # the reference used 4 * ref_spp samples per pixel here

    def blocks(a):
        return a.reshape(8, 16, 8, 16, 3).sum(axis=(1, 3))

    z = (blocks(image) - blocks(reference)) / np.sqrt(blocks(var) + blocks(ref_var) + 1e-30)
    # 192 block-channel tests; a Bonferroni bound at 1e-3 overall is |z| < 4.5.
    assert np.max(np.abs(z)) < 4.5, np.round(z, 1)
    assert abs(z.mean()) < 0.5
