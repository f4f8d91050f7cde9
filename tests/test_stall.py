"""A job whose nodes all live but cannot all reach each other ends, never hangs: nodes wait for
one another as long as their coordinator speaks (an idle member is no lost one), and say in
their heartbeats how long they have been waiting, so the coordinator ends a job in which every
node has waited for over ``--node-timeout`` (issue 37's "every network wait has a timeout";
found when a firewall, docker's FORWARD DROP, cut the peer traffic of tests/test_netns.py and
the render waited for ever). Real processes and sockets."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.node_failure import NodeFailure

from scenes import bumpy_scene, reap, settings, write_store


@pytest.mark.slow  # 22 s of waiting for the stall; .ci/run runs it
def test_nodes_cut_off_from_a_peer_end_the_job_instead_of_waiting_for_ever(tmp_path):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    port = 46000 + os.getpid() % 1000
    logs = [tmp_path / f"n{i}.log" for i in range(2)]
    # node 1 tells its peers an address nothing listens on: they can never send it a batch,
    # while it and they keep heartbeating to the coordinator
    advertise = [[], ["--advertise", "127.0.0.2"]]
    errs = [open(log, "w") for log in logs]  # noqa: SIM115 - closed below
    nodes = [subprocess.Popen(
        [sys.executable, "-m", "vastray.cli", "node", "--coordinator",
         f"tcp://127.0.0.1:{port}", "--timeout", "600", *advertise[i]],
        stdout=subprocess.DEVNULL, stderr=errs[i]) for i in range(2)]
    start = time.monotonic()
    try:
        with pytest.raises(NodeFailure) as failure:
            render_distributed(store.path, None, settings(width=32, height=24, spp=2,
                                                          integrator="pt"), 2,
                               listen=f"127.0.0.1:{port}", timeout=15, survive_node_loss=False,
                               options=JobOptions(scheduler="async", max_samples_in_flight=200))
    finally:
        reap(nodes)
        for err in errs:
            err.close()
    assert "every node has waited for another for over 15 s" in str(failure.value), failure.value
    assert time.monotonic() - start < 300  # ended by the coordinator, not by a node's timeout
