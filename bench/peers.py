"""vastray against a peer renderer, Mitsuba 3, on the same scene (issue 9).

Both render one ~1 M-triangle isosurface (the ``rm`` scene, one domain, its scalars dropped so
the surface is plain diffuse) at the same resolution, samples per pixel, path depth, camera,
light and material, on the same number of threads:

* camera: pinhole, 35 degree vertical field of view, box pixel filter (uniform jitter);
* light: one point light (intensity in W/sr on both sides);
* material: two-sided Lambertian, albedo 0.7 (vastray's default material; Mitsuba
  ``twosided(diffuse)``), flat shading (geometric normals; Mitsuba ``face_normals``);
* depth: vastray ``--bounces 2`` = Mitsuba ``path`` ``max_depth=4``. In vastray
  (``render/integrators.py``) the camera ray finds path vertex 0 and a vertex of depth d
  spawns a continuation only while ``d < bounces``: vertices 0, 1, 2 each send a shadow ray
  to the light. Mitsuba samples the emitter at the vertex of depth d (0-based) while
  ``d + 1 < max_depth``: vertices 0, 1, 2 for ``max_depth=4``. Russian roulette is off
  (``rr_depth`` beyond the depth) and the point light is a delta light, so both estimate the
  same integral with the same strategy; their images differ only by noise.

Timing: each renderer renders once untimed (vastray loads its numba kernels, Mitsuba's LLVM
backend compiles its kernel), then ``--repeat`` times, interleaved with the other, with other
seeds; the best time of each side makes the ratio (on a shared machine noise only slows).
Scene loading (vastray: the domain's read and BVH build, which the renderer reports; Mitsuba:
``load_dict``, i.e. the PLY read and its BVH build) is excluded from the render times on both
sides and printed apart.
Mitsuba's ``llvm_ad_rgb`` variant (vectorised LLVM JIT, the one to beat) needs a system
libLLVM; where it cannot load the script says so and compares with ``scalar_rgb`` only.

Prints ``mitsuba_ratio=`` (vastray render s / Mitsuba ``llvm_ad_rgb`` render s; issue 9:
floor 2.5, goal 1.5), ``mitsuba_scalar_ratio=`` (the same against ``scalar_rgb``) and
``mean_rel_diff_*=`` (relative difference of the images' means: they must agree within 2 %).

Under contention (issue 39), ``--hog N`` also runs both sides beside N busy processes (pure
CPU spinners the script starts, and kills when it ends, Ctrl-C included; each also stops
when its parent is gone): after the quiet runs, ``--repeat`` more interleaved runs of
vastray and Mitsuba ``llvm_ad_rgb`` under the hog, and ``mitsuba_ratio_hog=`` (median
vastray render s / median Mitsuba render s; noise is large under a hog, so medians, not
bests). ``mitsuba_ratio_median=`` is the quiet ratio of medians, for comparison. Issue 39
asks for medians of >= 5 interleaved runs: ``--repeat 5``.

The same work (issue 39): Mitsuba 3 builds its Embree scene with ``RTC_SCENE_FLAG_NONE`` and
``RTC_BUILD_QUALITY_HIGH`` and traces 16-wide packets (``src/render/scene_embree.inl``); vastray's
default is Embree's watertight triangle test (``RTC_SCENE_FLAG_ROBUST``: rays through shared
edges never slip through), which costs more per ray. So ``mitsuba_ratio=`` compares vastray as
users run it with a peer doing less work per query; ``--repeat`` more interleaved runs with
``VASTRAY_TRIANGLE_TEST=fast`` (Mitsuba's triangle test) print ``mitsuba_ratio_same_test=``,
and ``embree_camera_rays_s=`` times the query alone: Mitsuba's own camera rays (its sensor,
this resolution and spp) traced by Mitsuba and by vastray's kernels (watertight and fast), the
same rays and threads on both sides, hits counted to show they agree; ``mitsuba_coherent``
is Mitsuba tracing them as coherent packets (one frustum per packet, Embree's
``intersectCoherent``), as its path integrator traces camera rays in a render: vastray traces
every packet ray by ray, since a coherent packet's hits are not the single-ray hits bit for
bit (docs/DESIGN.md, render workers). ``embree_bounce_rays_s=``
and ``embree_shadow_rays_s=`` do the same with vastray's own bounce and shadow rays (recorded
from one render of the scene; Mitsuba traces them with ``ray_intersect_preliminary`` and
``ray_test``): together, where the two renderers' query time differs, kind by kind.

Install Mitsuba (optional extra): ``pip install -e ".[peers]"`` (or ``pip install mitsuba``);
for ``llvm_ad_rgb`` also a recent system libLLVM: Dr.Jit 1.5 refuses LLVM 14 and, with LLVM 15
(Debian 12's ``llvm`` package), aborted on its first kernel ("Cannot select ... fminimum");
LLVM 19 works: ``apt-get install -y libllvm19`` (Debian 12), or point ``DRJIT_LIBLLVM_PATH``
at a ``libLLVM-*.so``.

    python bench/peers.py [--quick] [--spp 16] [--resolution 288] [--threads N] [--repeat 3]
                          [--hog N] [--scan FILE[:ISO]]

``--scan`` renders a real scan (issue 39: "and on real scans") instead of ``rm``, with the
same camera framing, light and material rules.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from bench_scenes import CACHE, SHARED_DATA, cached_rm
from hogs import busy_processes

from vastray.render.camera import Camera
from vastray.render.driver import render
from vastray.render.integrators import RenderSettings
from vastray.render.lights import PointLight
from vastray.render.scene_config import SceneConfig
from vastray.scene.embree.scenes import TRIANGLE_TEST_ENV, Scene
from vastray.scene.store import DomainArrays, Store, StoreWriter

WIDTH = HEIGHT = 256
FOV = 35.0
BOUNCES = 2  # vastray --bounces
MAX_DEPTH = BOUNCES + 2  # Mitsuba: see the module docstring
ALBEDO = 0.7


def plain_store(resolution: int) -> Store:
    """The ``rm`` scene at ``resolution``^3 as one domain without scalars (plain diffuse)."""
    path = CACHE / f"peers-rm-{resolution}.store"
    if not (path / "manifest.json").is_file():
        write_plain(cached_rm(resolution, (1, 1, 1)), path, "rm")
    return Store(path)


def write_plain(source: Store, path: Path, name: str) -> None:
    """``source``'s one domain as a store at ``path`` of its triangles alone (no scalars, one
    object ``name``): the plain diffuse surface both renderers shade."""
    dom = source.load_domain(0, mmap=False)
    with StoreWriter(path, objects=[{"name": name}], overwrite=True) as writer:
        writer.add_domain(DomainArrays(np.asarray(dom.vertices), np.asarray(dom.indices)))


def scan_store(spec: str) -> tuple[Store, str]:
    """A real scan as one plain domain: ``spec`` is a mesh file, or a volume file and its
    iso value as ``FILE:ISO``, absolute or under ``../shared/data`` (e.g.
    ``volumes/embryo_256.nii.gz:60``, 976,059 triangles). Returns the store and its label."""
    name, _, iso = spec.rpartition(":")
    try:
        float(iso)
    except ValueError:  # no iso value: a mesh
        name, iso = spec, ""
    source = Path(name) if Path(name).is_file() else SHARED_DATA / name
    if not source.is_file():
        raise SystemExit(f"--scan: no file {name!r} (nor {SHARED_DATA / name}); give a mesh, "
                         f"or a volume and its iso value as FILE:ISO")
    path = CACHE / f"peers-{source.name}-{iso or 'mesh'}.store"
    if not (path / "manifest.json").is_file():
        from vastray.cli import main as cli

        whole = CACHE / f"peers-{source.name}-{iso or 'mesh'}-source.store"
        args = ["partition", str(source), "-o", str(whole), "--grid", "1x1x1", "--force",
                "--quiet"] + (["--iso", iso] if iso else [])
        if cli(args) != 0:
            raise SystemExit(f"--scan: could not partition {source}")
        write_plain(Store(whole), path, source.stem)
    label = f"{source.name}" + (f" at iso {iso}" if iso else "")
    return Store(path), label


def write_ply(path: Path, vertices: np.ndarray, indices: np.ndarray) -> None:
    """A binary little-endian PLY of the mesh (what Mitsuba loads)."""
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(indices)}\nproperty list uchar uint vertex_indices\n"
              "end_header\n").encode()
    faces = np.empty(len(indices), dtype=[("n", "u1"), ("i", "<u4", 3)])
    faces["n"] = 3
    faces["i"] = indices
    with open(path, "wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(vertices, "<f4").tobytes())
        f.write(faces.tobytes())


def setup(store: Store):
    """Camera and point light shared by both renderers."""
    lo, hi = store.bounds
    camera = Camera.framing(lo, hi, WIDTH, HEIGHT, fov=FOV)
    center, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    light_pos = center + np.array([0.6, 1.6, 0.9]) * radius
    intensity = 1.5 * radius ** 2  # about 1 W/m^2 irradiance at the scene's centre
    return camera, light_pos, intensity


def run_vastray(store: Store, camera: Camera, light_pos, intensity, spp: int, threads: int,
                seed: int):
    config = SceneConfig(camera={"position": camera.position, "look_at": camera.look_at,
                                 "up": camera.up, "fov": FOV},
                         lights=[PointLight(np.asarray(light_pos, float), np.full(3, intensity))])
    settings = RenderSettings(width=WIDTH, height=HEIGHT, spp=spp, integrator="pt",
                              bounces=BOUNCES, seed=seed)
    result = render(store, config, settings, threads=threads, progress=False)
    return result.film.image(), result.seconds["load"], result.seconds["trace_and_shade"], result


def mitsuba_scene(mi, ply: Path, camera: Camera, light_pos, intensity, spp: int) -> dict:
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MAX_DEPTH, "rr_depth": 1000},
        "sensor": {
            "type": "perspective", "fov": FOV, "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(origin=camera.position.tolist(),
                                                       target=camera.look_at.tolist(),
                                                       up=camera.up.tolist()),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        },
        "light": {"type": "point", "position": list(map(float, light_pos)),
                  "intensity": {"type": "rgb", "value": [intensity] * 3}},
        "mesh": {"type": "ply", "filename": str(ply), "face_normals": True,
                 "bsdf": {"type": "twosided",
                          "material": {"type": "diffuse",
                                       "reflectance": {"type": "rgb", "value": [ALBEDO] * 3}}}},
    }


class MitsubaRenderer:
    """One Mitsuba variant with the scene loaded (load timed) and its kernel warmed up."""

    def __init__(self, variant: str, ply: Path, camera, light_pos, intensity, spp: int,
                 threads: int):
        import drjit as dr
        import mitsuba as mi

        self.mi, self.variant = mi, variant
        mi.set_variant(variant)
        # Dr.Jit's thread pool: the LLVM backend's kernels and scalar block rendering
        dr.set_thread_count(threads)
        start = time.perf_counter()
        self.scene = mi.load_dict(mitsuba_scene(mi, ply, camera, light_pos, intensity, spp))
        self.load = time.perf_counter() - start
        start = time.perf_counter()
        self.render(seed=1)  # llvm: traces the Python code and compiles the kernel
        self.warm = time.perf_counter() - start

    def render(self, seed: int) -> np.ndarray:
        """The image, evaluated: (H, W, 3) float32 linear RGB, row 0 at the top."""
        return np.array(self.mi.render(self.scene, seed=seed)).astype(np.float32)


def try_llvm() -> str | None:
    """None when ``llvm_ad_rgb`` renders, else why not. Tried in a child process: with too old
    a libLLVM (15 here) the first kernel aborts the whole process (LLVM's "Cannot select")."""
    import mitsuba as mi

    if "llvm_ad_rgb" not in mi.variants():
        return "this Mitsuba build has no llvm_ad_rgb variant"
    probe = ("import mitsuba as mi, numpy as np; mi.set_variant('llvm_ad_rgb'); "
             "mi.set_log_level(mi.LogLevel.Error); "
             "np.array(mi.render(mi.load_dict(mi.cornell_box()), spp=1))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    if done.returncode == 0:
        return None
    lines = [ln for ln in (done.stderr or "").splitlines() if ln and not ln.startswith(" ")]
    return f"exit status {done.returncode}: {(lines or ['?'])[-1][:300]}"


def interleaved(store, camera, light_pos, intensity, spp, threads, peer, repeat, seed0):
    """``repeat`` timed renders of each side, alternating: vastray, Mitsuba, vastray, ...

    Returns (vastray image, vastray render s, vastray load s, Mitsuba image, Mitsuba s)."""
    v_times, m_times, v_loads = [], [], []
    for rep in range(repeat):
        v_img, v_load, v_s, _ = run_vastray(store, camera, light_pos, intensity, spp, threads,
                                            seed=seed0 + rep)
        v_times.append(v_s)
        v_loads.append(v_load)
        start = time.perf_counter()
        img = peer.render(seed=seed0 + rep)
        m_times.append(time.perf_counter() - start)
    return v_img, v_times, v_loads, img, m_times


@contextlib.contextmanager
def triangle_test(test: str):
    """vastray's scenes built with ``test`` (``VASTRAY_TRIANGLE_TEST``) inside the block."""
    before = os.environ.get(TRIANGLE_TEST_ENV)
    os.environ[TRIANGLE_TEST_ENV] = test
    try:
        yield
    finally:
        if before is None:
            del os.environ[TRIANGLE_TEST_ENV]
        else:
            os.environ[TRIANGLE_TEST_ENV] = before


def camera_rays_same(peer: MitsubaRenderer, store: Store, spp: int, threads: int,
                     repeat: int) -> dict[str, tuple[float, int]]:
    """Mitsuba's own camera rays (pixel-major, ``spp`` jittered samples a pixel) traced by
    Mitsuba (``ray_intersect_preliminary``, its packets traced ray by ray, and as coherent
    packets: what its path integrator asks for camera rays) and by vastray's closest-hit
    kernel on scenes with the watertight and the fast triangle test, ``threads`` threads each.

    Returns {side: (best seconds of ``repeat``, rays that hit)}."""
    import drjit as dr

    mi = peer.mi
    n = WIDTH * HEIGHT * spp
    pixel = dr.arange(mi.UInt32, n) // spp
    jitter = np.random.default_rng(7).random((2, n), dtype=np.float32)
    position = mi.Point2f((mi.Float(pixel % WIDTH) + mi.Float(jitter[0])) / WIDTH,
                          (mi.Float(pixel // WIDTH) + mi.Float(jitter[1])) / HEIGHT)
    ray, _ = peer.scene.sensors()[0].sample_ray(0.0, 0.5, position, mi.Point2f(0.5, 0.5))
    dr.eval(ray)
    out = {}
    for side, coherent in (("mitsuba", False), ("mitsuba_coherent", True)):
        out[side] = _mitsuba_times(
            dr, repeat, lambda c=coherent: peer.scene.ray_intersect_preliminary(ray, coherent=c),
            lambda pi: (pi.t, pi.prim_index), lambda pi: pi.is_valid())
    origins = np.ascontiguousarray(np.array(ray.o).T, np.float32)
    directions = np.ascontiguousarray(np.array(ray.d).T, np.float32)
    t_far = np.full(n, np.inf, np.float32)
    out.update(_vastray_times(store, repeat, lambda scene: _batched(
        lambda o, d, t: scene.intersect(o, d, t, 1)["primID"] >= 0,
        origins, directions, t_far, threads)))
    return out


def _mitsuba_times(dr, repeat: int, trace, evaluated, hit) -> tuple[float, int]:
    """(best seconds of ``repeat`` runs of Mitsuba's ``trace()``, evaluated as far as
    ``evaluated(result)``, and the rays ``hit(result)`` counts)."""
    times, hits = [], 0
    for _ in range(repeat):
        # a new variable each time: an old result alive would be reused, untraced
        result = None
        start = time.perf_counter()
        result = trace()
        dr.eval(evaluated(result))
        dr.sync_thread()
        times.append(time.perf_counter() - start)
        hits = int(dr.count(hit(result))[0])
    return min(times), hits


def _batched(query, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray,
             threads: int) -> np.ndarray:
    """``query(origins, directions, t_far)``'s (k,) bool answers (a query of one thread) over
    the rays in the renderer's batches (``RenderSettings.batch_size``) on ``threads`` workers,
    joined: as a render runs its queries (a worker a thread, each batch's query on its
    worker's thread, ``render.driver``). Until session 55 vastray's side was one call of a
    million rays split over the threads, which a render never makes: it faulted in 36 MB of
    fresh outputs each time and handed every piece to the split pool, charging vastray's
    camera query 1.2-1.4x what the renderer spends on the same rays."""
    size = RenderSettings.batch_size
    starts = range(0, len(origins), size)
    with ThreadPoolExecutor(threads) as pool:
        return np.concatenate(list(pool.map(
            lambda s: query(origins[s:s + size], directions[s:s + size], t_far[s:s + size]),
            starts)))


def _vastray_times(store: Store, repeat: int, query) -> dict[str, tuple[float, int]]:
    """{"vastray" | "vastray_fast": (best seconds of ``repeat`` runs of ``query(scene)``, the
    rays its (n,) bool answer counts)}, on ``store``'s one domain built with the watertight
    and with the fast triangle test; each scene answers once untimed first."""
    dom = store.load_domain(0, mmap=False)
    out = {}
    for side, test in (("vastray", "watertight"), ("vastray_fast", "fast")):
        with triangle_test(test):
            scene = Scene(np.asarray(dom.vertices), np.asarray(dom.indices))
        try:
            query(scene)
            times = []
            for _ in range(repeat):
                start = time.perf_counter()
                hit = query(scene)
                times.append(time.perf_counter() - start)
            out[side] = (min(times), int(hit.sum()))
        finally:
            scene.close()
    return out


def recorded_rays_same(peer: MitsubaRenderer, store: Store, camera: Camera, light_pos,
                       intensity, spp: int, threads: int, repeat: int
                       ) -> dict[str, dict[str, tuple[float, int, int]]]:
    """vastray's own bounce and shadow rays (those of one render of this scene, recorded by
    the tracer) traced by Mitsuba (``ray_intersect_preliminary``; ``ray_test`` up to each
    shadow ray's ``maxt``) and by vastray's kernels (watertight and fast), ``threads``
    threads each: where a render's query time goes after its camera rays, on the same rays.

    Returns {"bounce" | "shadow": {side: (best seconds of ``repeat``, rays, rays that hit)}}."""
    import drjit as dr

    config = SceneConfig(camera={"position": camera.position, "look_at": camera.look_at,
                                 "up": camera.up, "fov": FOV},
                         lights=[PointLight(np.asarray(light_pos, float), np.full(3, intensity))])
    settings = RenderSettings(width=WIDTH, height=HEIGHT, spp=spp, integrator="pt",
                              bounces=BOUNCES, seed=3)
    batches: list = []
    render(store, config, settings, threads=threads, progress=False, record_rays=batches)
    out: dict[str, dict[str, tuple[float, int, int]]] = {}
    for kind in ("bounce", "occluded"):
        mine = [b for b in batches if b[0] == kind]
        if not mine:
            continue
        org = np.concatenate([b[1] for b in mine]).astype(np.float32)
        dirs = np.concatenate([b[2] for b in mine]).astype(np.float32)
        t_max = (np.concatenate([b[3] for b in mine]).astype(np.float32) if kind == "occluded"
                 else np.full(len(org), np.inf, np.float32))
        mitsuba, vastray = _recorded_times(peer, dr, store, org, dirs, t_max,
                                           kind == "occluded", threads, repeat)
        out["shadow" if kind == "occluded" else kind] = {
            side: (secs, len(org), hits)
            for side, (secs, hits) in {"mitsuba": mitsuba, **vastray}.items()}
    return out


def _recorded_times(peer: MitsubaRenderer, dr, store: Store, org: np.ndarray,
                    dirs: np.ndarray, t_max: np.ndarray, occlusion: bool, threads: int,
                    repeat: int) -> tuple[tuple[float, int], dict[str, tuple[float, int]]]:
    """``recorded_rays_same``'s timings of one query kind, closest hits or (``occlusion``)
    shadow rays up to ``t_max``: Mitsuba's (seconds, hits), vastray's ``_vastray_times``."""
    mi = peer.mi
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(org[:, k])) for k in range(3))),
                   mi.Vector3f(*(mi.Float(np.ascontiguousarray(dirs[:, k])) for k in range(3))))
    if occlusion:
        ray.maxt = mi.Float(t_max)
    dr.eval(ray)
    if occlusion:
        return (_mitsuba_times(dr, repeat, lambda: peer.scene.ray_test(ray),
                               lambda blocked: blocked, lambda blocked: blocked),
                _vastray_times(store, repeat, lambda scene: _batched(
                    lambda o, d, t: scene.occluded(o, d, t, 1), org, dirs, t_max, threads)))
    return (_mitsuba_times(dr, repeat, lambda: peer.scene.ray_intersect_preliminary(ray),
                           lambda pi: (pi.t, pi.prim_index), lambda pi: pi.is_valid()),
            _vastray_times(store, repeat, lambda scene: _batched(
                lambda o, d, t: scene.intersect(o, d, t, 1)["primID"] >= 0,
                org, dirs, t_max, threads)))


def _blocks(image: np.ndarray) -> np.ndarray:
    """Means of 8 x 8 pixel blocks: (H / 8, W / 8, 3)."""
    return image.reshape(HEIGHT // 8, 8, WIDTH // 8, 8, 3).mean(axis=(1, 3))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="smaller scene (160^3, ~0.3 M triangles) and 4 spp")
    parser.add_argument("--resolution", type=int, default=None,
                        help="rm scene resolution (default 288: ~1 M triangles)")
    parser.add_argument("--spp", type=int, default=None, help="samples per pixel (default 16)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--repeat", type=int, default=None,
                        help="timed runs of each side, interleaved (default 3; --quick 1)")
    parser.add_argument("--hog", type=int, default=0, metavar="N",
                        help="also time both sides (llvm_ad_rgb) beside N busy processes and "
                             "print mitsuba_ratio_hog= (default 0: quiet runs only)")
    parser.add_argument("--scan", default=None, metavar="FILE[:ISO]",
                        help="render a real scan instead of rm: a mesh, or a volume and its "
                             "iso value, absolute or under ../shared/data (e.g. "
                             "volumes/embryo_256.nii.gz:60, ~1 M triangles)")
    parser.add_argument("--save", type=Path, default=None,
                        help="write both images (.npy) into this folder")
    args = parser.parse_args()
    resolution = args.resolution or (160 if args.quick else 288)
    spp = args.spp or (4 if args.quick else 16)
    args.repeat = args.repeat or (1 if args.quick else 3)
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        print("Mitsuba 3 is not installed: pip install -e \".[peers]\" (or pip install "
              "mitsuba); its llvm_ad_rgb variant also needs a recent system libLLVM, "
              "e.g. apt-get install -y libllvm19", file=sys.stderr)
        return 2

    if args.scan:
        store, label = scan_store(args.scan)
    else:
        store, label = plain_store(resolution), f"rm {resolution}^3"
    n_tri = store.n_triangles
    camera, light_pos, intensity = setup(store)
    print(f"scene: {label}, {n_tri:,} triangles, 1 domain; {WIDTH}x{HEIGHT}, {spp} "
          f"spp, vastray --bounces {BOUNCES} = Mitsuba max_depth {MAX_DEPTH}, point light, "
          f"two-sided diffuse {ALBEDO}, {args.threads} threads")

    # vastray: a warm-up render (numba kernels from the on-disk cache), then timed ones
    start = time.perf_counter()
    run_vastray(store, camera, light_pos, intensity, spp, args.threads, seed=1)
    print(f"vastray: warm-up render (incl. load) {time.perf_counter() - start:.3f} s")

    results = {}
    why_not = try_llvm()
    variants = ["llvm_ad_rgb", "scalar_rgb"] if why_not is None else ["scalar_rgb"]
    if why_not is not None:
        print(f"llvm_ad_rgb unavailable ({why_not}): comparing with scalar_rgb only "
              "(install a recent system libLLVM, e.g. apt-get install -y libllvm19)")
    with tempfile.TemporaryDirectory() as tmp:
        ply = Path(tmp) / "scene.ply"
        dom = store.load_domain(0)
        write_ply(ply, np.asarray(dom.vertices), np.asarray(dom.indices))
        for variant in variants:
            peer = MitsubaRenderer(variant, ply, camera, light_pos, intensity, spp, args.threads)
            print(f"mitsuba {variant}: load (PLY read + BVH build) {peer.load:.3f} s, warm-up "
                  f"render {peer.warm:.3f} s")
            # interleaved: vastray, Mitsuba, vastray, ... ; best of each side
            v_img, v_times, v_loads, img, m_times = interleaved(
                store, camera, light_pos, intensity, spp, args.threads, peer, args.repeat, 2)
            results[variant] = img
            print(f"  render s, {args.repeat} interleaved runs: vastray "
                  f"{' '.join(f'{t:.3f}' for t in v_times)} (load excluded: "
                  f"{' '.join(f'{t:.3f}' for t in v_loads)} s of read + BVH build); "
                  f"mitsuba {variant} {' '.join(f'{t:.3f}' for t in m_times)}")
            key = "mitsuba_ratio" if variant == "llvm_ad_rgb" else "mitsuba_scalar_ratio"
            rel = float(v_img.mean() / img.mean() - 1.0)
            per_channel = v_img.mean(axis=(0, 1)) / img.mean(axis=(0, 1)) - 1.0
            # pixel-wise: noise of both at this spp dominates; 8x8 block means average it out
            block_mad = float(np.abs(_blocks(v_img) - _blocks(img)).mean() / img.mean())
            print(f"{key}={min(v_times) / min(m_times):.3f} (best vastray / best mitsuba)  "
                  f"mean_rel_diff_{variant}={rel:+.4f} (per channel "
                  f"{np.array2string(per_channel, precision=4)}; 8x8-block mean abs diff / "
                  f"mean {block_mad:.4f})")
            if abs(rel) > 0.02:
                print(f"WARNING: images differ by {rel:+.2%} in mean (> 2 %)")
            if variant == "llvm_ad_rgb":
                with triangle_test("fast"):
                    f_img, f_times, _, _, fm_times = interleaved(
                        store, camera, light_pos, intensity, spp, args.threads, peer,
                        args.repeat, 2)
                f_rel = float(f_img.mean() / img.mean() - 1.0)
                print(f"  the same work, vastray with Mitsuba's triangle test "
                      f"(VASTRAY_TRIANGLE_TEST=fast), render s: vastray "
                      f"{' '.join(f'{t:.3f}' for t in f_times)}; mitsuba {variant} "
                      f"{' '.join(f'{t:.3f}' for t in fm_times)}")
                print(f"mitsuba_ratio_same_test={min(f_times) / min(fm_times):.3f} (best / "
                      f"best; mitsuba_ratio above is vastray's default watertight test)  "
                      f"mean_rel_diff_same_test={f_rel:+.4f}")
                same = camera_rays_same(peer, store, spp, args.threads, max(3, args.repeat))
                print("embree_camera_rays_s=" + ",".join(
                    f"{side}:{secs:.4f}" for side, (secs, _) in same.items())
                      + f"  ({WIDTH * HEIGHT * spp:,} of Mitsuba's camera rays, "
                        f"{args.threads} threads, best of {max(3, args.repeat)}; hits "
                      + ", ".join(f"{side} {hit:,}" for side, (_, hit) in same.items()) + ")")
                recorded = recorded_rays_same(peer, store, camera, light_pos, intensity, spp,
                                              args.threads, max(3, args.repeat))
                for kind, sides in recorded.items():
                    rays = next(iter(sides.values()))[1]
                    print(f"embree_{kind}_rays_s=" + ",".join(
                        f"{side}:{secs:.4f}" for side, (secs, _, _) in sides.items())
                          + f"  ({rays:,} of vastray's {kind} rays, "
                            f"{rays and sides['vastray'][0] / rays * 1e9 * args.threads:.0f} vs "
                            f"{rays and sides['mitsuba'][0] / rays * 1e9 * args.threads:.0f} "
                            f"thread-ns a ray; hits "
                          + ", ".join(f"{side} {hit:,}" for side, (_, _, hit) in sides.items())
                          + ")")
            if variant == "llvm_ad_rgb" and args.hog:
                print(f"mitsuba_ratio_median="
                      f"{np.median(v_times) / np.median(m_times):.3f} (median / median)")
                with busy_processes(args.hog):
                    _, hv_times, _, _, hm_times = interleaved(
                        store, camera, light_pos, intensity, spp, args.threads, peer,
                        args.repeat, 2 + args.repeat)
                print(f"  under a hog of {args.hog} busy processes, render s, {args.repeat} "
                      f"interleaved runs: vastray {' '.join(f'{t:.3f}' for t in hv_times)}; "
                      f"mitsuba {variant} {' '.join(f'{t:.3f}' for t in hm_times)}")
                print(f"mitsuba_ratio_hog={np.median(hv_times) / np.median(hm_times):.3f} "
                      f"(median vastray / median mitsuba, {args.hog} busy processes; "
                      f"slowdown vastray {np.median(hv_times) / np.median(v_times):.2f}x, "
                      f"mitsuba {np.median(hm_times) / np.median(m_times):.2f}x)")
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
        np.save(args.save / "vastray.npy", v_img)
        for variant, img in results.items():
            np.save(args.save / f"mitsuba_{variant}.npy", img)
    if "llvm_ad_rgb" not in results:
        print("mitsuba_ratio=n/a (llvm_ad_rgb unavailable)")
        if args.hog:
            print("mitsuba_ratio_hog=n/a (llvm_ad_rgb unavailable)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
