"""Numerical stability far from the origin and at extreme distances (issue 20, part 2).

Renders one small scene (a bumpy sphere on a ground slab with boxes, a point light and a sky;
path tracing with one bounce, 2x2x2 domains, 64x48) as it is, translated by 1e3 ... 1e7 with
its camera and light, and seen from cameras 6e4 and 6e5 away (field of view narrowed to keep
the framing), and prints each image's change of mean and relative MSE against its reference,
beside the seed-to-seed noise (the reference scene rendered with another seed). ``--scales``
renders it scaled (camera and light with it) instead, against the unit-scale image: where
float32 ray tracing stops resolving a scene (``vastray.scene.extent``)::

    python bench/numerics.py                  # 8 spp
    python bench/numerics.py --shifts 1e5 1e6 --spp 16
    python bench/numerics.py --scales         # 1e-12 ... 1e18

References: the scene at the origin for the translations; for the far cameras, a camera 2e3
away whose rays start at the camera (the projection of a 2.6-unit scene changes by about 1e-3
between the two: well under a pixel). ``tests/test_numerics.py`` asserts the same figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from vastray.render import driver  # noqa: E402

from scenes import compare, far_config, far_settings, far_store  # noqa: E402


def image(store, config, settings):
    return driver.render(store, config, settings, threads=1, progress=False).film.image()


def unclipped(store, config, settings):
    """``image`` with every camera ray starting at the camera."""
    with mock.patch.object(driver, "with_camera_clip", lambda shading, *_: shading):
        return image(store, config, settings)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shifts", type=float, nargs="*", default=[1e3, 1e4, 1e5, 1e6, 1e7])
    parser.add_argument("--distances", type=float, nargs="*", default=[6e4, 6e5])
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--scales", type=float, nargs="*", default=None,
                        help="render the scene scaled by these instead (none given: 1e-12 ... "
                             "1e18)")
    args = parser.parse_args()
    s = far_settings(args.spp)
    with tempfile.TemporaryDirectory() as tmp:
        base = far_store(Path(tmp) / "base.store", 0.0)
        reference = image(base, far_config(), s)
        noise = compare(image(base, far_config(), dataclasses.replace(s, seed=2)), reference)
        print(f"noise (seed 2 vs 1): mean {noise['mean']:+.4%}  rel_mse_global {noise['rel_mse_global']:.4g}")
        if args.scales is not None:
            for scale in args.scales or [10.0 ** e for e in (*range(-12, -5), *range(6, 15), 18)]:
                store = far_store(Path(tmp) / f"x{scale:g}.store", 0.0, scale=scale)
                extent = float(np.max(store.bounds[1] - store.bounds[0]))
                c = compare(image(store, far_config(scale=scale), s), reference)
                print(f"scaled {scale:.0e} (extent {extent:.2g}): mean {c['mean']:+.4%}  "
                      f"rel_mse_global {c['rel_mse_global']:.4g}  nonfinite {c['nonfinite']}")
            return
        for shift in args.shifts:
            start = time.perf_counter()
            store = far_store(Path(tmp) / f"s{shift:g}.store", shift)
            c = compare(image(store, far_config(shift), s), reference)
            print(f"translated {shift:.0e}: mean {c['mean']:+.4%}  rel_mse_global {c['rel_mse_global']:.4g}  "
                  f"nonfinite {c['nonfinite']}  ({time.perf_counter() - start:.1f} s)")
        near = unclipped(base, far_config(distance=2e3), s)
        for distance in args.distances:
            c = compare(image(base, far_config(distance=distance), s), near)
            print(f"camera {distance:.0e} away (vs 2e3): mean {c['mean']:+.4%}  "
                  f"rel_mse_global {c['rel_mse_global']:.4g}")


if __name__ == "__main__":
    main()
