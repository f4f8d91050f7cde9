"""Launch under the engines clusters already run: ranks from Slurm / PMI / Open MPI variables,
the coordinator found through a rendezvous file, and the shipped Slurm batch script run for N
local processes with the variables srun would set."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.actors.rendezvous import (
    coordinator_address,
    launcher_rank,
    launcher_size,
    read_address,
    write_address,
)
from vastray.cli import main
from vastray.render.driver import render
from vastray.render.imageio import read_exr
from vastray.render.scene_config import load_scene_config
from vastray.scene.errors import InputError

from scenes import bumpy_scene, settings, write_store

ROOT = Path(__file__).resolve().parents[1]

#: A stand-in for srun: SLURM_NTASKS copies of the command, each with its SLURM_PROCID.
FAKE_SRUN = """#!/bin/sh
i=0; pids=""
while [ "$i" -lt "$SLURM_NTASKS" ]; do
  SLURM_PROCID=$i "$@" 2> "$NODE_LOGS/node$i.log" &
  pids="$pids $!"; i=$((i + 1))
done
status=0
for p in $pids; do wait "$p" || status=1; done
exit $status
"""


@pytest.mark.parametrize("variables, rank, size", [
    ({"SLURM_PROCID": "3", "SLURM_NTASKS": "8"}, 3, 8),
    ({"PMI_RANK": "1", "PMI_SIZE": "4"}, 1, 4),
    ({"OMPI_COMM_WORLD_RANK": "2", "OMPI_COMM_WORLD_SIZE": "3"}, 2, 3),
    ({}, None, None),
])
def test_rank_and_size_from_the_launcher(monkeypatch, variables, rank, size):
    for name in ("SLURM_PROCID", "SLURM_NTASKS", "PMI_RANK", "PMI_SIZE", "PMIX_RANK",
                 "PMIX_SIZE", "OMPI_COMM_WORLD_RANK", "OMPI_COMM_WORLD_SIZE"):
        monkeypatch.delenv(name, raising=False)
    for name, value in variables.items():
        monkeypatch.setenv(name, value)
    assert launcher_rank() == rank and launcher_size() == size


def test_rendezvous_file(tmp_path):
    with pytest.raises(InputError, match="no coordinator address appeared"):
        read_address(tmp_path / "job.addr", timeout=0.3)
    write_address(tmp_path / "job.addr", "tcp://head:5555")
    assert read_address(tmp_path / "job.addr", timeout=1) == "tcp://head:5555"
    (tmp_path / "bad.addr").write_text("head:5555\n")
    with pytest.raises(InputError, match="not a tcp://HOST:PORT"):
        read_address(tmp_path / "bad.addr", timeout=1)


def test_coordinator_address_is_checked_before_any_socket():
    assert coordinator_address("127.0.0.1:5999") == "tcp://127.0.0.1:5999"
    assert coordinator_address("tcp://localhost:5999") == "tcp://localhost:5999"
    for bad in ("udp://head:5555", "tcp://head", "head:port", "tcp://head:70000"):
        with pytest.raises(InputError, match="is not tcp://HOST:PORT"):
            coordinator_address(bad)
    with pytest.raises(InputError, match="host 'nosuch.invalid' not found") as refused:
        coordinator_address("tcp://nosuch.invalid:5555")
    assert "the coordinator is running" in str(refused.value)


def test_a_name_that_does_not_resolve_is_tried_again_for_the_wait_given(monkeypatch):
    import socket
    import time

    calls = []

    def resolve(host, *args, **kwargs):
        calls.append(time.monotonic())
        if len(calls) < 3:  # the name service knows the host from the third try on
            raise socket.gaierror(-2, "Name or service not known")
        return []

    monkeypatch.setattr(socket, "getaddrinfo", resolve)
    assert coordinator_address("tcp://coordinator:5555", wait=5) == "tcp://coordinator:5555"
    assert len(calls) == 3

    def never(*args, **kwargs):
        raise socket.gaierror(-2, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", never)
    start = time.monotonic()
    with pytest.raises(InputError, match="after 1 s"):
        coordinator_address("tcp://coordinator:5555", wait=1)
    assert time.monotonic() - start >= 1


@pytest.mark.parametrize("address, says", [
    ("tcp://nosuch.invalid:5999", "host 'nosuch.invalid' not found"),
    ("udp://127.0.0.1:5999", "is not tcp://HOST:PORT"),
])
def test_node_names_a_bad_coordinator_at_once(address, says):
    started = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "vastray.cli", "node", "--coordinator", address,
                          "--timeout", "30"], capture_output=True, text=True, timeout=60)
    assert time.monotonic() - started < 20  # named, not waited out
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"node ?: error: --coordinator {address!r}")
    assert says in out.stderr and "ZMQError" not in out.stderr


def test_rendezvous_needs_listen(tmp_path, capsys):
    store = write_store(tmp_path / "s", bumpy_scene(), grid=(2, 1, 1))
    assert main(["render", str(store.path), "-o", str(tmp_path / "o.exr"), "--nodes", "2",
                 "--rendezvous", str(tmp_path / "a"), "--quiet"]) == 2
    assert "--rendezvous FILE needs --listen" in capsys.readouterr().err


@pytest.mark.skipif(sys.platform == "win32", reason="a POSIX shell script")
def test_the_slurm_batch_script_renders_with_srun_ranks(tmp_path):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    srun = tmp_path / "fake-srun"
    srun.write_text(FAKE_SRUN)
    srun.chmod(0o755)
    (tmp_path / "logs").mkdir()
    shim = tmp_path / "bin"  # a `vastray` that writes down how it was called
    shim.mkdir()
    (shim / "vastray").write_text(f'#!/bin/sh\necho "$*" >> {tmp_path}/calls\n'
                                  f'exec {Path(sys.executable).parent}/vastray "$@"\n')
    (shim / "vastray").chmod(0o755)
    env = dict(os.environ, STORE=str(store.path), OUT=str(tmp_path / "o.exr"),
               KEYS=str(tmp_path / "keys"), RDV=str(tmp_path / "job.addr"), SRUN=str(srun),
               LISTEN="127.0.0.1:0", BIND="127.0.0.1", SLURM_NTASKS="3", SLURM_JOB_ID="42",
               NODE_LOGS=str(tmp_path / "logs"),
               PATH=f"{shim}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}"
                    f"{os.environ.get('PATH', '')}")
    out = subprocess.run(["bash", str(ROOT / "examples" / "slurm.sbatch"), "--width", "24",
                          "--height", "18", "--spp", "2", "--scheduler", "async",
                          "--node-timeout", "30"],
                         env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    st = settings(width=24, height=18, spp=2, bounces=3, shadow_samples=16, seed=0)
    reference = render(store, load_scene_config(None), st, progress=False).film.image()
    np.testing.assert_allclose(read_exr(tmp_path / "o.exr"), reference, rtol=1e-6, atol=1e-6)
    for i in range(3):  # each node took the rank srun gave it
        log = (tmp_path / "logs" / f"node{i}.log").read_text()
        assert re.search(rf"as node {i} of 3", log), log
    assert not (tmp_path / "job.addr").exists()  # the coordinator removed its rendezvous
    # each node was given its host's bundle, never the key folder (issue 37: revocation)
    nodes = [c.split() for c in (tmp_path / "calls").read_text().splitlines()
             if c.startswith("node ")]
    host = socket.gethostname().split(".")[0]
    assert len(nodes) == 3 and all(
        c[c.index("--keys") + 1] == str(tmp_path / "keys" / "bundles" / host) for c in nodes), nodes
