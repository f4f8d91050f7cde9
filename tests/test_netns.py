"""The multi-host path across separate network namespaces (veth + bridge), when this machine
lets the test create them; skipped with the reason otherwise."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid

import numpy as np
import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.render.driver import render
from vastray.render.scene_config import SceneConfig
from vastray.transport.keys import add_node_key, generate_keys, load_coordinator_keys

from scenes import bumpy_scene, reap, settings, write_store

SUBNET = "10.231.77"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture
def namespaces():
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("needs root and iproute2 to create network namespaces")
    tag = uuid.uuid4().hex[:6]
    bridge, names = f"vtb{tag}", [f"vtn{tag}{i}" for i in range(2)]
    forward = None
    try:
        _ip("link", "add", bridge, "type", "bridge")
    except subprocess.CalledProcessError as exc:
        pytest.skip(f"cannot create network devices here: {exc.stderr.decode().strip()}")
    try:
        _ip("addr", "add", f"{SUBNET}.1/24", "dev", bridge)
        _ip("link", "set", bridge, "up")
        for i, ns in enumerate(names):
            _ip("netns", "add", ns)
            host_end, ns_end = f"vth{tag}{i}", f"vtp{tag}{i}"
            _ip("link", "add", host_end, "type", "veth", "peer", "name", ns_end)
            _ip("link", "set", ns_end, "netns", ns)
            _ip("link", "set", host_end, "master", bridge)
            _ip("link", "set", host_end, "up")
            _ip("-n", ns, "addr", "add", f"{SUBNET}.{11 + i}/24", "dev", ns_end)
            _ip("-n", ns, "link", "set", ns_end, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        # Traffic between the namespaces crosses the bridge, and where bridged frames go
        # through iptables (br_netfilter, loaded by docker, which also sets FORWARD's policy
        # to DROP) it is dropped: the nodes reached the coordinator but not each other. Let
        # this bridge's own traffic through, as a cluster's network would.
        forward = ["FORWARD", "-i", bridge, "-o", bridge, "-j", "ACCEPT"]
        if shutil.which("iptables") is not None:
            opened = subprocess.run(["iptables", "-I", *forward], capture_output=True)
            if opened.returncode != 0:
                forward = None
        yield names
    finally:
        if forward is not None and shutil.which("iptables") is not None:
            subprocess.run(["iptables", "-D", *forward], capture_output=True)
        for ns in names:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        subprocess.run(["ip", "link", "del", bridge], capture_output=True)


def test_nodes_in_separate_network_namespaces(namespaces, tmp_path):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    generate_keys(tmp_path / "keys")
    for ns in namespaces:  # each node its own key
        add_node_key(tmp_path / "keys", ns)
    port = 47000 + os.getpid() % 1000
    nodes = [subprocess.Popen(
        ["ip", "netns", "exec", ns, sys.executable, "-m", "vastray.cli", "node",
         "--coordinator", f"tcp://{SUBNET}.1:{port}", "--bind", "0.0.0.0",
         "--keys", str(tmp_path / "keys"), "--key-name", ns, "--timeout", "120"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for ns in namespaces]
    try:
        st = settings(width=24, height=18, spp=2, integrator="pt")
        result = render_distributed(store.path, None, st, 2, listen=f"{SUBNET}.1:{port}",
                                    keys=load_coordinator_keys(tmp_path / "keys"), timeout=120,
                                    options=JobOptions(max_samples_in_flight=200))
        reference = render(store, SceneConfig(), st, progress=False).film.image()
        np.testing.assert_allclose(result.film.image(), reference, rtol=1e-6, atol=1e-6)
    finally:
        reap(nodes)
    errors = []
    for node in nodes:
        errors.append(node.stderr.read().decode())
        node.stderr.close()
    assert all(node.returncode == 0 for node in nodes), errors
