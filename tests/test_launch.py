"""`vastray launch`: host files, node start-up through an ssh-like command, log collection,
failure naming the host, and teardown. No SSH server runs here, so the remote shell is a local
``sh`` standing in for ``ssh HOST``: everything after the hop is the real thing."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from vastray.actors.launch import Host, read_hostfile
from vastray.cli import main
from vastray.render.imageio import read_exr
from vastray.scene.errors import InputError

from scenes import bumpy_scene, write_store

LOCAL_SHELL = "#!/bin/sh\n# stand-in for `ssh HOST CMD`: drop HOST, run CMD here\nshift\nexec sh -c \"$1\"\n"


@pytest.fixture
def local_ssh(tmp_path):
    script = tmp_path / "local-ssh"
    script.write_text(LOCAL_SHELL)
    script.chmod(0o755)
    return str(script)


def _assert_reference_image(store, out: Path, tmp_path: Path, spp: int = 2) -> None:
    """The launched render (24x18, ``spp``) equals the single-process render of the same
    settings (a black or partial image does not pass)."""
    reference = tmp_path / "reference.exr"
    assert main(["render", str(store.path), "-o", str(reference), "--width", "24", "--height",
                 "18", "--spp", str(spp), "--quiet"]) == 0
    expected = read_exr(reference)
    assert expected.max() > 0.05
    np.testing.assert_allclose(read_exr(out), expected, rtol=1e-6, atol=1e-6)


def test_hostfile_parsing(tmp_path):
    path = tmp_path / "hosts"
    path.write_text("# cluster\nn1\nn2 python=/opt/py slots=2  # two nodes\n\n")
    assert read_hostfile(path) == [Host("n1"), Host("n2", "/opt/py", 2), Host("n2", "/opt/py", 2)]
    path.write_text("n1 colour=blue\n")
    with pytest.raises(InputError, match="unknown option"):
        read_hostfile(path)
    path.write_text("# nothing\n")
    with pytest.raises(InputError, match="no hosts"):
        read_hostfile(path)


def test_launch_renders_on_hosts_and_collects_logs(tmp_path, local_ssh, capsys):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    main(["keys", "-o", str(tmp_path / "keys"), "--node", "alpha", "--node", "beta"])
    (tmp_path / "hosts").write_text(f"alpha python={sys.executable}\n"
                                    f"beta python={sys.executable} slots=2\n")
    out = tmp_path / "o.exr"
    args = ["launch", "--hosts", str(tmp_path / "hosts"), "--advertise", "127.0.0.1",
            "--ssh", local_ssh, "--logs", str(tmp_path / "logs"), str(store.path), "-o",
            str(out), "--keys", str(tmp_path / "keys"), "--width", "24", "--height", "18",
            "--spp", "2", "--node-timeout", "30"]  # as a user runs it: no --quiet
    assert main(args) == 0
    err = capsys.readouterr().err
    assert f"wrote {out}" in err.strip().splitlines()[-1]
    assert f"3 node(s) started; their logs are in {tmp_path / 'logs'}" in err
    _assert_reference_image(store, out, tmp_path)
    logs = sorted(p.name for p in (tmp_path / "logs").iterdir())
    assert logs == ["node0-alpha.log", "node1-beta.log", "node2-beta.log"]


def test_launch_failure_names_the_host_and_writes_nothing(tmp_path, local_ssh, capsys):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    main(["keys", "-o", str(tmp_path / "keys"), "--node", "alpha", "--node", "broken"])
    (tmp_path / "hosts").write_text(f"alpha python={sys.executable}\n"
                                    "broken python=/nonexistent/python\n")
    out = tmp_path / "o.exr"
    code = main(["launch", "--hosts", str(tmp_path / "hosts"), "--advertise", "127.0.0.1",
                 "--ssh", local_ssh, "--logs", str(tmp_path / "logs"), str(store.path), "-o",
                 str(out), "--keys", str(tmp_path / "keys"), "--node-timeout", "20"])  # no --quiet
    assert code != 0
    assert "broken" in capsys.readouterr().err
    assert not out.exists()


def test_launch_needs_a_key_for_every_host_before_any_ssh(tmp_path, capsys):
    main(["keys", "-o", str(tmp_path / "keys"), "--node", "alpha"])
    (tmp_path / "hosts").write_text("alpha\ngamma\n")
    code = main(["launch", "--hosts", str(tmp_path / "hosts"), "-o", str(tmp_path / "o.exr"),
                 "--keys", str(tmp_path / "keys"), "--logs", str(tmp_path / "logs"),
                 "--ssh", "false", "x.store"])
    assert code == 2
    assert "no key for node 'gamma'" in capsys.readouterr().err
    assert not (tmp_path / "logs").exists()  # no session was started


def test_launch_needs_keys(tmp_path, capsys):
    (tmp_path / "hosts").write_text("alpha\n")
    assert main(["launch", "--hosts", str(tmp_path / "hosts"), "-o", str(tmp_path / "o.exr"),
                 "x.store"]) != 0
    assert "--keys" in capsys.readouterr().err


@pytest.mark.parametrize("flag", [["--nodes", "4"], ["--listen", "0.0.0.0:5555"]])
def test_launch_refuses_the_options_it_sets_itself(tmp_path, capsys, flag):
    (tmp_path / "hosts").write_text("alpha\n")
    code = main(["launch", "--hosts", str(tmp_path / "hosts"), "-o", str(tmp_path / "o.exr"),
                 "--keys", str(tmp_path), "--logs", str(tmp_path / "logs"), "x.store", *flag])
    assert code == 2
    err = capsys.readouterr().err
    assert f"{flag[0]} is for `vastray render`" in err and "one node per HOSTFILE line" in err
    assert not (tmp_path / "logs").exists() and not (tmp_path / "o.exr").exists()


def test_launch_help_shows_where_the_logs_go(capsys):
    with pytest.raises(SystemExit):
        main(["launch", "--help"])
    assert "(default: vastray-logs)" in " ".join(capsys.readouterr().out.split())


@pytest.fixture
def sshd(tmp_path):
    """A real OpenSSH server on loopback, with a key made for this test only."""
    import shutil
    import socket
    import subprocess
    import time

    sshd_bin = shutil.which("sshd") or "/usr/sbin/sshd"
    if not Path(sshd_bin).exists() or shutil.which("ssh") is None:
        pytest.skip("needs OpenSSH (sshd and ssh) installed")
    import os

    if os.geteuid() != 0:
        pytest.skip("sshd needs root to run here")
    keys = tmp_path / "ssh"
    keys.mkdir()
    for name in ("host", "user"):
        subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(keys / name)],
                       check=True)
    (keys / "authorized_keys").write_text((keys / "user.pub").read_text())
    keys.chmod(0o700)
    (keys / "authorized_keys").chmod(0o600)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    Path("/run/sshd").mkdir(exist_ok=True)
    config = keys / "sshd_config"
    config.write_text(f"Port {port}\nListenAddress 127.0.0.1\nHostKey {keys / 'host'}\n"
                      f"AuthorizedKeysFile {keys / 'authorized_keys'}\nPasswordAuthentication no\n"
                      "PermitRootLogin prohibit-password\nStrictModes no\nUsePAM no\n"
                      f"PidFile {keys / 'sshd.pid'}\n")
    server = subprocess.Popen([sshd_bin, "-D", "-e", "-f", str(config)],
                              stderr=subprocess.DEVNULL)
    for _ in range(50):
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.1)
    yield (f"ssh -i {keys / 'user'} -p {port} -o BatchMode=yes -o StrictHostKeyChecking=no "
           "-o UserKnownHostsFile=/dev/null -o LogLevel=ERROR -tt")
    server.terminate()
    server.wait()


def test_launch_over_a_real_ssh_server(tmp_path, sshd):
    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    main(["keys", "-o", str(tmp_path / "keys"), "--node", "127.0.0.1"])
    (tmp_path / "hosts").write_text(f"127.0.0.1 python={sys.executable} slots=2\n")
    out = tmp_path / "o.exr"
    assert main(["launch", "--hosts", str(tmp_path / "hosts"), "--advertise", "127.0.0.1",
                 "--ssh", sshd, "--logs", str(tmp_path / "logs"), str(store.path), "-o",
                 str(out), "--keys", str(tmp_path / "keys"), "--width", "24", "--height", "18",
                 "--spp", "2", "--node-timeout", "30", "--scheduler", "async", "--quiet"]) == 0
    _assert_reference_image(store, out, tmp_path)


def test_launch_survives_a_node_killed_mid_frame(tmp_path, local_ssh, capsys):
    # kill -9 of the node that got rank 2: its session exits, the coordinator does not wait
    # for it again, and the two others regroup and render the frame. 16 spp in tiles of 50
    # paths keep the frame going for seconds after the kill (at 2 spp it could end first).
    import os
    import re
    import signal
    import threading
    import time

    store = write_store(tmp_path / "s", bumpy_scene(), kd=6)
    main(["keys", "-o", str(tmp_path / "keys"), "--node", "alpha", "--node", "beta"])
    (tmp_path / "hosts").write_text(f"alpha python={sys.executable}\n"
                                    f"beta python={sys.executable} slots=2\n")
    logs, out, hit = tmp_path / "logs", tmp_path / "o.exr", []

    def strike():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not hit:
            texts = {p: p.read_text(errors="replace") for p in logs.glob("*.log")}
            if len(texts) == 3 and all("joined" in t for t in texts.values()):
                time.sleep(1.0)
                victim = next(p for p, t in texts.items() if "as node 2 of 3" in t)
                for pid in _writing_to(victim):  # the node (and its stand-in ssh session)
                    os.kill(pid, signal.SIGKILL)
                    hit.append(pid)
                return
            time.sleep(0.05)

    striker = threading.Thread(target=strike)
    striker.start()
    try:
        code = main(["launch", "--hosts", str(tmp_path / "hosts"), "--advertise", "127.0.0.1",
                     "--ssh", local_ssh, "--logs", str(logs), str(store.path), "-o", str(out),
                     "--keys", str(tmp_path / "keys"), "--width", "24", "--height", "18",
                     "--spp", "16", "--node-timeout", "30", "--heartbeat-timeout", "5",
                     "--scheduler", "async", "--max-samples-in-flight", "50"])
    finally:
        striker.join()
    err = capsys.readouterr().err
    assert hit, "the test found no node 2 to kill"
    assert code == 0, err
    assert re.search(r"node on \S+ \(node \d\) exited with code \S+: .*; rendering the frame "
                     r"again on the 2 other node\(s\) once they have joined again", err), err
    _assert_reference_image(store, out, tmp_path, spp=16)


def _writing_to(log: Path) -> list[int]:
    """Pids of the processes whose stderr is ``log``."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and (proc / "fd" / "2").readlink() == log.resolve():
                found.append(int(proc.name))
        except OSError:
            continue
    return found
