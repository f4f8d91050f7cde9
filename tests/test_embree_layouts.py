"""The layouts the compiled Embree binding hard-codes, checked against the library at load
(``vastray.scene.embree.probe``), the refusal of a library that differs, and the scene flag
the argument filter needs."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
import trimesh

from vastray.scene.bvh import DomainBVH
from vastray.scene.embree import kernels, library, probe
from vastray.scene.embree.scenes import FILTER_FLAG, SCENE_FLAGS, Scene, TopScene

from scenes import forget_binding, mesh_arrays


def _box():
    return mesh_arrays(trimesh.creation.box(extents=[2.0, 1.0, 0.5]))


def _refused(match: str) -> str:
    """Load the library again: it must be refused with one warning of one line matching
    ``match``, and a domain must fall back to embreex (and still trace)."""
    with pytest.warns(library.EmbreeFallbackWarning, match=match) as caught:
        assert library.binding() is None
    messages = [str(w.message) for w in caught
                if issubclass(w.category, library.EmbreeFallbackWarning)]
    assert len(messages) == 1 and "\n" not in messages[0]
    bvh = DomainBVH(0, _box())
    assert not bvh.compiled
    hit = bvh.intersect(np.array([[0.0, 0.0, 5.0]], np.float32),
                        np.array([[0.0, 0.0, -1.0]], np.float32),
                        np.array([np.inf], np.float32))
    assert hit["primID"][0] >= 0 and np.isclose(hit["tfar"][0], 4.75)
    return messages[0]


def test_installed_library_passes_the_layout_check(reload_binding):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        api = library.binding()  # loads the library and runs the probe
    assert api is not None
    assert (api.major, api.minor) in library.TESTED_VERSIONS
    probe.check_layouts(api)  # again, explicitly: no LayoutMismatch
    assert DomainBVH(0, _box()).compiled


def test_untested_version_is_refused(reload_binding, monkeypatch):
    monkeypatch.setattr(library, "TESTED_VERSIONS", ((4, 3),))
    message = _refused("not a tested version")
    print(message)
    assert "(4.3)" in message


@pytest.mark.parametrize("name, value, problem", [
    ("RAYHIT_PRIM", kernels.RAYHIT_PRIM + 1, "RTCRayHit word"),  # primID elsewhere
    ("RAYHIT_TFAR", kernels.RAYHIT_TFAR + 1, "no hit"),  # Embree reads a garbage tfar
    ("HITN_INST", kernels.HITN_INST + 1, "the filter read"),  # RTCHitN's instID elsewhere
    ("ARG_CONTEXT", kernels.ARG_CONTEXT - 8, "RTCFilterFunctionNArguments"),
    ("CTX_RECORD", 4, "RTCRayQueryContext"),  # our record over Embree's instance stack
    ("PACKET", 16, "8-ray packet"),  # RTCRayHit8's lanes elsewhere
])
def test_mismatching_layout_is_refused(reload_binding, monkeypatch, name, value, problem):
    """The probe's expectations changed one at a time (as a library laid out otherwise would
    differ from them): refused in one line naming the structure, then embreex."""
    if name == "PACKET" and os.environ.get(library.EMBREE_CONFIG_ENV):
        pytest.skip(f"{library.EMBREE_CONFIG_ENV} set: the library may not trace packets, "
                    "and then no packet is probed")
    monkeypatch.setattr(kernels, name, value)
    message = _refused("does not match the layouts the kernels use")
    print(message)
    assert problem in message


class _TwoInstanceLevels(library.Api):
    """The library, but every hit written as a build with ``RTC_MAX_INSTANCE_LEVEL_COUNT`` 2
    (and instance arrays) writes it: instID[0], instID[1], instPrimID[0], instPrimID[1] at
    words 19-22 of RTCRayHit, where the kernels keep their 96-byte buffer's end."""

    def __init__(self, path):
        super().__init__(path)
        real = self.rtcIntersect1

        def intersect(scene, rayhit, args):
            real(scene, rayhit, args)
            words = (ctypes.c_uint32 * 24).from_address(rayhit)
            if words[kernels.RAYHIT_PRIM] != 0xFFFFFFFF:
                words[20], words[21], words[22] = 0xFFFFFFFF, 0, 0xFFFFFFFF

        self.rtcIntersect1 = intersect


def test_wider_instance_stack_is_refused(reload_binding, monkeypatch):
    monkeypatch.setattr(library, "Api", _TwoInstanceLevels)
    message = _refused("RTC_MAX_INSTANCE_LEVEL_COUNT")
    print(message)
    assert "RTCRayHit word 20" in message
    monkeypatch.undo()
    forget_binding()
    assert library.binding() is not None  # the real one passes again


def test_filter_flag_is_set_on_every_scene_the_filter_traverses():
    api = library.binding()
    assert api is not None
    arrays = _box()
    robust = Scene(arrays.vertices, arrays.indices)
    fast = Scene(arrays.vertices, arrays.indices, flags=library.RTC_SCENE_FLAG_NONE)
    top = TopScene([robust, fast], [0, 1])
    try:
        flags = {name: api.rtcGetSceneFlags(scene.handle)
                 for name, scene in (("robust", robust), ("fast", fast), ("top", top))}
        assert FILTER_FLAG == library.RTC_SCENE_FLAG_FILTER_FUNCTION_IN_ARGUMENTS == 1 << 3
        assert flags == {"robust": SCENE_FLAGS | FILTER_FLAG, "fast": FILTER_FLAG,
                         "top": SCENE_FLAGS | FILTER_FLAG}
        # and the tie filter runs through them: closest hits as before
        o = np.array([[0.0, 0.0, 5.0]], np.float32)
        d = np.array([[0.0, 0.0, -1.0]], np.float32)
        t = np.array([np.inf], np.float32)
        assert robust.intersect(o, d, t)["primID"][0] >= 0
        assert top.intersect(o, d, t)["id"][0] == 0
    finally:
        for scene in (top, robust, fast):
            scene.close()


WITHOUT_AVX = textwrap.dedent("""
    import os, warnings
    import numpy as np
    warnings.simplefilter("error")  # no EmbreeFallbackWarning: the compiled binding is used
    from vastray.scene.embree import kernels, library
    from vastray.scene.embree.scenes import Scene, TopScene
    api = library.binding()
    assert api is not None and not api.packets, api
    rng = np.random.default_rng(3)
    v = rng.random((300, 3)).astype(np.float32)
    f = rng.integers(0, 300, (400, 3)).astype(np.uint32)
    o = (rng.random((5000, 3)) * 3 - 1).astype(np.float32)
    d = (rng.random((5000, 3)) - 0.5).astype(np.float32)
    t = np.full(5000, np.inf, np.float32)
    whole = Scene(v, f)
    parts = [Scene(v, f[:150]), Scene(v, f[150:])]
    top = TopScene(parts, [0, 1])
    a = whole.intersect(o, d, t, threads=2)
    b = top.intersect(o, d, t, threads=1)
    assert (a["primID"] >= 0).sum() > 100
    # the same hits whether the mesh is one scene or two instances (the tie filter's records)
    np.testing.assert_array_equal(a["tfar"], b["tfar"])
    np.testing.assert_array_equal(np.where(b["id"] == 1, b["primID"] + 150, b["primID"]),
                                  a["primID"])
    np.testing.assert_array_equal(whole.occluded(o, d, t, threads=2), a["primID"] >= 0)
    print(sum(len(k.overloads) for k in (kernels.intersect_nearest, kernels.occluded1)),
          sum(len(k.overloads) for k in (kernels.intersect_nearest8, kernels.occluded8)))
    os.environ["VASTRAY_QUERIES"] = "packets"
    try:
        whole.occluded(o, d, t)
    except ValueError as exc:
        print(exc)
""")


def test_a_library_tracing_packets_ray_by_ray_runs_the_one_ray_kernels():
    """Without AVX (emulated: Embree's ``max_isa=sse4.2``) ``rtcIntersect8`` traces a packet's
    rays one by one and hands the filter one lane, which the packet kernels' per-lane records
    cannot follow. Such a library is not refused (with 16-ray packets an AVX2 one was, and
    every query went through embreex): it is used with the 1-ray kernels, ties broken as
    everywhere, and a request for packets there is refused with the reason."""
    env = {**os.environ, library.EMBREE_CONFIG_ENV: "max_isa=sse4.2"}
    env.pop("VASTRAY_QUERIES", None)
    out = subprocess.run([sys.executable, "-c", WITHOUT_AVX], env=env, check=True,
                         capture_output=True, text=True).stdout.splitlines()
    single, packets = (int(x) for x in out[0].split())
    assert single == 2 and packets == 0  # only the 1-ray kernels ran
    assert "traces 8-ray packets ray by ray" in out[1] and "unset VASTRAY_QUERIES" in out[1]
