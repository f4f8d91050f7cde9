"""A node loss is survived, not just reported: kill -9 or SIGSTOP one of 4 nodes mid-frame, and
the frame completes with the image of the fault-free render."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from test_distributed import _node_pids

from vastray.actors.coordinator import render_distributed
from vastray.render.driver import render
from vastray.render.scene_config import load_scene_config

from scenes import POINT_AND_SKY_TOML, bumpy_scene, settings, write_store


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("loss")
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    return write_store(root / "s", bumpy_scene(), kd=8), root / "scene.toml"


@pytest.mark.parametrize("scheduler, sig", [
    ("domain", signal.SIGKILL), ("async", signal.SIGKILL), ("spec-insitu", signal.SIGKILL),
    ("image", signal.SIGKILL), ("async", signal.SIGSTOP), ("image", signal.SIGSTOP)])
def test_a_lost_node_is_survived_with_the_fault_free_image(scene, scheduler, sig):
    store, toml = scene
    st = settings(width=32, height=24, spp=32, integrator="pt")
    hit = []

    def strike():  # node 2, once it is rendering
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not hit:
            pids = _node_pids(2)
            if pids:
                time.sleep(1.0)
                for pid in pids:
                    os.kill(pid, sig)
                hit.extend(pids)
            time.sleep(0.1)

    striker = threading.Thread(target=strike)
    striker.start()
    try:
        result = render_distributed(store.path, toml, st, 4, scheduler=scheduler, timeout=60,
                                    heartbeat_timeout=5.0, max_samples_in_flight=300)
    finally:
        striker.join()
    assert hit, "the test found no node 2 to stop"
    assert result.counters["nodes_asked"] == 4 and result.counters["nodes"] == 3
    assert len(result.counters["node_failures"]) == 1
    assert "node 2" in result.counters["node_failures"][0]
    reference = render(store, load_scene_config(toml), st, progress=False).film
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(result.film.count, reference.count)  # nothing counted twice
