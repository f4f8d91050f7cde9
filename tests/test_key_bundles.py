"""Per-node key bundles (issue 37): `vastray keys` gives each node a folder holding its own
key pair and the coordinator's public key, nothing else, so a host handed only its bundle and
then revoked (its public key off the allow-list) has no other node's secret to join with.
Real processes and ZeroMQ sockets; `vastray launch` through a local stand-in for ssh."""

from __future__ import annotations

import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vastray.cli import main
from vastray.render.imageio import read_exr

from scenes import bumpy_scene, free_port, write_store

SMALL = ["--width", "24", "--height", "18", "--spp", "2"]
LOCAL_SSH = "#!/bin/sh\n# stand-in for `ssh HOST CMD`: drop HOST, run CMD here\nshift\nexec sh -c \"$1\"\n"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("bundles") / "s.store", bumpy_scene(), kd=6)


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}


def _values(path: Path) -> dict[str, str]:
    return dict(re.findall(r"^(\w+) = (\S+)$", path.read_text(), re.M))


def _assert_reference_image(store, out: Path, tmp_path: Path) -> None:
    """``out`` is the single-process render of the same settings (not black, not partial)."""
    reference = tmp_path / "reference.exr"
    assert main(["render", str(store.path), "-o", str(reference), *SMALL, "--quiet"]) == 0
    expected = read_exr(reference)
    assert expected.max() > 0.05
    np.testing.assert_allclose(read_exr(out), expected, rtol=1e-6, atol=1e-6)


def test_a_bundle_holds_its_node_key_pair_and_the_coordinator_public_key_only(tmp_path, capsys):
    keys = tmp_path / "keys"
    assert main(["keys", "-o", str(keys), "--node", "n1", "--node", "n2"]) == 0
    printed = capsys.readouterr().out.split()
    coordinator = _values(keys / "coordinator.key")
    for name, other in (("n1", "n2"), ("n2", "n1")):
        bundle = keys / "bundles" / name
        assert str(bundle) in printed  # what to hand to host NAME
        assert _files(bundle) == {"coordinator.pub", f"nodes/{name}.key"}
        pair = bundle / "nodes" / f"{name}.key"
        assert stat.S_IMODE(pair.stat().st_mode) == 0o600
        for folder in (bundle, bundle / "nodes", keys / "bundles"):
            assert stat.S_IMODE(folder.stat().st_mode) == 0o700, folder
        assert _values(pair) == _values(keys / "nodes" / f"{name}.key")  # public and secret
        assert _values(pair)["public"] in (keys / "public" / f"{name}.key").read_text()
        assert _values(bundle / "coordinator.pub") == {"public": coordinator["public"]}
        text = "".join(p.read_text() for p in bundle.rglob("*") if p.is_file())
        assert coordinator["secret"] not in text
        assert _values(keys / "nodes" / f"{other}.key")["secret"] not in text


def test_bundles_follow_a_replaced_coordinator_key_and_are_made_for_an_older_folder(tmp_path):
    keys = tmp_path / "keys"
    assert main(["keys", "-o", str(keys), "--node", "n1", "--node", "n2"]) == 0
    shutil.rmtree(keys / "bundles")  # a folder made before bundles existed
    assert main(["keys", "-o", str(keys), "--keep-existing"]) == 0
    assert _files(keys / "bundles" / "n2") == {"coordinator.pub", "nodes/n2.key"}
    assert main(["keys", "-o", str(keys), "--force", "--node", "n1"]) == 0
    new = _values(keys / "coordinator.key")["public"]
    for name in ("n1", "n2"):  # n2 was not named: its bundle gets the new key all the same
        assert _values(keys / "bundles" / name / "coordinator.pub")["public"] == new


def _node(port: int, keys: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vastray.cli", "node", "--coordinator",
                             f"tcp://127.0.0.1:{port}", "--timeout", "30", "--keys", str(keys),
                             *extra], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _reap(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    if proc.stderr is not None and not proc.stderr.closed:
        proc.stderr.close()


def test_a_revoked_host_holding_only_its_bundle_cannot_join(store, tmp_path):
    keys = tmp_path / "keys"
    assert main(["keys", "-o", str(keys), "--node", "n1", "--node", "n2"]) == 0
    for name in ("n1", "n2"):  # each host is given its own bundle, and nothing else
        shutil.copytree(keys / "bundles" / name, tmp_path / f"host-{name}" / "vastray-keys")
    (keys / "public" / "n2.key").unlink()  # n2 is revoked
    port, out = free_port(), tmp_path / "x.exr"
    started = []
    coordinator = subprocess.Popen(
        [sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o", str(out), *SMALL,
         "--nodes", "1", "--listen", f"127.0.0.1:{port}", "--keys", str(keys),
         "--node-timeout", "60"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    started.append(coordinator)
    try:
        n2_bundle = tmp_path / "host-n2" / "vastray-keys"
        started.append(n2 := _node(port, n2_bundle))  # its own key: off the allow-list
        _, log = n2.communicate(timeout=60)
        assert n2.returncode != 0 and b"authentication" in log, log
        started.append(posing := _node(port, n2_bundle, "--key-name", "n1"))  # n1's: not there
        _, log = posing.communicate(timeout=60)
        assert posing.returncode == 2 and b"no key for node 'n1'" in log, log
        assert b"holds the key of 'n2' only" in log and b"Traceback" not in log, log
        started.append(n1 := _node(port, tmp_path / "host-n1" / "vastray-keys"))
        _, err = coordinator.communicate(timeout=120)
        _, n1_log = n1.communicate(timeout=60)
        assert coordinator.returncode == 0, err
        assert n1.returncode == 0 and b"joined" in n1_log, n1_log
        assert b"not on the allow-list" in err, err
    finally:
        for proc in started:
            _reap(proc)
    _assert_reference_image(store, out, tmp_path)


@pytest.fixture
def local_ssh(tmp_path):
    script = tmp_path / "local-ssh"
    script.write_text(LOCAL_SSH)
    script.chmod(0o755)
    return str(script)


def _launch(store, tmp_path: Path, local_ssh: str, *extra: str) -> int:
    (tmp_path / "hosts").write_text(f"alpha python={sys.executable}\n")
    return main(["launch", "--hosts", str(tmp_path / "hosts"), "--advertise", "127.0.0.1",
                 "--ssh", local_ssh, "--logs", str(tmp_path / "logs"), str(store.path), "-o",
                 str(tmp_path / "o.exr"), "--keys", str(tmp_path / "keys"), *SMALL,
                 "--node-timeout", "30", "--quiet", *extra])


def test_launch_starts_each_node_with_the_bundle_its_host_was_given(store, tmp_path, local_ssh):
    assert main(["keys", "-o", str(tmp_path / "keys"), "--node", "alpha"]) == 0
    given = tmp_path / "alpha-home" / "vastray-keys"
    shutil.copytree(tmp_path / "keys" / "bundles" / "alpha", given)
    shutil.rmtree(tmp_path / "keys" / "bundles")  # the node can only have used the copy
    assert _launch(store, tmp_path, local_ssh, "--node-keys", str(given)) == 0
    _assert_reference_image(store, tmp_path / "o.exr", tmp_path)


def test_launch_without_the_hosts_bundle_names_it_before_any_ssh(store, tmp_path, local_ssh,
                                                                 capsys):
    assert main(["keys", "-o", str(tmp_path / "keys"), "--node", "alpha"]) == 0
    shutil.rmtree(tmp_path / "keys" / "bundles")  # a folder made before bundles existed
    capsys.readouterr()
    assert _launch(store, tmp_path, local_ssh) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no bundle for node 'alpha'" in err[0], err
    assert "--keep-existing" in err[0]
    assert not (tmp_path / "logs").exists() and not (tmp_path / "o.exr").exists()
