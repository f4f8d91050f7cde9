"""A node's warm-up (``actors.node_warm_up``): after it, no scheduler's render has a compiled
kernel left to load nor a module left to import, and a node whose temporary folder cannot be
written still starts."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import tempfile
import textwrap

import pytest

from vastray.actors import node_warm_up
from vastray.scene.generate import generate

#: Run in a fresh process (this one's kernels are warm from other tests), started as a node
#: starts (``vastray.actors.node`` imported): warm the node, list every compiled kernel's
#: loaded signatures and whether scipy's linear algebra was imported, render with every
#: scheduler the nodes run (the simulator runs the nodes' own code in one process), list what
#: was loaded after, then import scipy's BLAS as a later user would.
FRESH_PROCESS = textwrap.dedent("""
    import json, sys
    import vastray.actors.node
    from numba.core.registry import CPUDispatcher
    from vastray.actors.job_options import JobOptions
    from vastray.actors.node_warm_up import warm_node
    from vastray.render.integrators import RenderSettings
    from vastray.render.scene_config import SceneConfig
    from vastray.scene.generate import generate
    from vastray.scene.store import Store
    from vastray.sim.costs import CostModel
    from vastray.sim.simulate import SIM_SCHEDULERS, simulate

    def loaded():
        found = set()
        for name, module in list(sys.modules.items()):
            if not name.startswith("vastray"):
                continue
            for value in list(vars(module).values()):
                members = vars(value).values() if isinstance(value, type) else [value]
                for member in members:
                    kernel = getattr(member, "__func__", member)
                    if isinstance(kernel, CPUDispatcher):
                        name = kernel.py_func.__module__ + "." + kernel.py_func.__qualname__
                        found |= {(name, str(sig)) for sig in kernel.signatures}
        return found

    store = Store(sys.argv[1])
    warm_node()
    warm, modules = loaded(), set(sys.modules)
    scipy_at_warm = sorted(m for m in modules if m.startswith("scipy.linalg"))
    for scheduler in SIM_SCHEDULERS:
        for integrator in ("pt", "ao"):
            settings = RenderSettings(width=24, height=18, spp=1, integrator=integrator,
                                      bounces=2)
            simulate(store, JobOptions(scheduler=scheduler, cache=3), 2, CostModel(),
                     settings, SceneConfig())
    left = sorted(n for n, _ in loaded() - warm)
    imported = sorted(m for m in set(sys.modules) - modules if m.startswith("vastray"))
    import scipy.linalg.cython_blas
    from numba.np import arraymath
    print(json.dumps({"warm": len(warm), "left": left, "imported": imported,
                      "scipy_at_warm": scipy_at_warm, "numba_blas": arraymath._HAVE_BLAS,
                      "cython_blas": hasattr(scipy.linalg.cython_blas, "__pyx_capi__")}))
""")


@pytest.fixture(scope="module")
def fresh_node(tmp_path_factory) -> dict:
    """What ``FRESH_PROCESS`` found, on a store written here (writing one imports scipy)."""
    path = tmp_path_factory.mktemp("warm-up") / "rm.store"
    generate("rm", path, 24, grid=(2, 2, 2))
    done = subprocess.run([sys.executable, "-c", FRESH_PROCESS, str(path)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_no_scheduler_has_a_kernel_left_to_load_after_the_warm_up(fresh_node):
    found = fresh_node
    assert found["warm"] >= 10, found  # the warm-up did call the kernels
    assert found["left"] == [], ("kernels a node's first frame would still load from numba's "
                                 f"cache; make the warm-up's tiny render call them: {found}")
    assert found["imported"] == [], ("modules a node's first frame would still import; add "
                                     f"them to node_warm_up.FIRST_USE_MODULES: {found}")


def test_a_node_without_a_writable_temporary_folder_still_warms_numba(
        tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "missing" / "folder"))
    with caplog.at_level(logging.WARNING, logger=node_warm_up.__name__):
        seconds = node_warm_up.warm_node()
    assert seconds >= 0.0
    assert "could not warm the render kernels" in caplog.text
    assert "first frame pays their first calls" in caplog.text


def test_the_tiny_store_has_occupancy_masks_with_empty_cells(tmp_path):
    store = node_warm_up._tiny_store(tmp_path / "warm.store")
    assert len(store.domains) == 3
    masks = [d.occupancy for d in store.domains]
    assert all(m is not None for m in masks)
    # holes: some cell of each mask is empty, so the mask's query skips rays
    assert all(m.any() and not m.all() for m in masks)


def test_a_node_warms_numba_without_scipy_and_still_renders_every_scheduler(fresh_node):
    # numba's BLAS probe did not import scipy.linalg (0.25 s of every node's start) ...
    assert fresh_node["scipy_at_warm"] == [], fresh_node
    assert fresh_node["numba_blas"] is False, fresh_node
    # ... yet every kernel of every scheduler ran (the test above), and scipy's BLAS
    # imports afterwards
    assert fresh_node["cython_blas"] is True, fresh_node


def test_a_nodes_log_says_how_it_queries_embree(tmp_path):
    # A node warms its kernels while it waits for a coordinator; its log line then names the
    # Embree version and the query path of its own host (a cluster's report describes the
    # coordinator's machine only). Emulated as an SSE-only host: one ray a call.
    import os
    import signal

    from scenes import free_port

    env = {**os.environ, "VASTRAY_RUNTIME_DIR": str(tmp_path),
           "VASTRAY_EMBREE_CONFIG": "max_isa=sse4.2"}
    node = subprocess.Popen([sys.executable, "-m", "vastray", "-v", "node", "--coordinator",
                             f"tcp://127.0.0.1:{free_port()}", "--timeout", "600"],
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines = []
        while not any("render kernels warm" in line for line in lines):
            line = node.stderr.readline()
            assert line, "".join(lines)  # the node ended before its warm-up line
            lines.append(line)
        node.send_signal(signal.SIGTERM)
        node.wait(timeout=60)
    finally:
        node.kill()
        node.wait()
        node.stderr.close()
    warm = next(line for line in lines if "render kernels warm" in line)
    assert "; Embree 4." in warm and warm.rstrip().endswith(", 1 ray a call)"), warm
