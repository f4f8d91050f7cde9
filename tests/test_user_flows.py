"""The product as a user runs it: the installed CLI in a subprocess, from a folder that is not the
repository, without ``--quiet``: outputs, formats, reports, file modes, refusals before work,
and clean-up on SIGTERM."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vastray.preflight import MemoryEstimate, check_memory, estimate_memory
from vastray.render.film import FILM_BYTES_PER_PIXEL
from vastray.render.imageio import read_exr, read_image, write_exr
from vastray.scene.errors import InputError
from vastray.scene.store import is_store
from vastray.transport.keys import COORDINATOR_KEY

from scenes import bumpy_scene, child_pids, free_port, write_store

SMALL = ["--width", "32", "--height", "24", "--spp", "2", "--shadow-samples", "2"]


def vastray(*args, cwd: Path, umask: int | None = None, timeout: float = 120):
    """Run the installed CLI as a user would: ``python -m vastray.cli`` in ``cwd``."""
    def set_umask():
        os.umask(umask)

    return subprocess.run([sys.executable, "-m", "vastray.cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout,
                          preexec_fn=None if umask is None else set_umask)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("flows") / "s.store", bumpy_scene(), grid=(2, 2, 1))


# (spec-ooc alone and image on nodes: every domain cached, the loop without occupancy masks;
# every scheduler the CLI offers, each through its own summary line)
@pytest.mark.parametrize("how", [[], ["--cache", "25%", "--scheduler", "spec-ooc"],
                                 ["--scheduler", "spec-ooc"],
                                 ["--scheduler", "image", "--cache", "1"],
                                 ["--nodes", "2", "--scheduler", "image"],
                                 ["--nodes", "2", "--scheduler", "async"],
                                 ["--nodes", "2", "--scheduler", "domain"],
                                 ["--nodes", "2", "--scheduler", "dynamic"],
                                 ["--nodes", "2", "--scheduler", "spec-insitu"],
                                 ["--scheduler", "reference"],
                                 ["--nodes", "2", "--scheduler", "temporal"]])
def test_every_render_exits_zero_without_quiet_and_names_its_files(store, tmp_path, how):
    ref = tmp_path / "ref.exr"
    assert vastray("render", store.path, "-o", ref, *SMALL, "--quiet", cwd=tmp_path).returncode == 0
    out = vastray("render", store.path, "-o", "a.exr", "--png", "a.png", "--report", "a.json",
                  "--reference", ref, *SMALL, *how, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("wrote a.exr, a.png, a.json (32x24"), last
    assert "MSE 0, PSNR inf dB" in last
    report = json.loads((tmp_path / "a.json").read_text(), parse_constant=_reject)
    assert report["error"]["psnr_db"] is None and report["error"]["mse"] == 0
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), read_exr(ref))


def _reject(name):
    raise AssertionError(f"report holds {name}: not strict JSON")


def test_output_format_follows_the_extension(store, tmp_path):
    for name in ("i.exr", "i.png", "i.pfm", "i.hdr"):
        out = vastray("render", store.path, "-o", name, *SMALL, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
    exr = read_exr(tmp_path / "i.exr")
    assert (tmp_path / "i.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(read_image(tmp_path / "i.pfm"), exr)
    assert (tmp_path / "i.hdr").read_bytes().startswith(b"#?RADIANCE\n")


@pytest.mark.parametrize("case", ["unknown_extension", "folder", "png_option", "same_file",
                                  "huge", "camera_on_target", "unmatched_object"])
def test_refused_before_any_work_with_one_line_and_no_file(store, tmp_path, case):
    args = ["render", store.path, "-o", "out.exr", *SMALL]
    if case == "unknown_extension":
        args[3] = "out.tif"
    elif case == "folder":
        (tmp_path / "dir").mkdir()
        args[3] = "dir"
    elif case == "png_option":
        args += ["--png", "preview.jpg"]
    elif case == "same_file":
        args += ["--report", "out.exr"]
    elif case == "huge":
        args += ["--width", "200000", "--height", "200000"]
    elif case == "camera_on_target":
        (tmp_path / "s.toml").write_text("[camera]\nposition = [1, 2, 3]\nlook_at = [1, 2, 3]\n")
        args += ["--scene", "s.toml"]
    elif case == "unmatched_object":
        (tmp_path / "s.toml").write_text('[[object]]\nfile = "wall.obj"\n')
        args += ["--scene", "s.toml"]
    start = time.monotonic()
    out = vastray(*args, cwd=tmp_path)
    assert time.monotonic() - start < 20  # refused up front, not after the frame
    assert out.returncode == 2
    err = out.stderr.strip()
    assert err.startswith("vastray render: error:") and len(err.splitlines()) == 1, err
    assert not [p for p in tmp_path.iterdir() if p.is_file() and p.suffix != ".toml"]
    if case == "huge":
        assert "200000x200000" in err and "available" in err


def test_memory_estimate_refuses_what_does_not_fit():
    estimate = estimate_memory(20000, 20000, 65536, 16)
    assert estimate.film == 20000 * 20000 * FILM_BYTES_PER_PIXEL  # the film's own state
    with pytest.raises(InputError, match=r"needs about .* GiB .* only 6\.3 GiB of the 7\.5 GiB "
                                         r"available may be used"):
        check_memory(estimate, 20000, 20000, available=8_000_000_000)
    check_memory(MemoryEstimate(1000, 1000, 1000), 10, 10, available=10_000)


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_outputs_and_stores_respect_the_umask(tmp_path, umask):
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert vastray("partition", mesh, "-o", "m.store", cwd=tmp_path, umask=umask).returncode == 0
    out = vastray("render", "m.store", "-o", "m.exr", "--png", "m.png", "--report", "m.json",
                  *SMALL, cwd=tmp_path, umask=umask)
    assert out.returncode == 0, out.stderr
    for name in ("m.exr", "m.png", "m.json", "m.store/manifest.json"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
    assert (tmp_path / "m.store").stat().st_mode & 0o777 == 0o777 & ~umask


def test_partition_force_replaces_only_a_store(tmp_path):
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    user = tmp_path / "thesis"
    user.mkdir()
    (user / "chapter1.tex").write_text("precious")
    out = vastray("partition", mesh, "-o", user, "--force", cwd=tmp_path)
    assert out.returncode == 2 and "not a vastray store" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    assert (user / "chapter1.tex").read_text() == "precious"
    plain = tmp_path / "notes.txt"
    plain.write_text("keep me")
    out = vastray("partition", mesh, "-o", plain, "--force", cwd=tmp_path)
    assert out.returncode == 2 and "not a folder" in out.stderr
    assert "Traceback" not in out.stderr and plain.read_text() == "keep me"
    assert vastray("partition", mesh, "-o", "m.store", cwd=tmp_path).returncode == 0
    out = vastray("partition", mesh, "-o", "m.store", cwd=tmp_path)
    assert out.returncode == 2 and "--force" in out.stderr
    assert vastray("partition", mesh, "-o", "m.store", "--force", cwd=tmp_path).returncode == 0
    assert is_store(tmp_path / "m.store")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no leftovers


def test_version_and_help_teach(tmp_path):
    out = vastray("--version", cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.startswith("vastray ")
    out = vastray("render", "--help", cwd=tmp_path)
    assert ".pfm" in out.stdout and "built-in scene" in out.stdout
    assert "../shared" not in vastray("partition", "--help", cwd=tmp_path).stdout


def _children(pid: int) -> list[int]:
    return child_pids(pid)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def _start_node_render(store, tmp_path) -> tuple[subprocess.Popen, list[int]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o", "x.exr",
         "--nodes", "2", "--scheduler", "async", "--width", "400", "--height", "300",
         "--spp", "64"], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    nodes: list[int] = []
    while len(nodes) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
        nodes = _children(proc.pid)
    assert len(nodes) == 2, "the coordinator did not start two nodes"
    time.sleep(2.0)  # let them join and start rendering
    return proc, nodes


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig, repeated", [(signal.SIGTERM, False), (signal.SIGTERM, True),
                                           (signal.SIGKILL, False)])
def test_a_stopped_coordinator_leaves_no_node_behind(store, tmp_path, sig, repeated):
    # repeated: `timeout` signals the command, then its process group, the command included,
    # so a second SIGTERM can land in the clean-up the first started
    proc, nodes = _start_node_render(store, tmp_path)
    proc.send_signal(sig)
    deadline = time.monotonic() + 10
    while repeated and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=10)
    deadline = time.monotonic() + 5
    while any(_alive(n) for n in nodes) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(n) for n in nodes), "a node outlived its coordinator by 5 s"
    if sig == signal.SIGTERM:
        assert proc.returncode == 143
        # the progress bar's line, then one line: no asyncio task or traceback reported
        assert err.decode().strip().splitlines()[-1].startswith("vastray render: terminated")
        assert "Traceback" not in err.decode() and "Task" not in err.decode(), err.decode()
    if sig == signal.SIGTERM and (tmp_path / "x.exr").exists():
        # a pass had finished: the image of the passes done, with the checkpoint to go on
        assert (tmp_path / "x.exr.checkpoint.npz").exists()
        assert "the passes done kept" in err.decode() and "--resume" in err.decode()
    else:
        assert not (tmp_path / "x.exr").exists()
        assert not (tmp_path / "x.exr.checkpoint.npz").exists()


def test_a_remote_node_exits_when_its_coordinator_goes_silent(store, tmp_path):
    # A node started elsewhere (no parent-death signal) notices the heartbeat stop.
    port = free_port()
    coordinator = subprocess.Popen(
        [sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o", "x.exr",
         "--nodes", "1", "--listen", f"127.0.0.1:{port}", "--width", "400", "--height", "300",
         "--spp", "64"], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    node = subprocess.Popen([sys.executable, "-m", "vastray.cli", "node", "--coordinator",
                             f"tcp://127.0.0.1:{port}", "--timeout", "60"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = bytearray()

    def read_stderr():
        while chunk := coordinator.stderr.read1(4096):
            err.extend(chunk)

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    try:
        # the coordinator is killed once the node has joined (a fixed wait of 4 s lost that
        # race on a busy machine, where a node's start takes seconds)
        deadline = time.monotonic() + 60
        while b"node 0 joined" not in err and time.monotonic() < deadline:
            time.sleep(0.1)
        assert node.poll() is None, node.stderr.read().decode()
        coordinator.kill()
        coordinator.wait(timeout=15)
        reader.join(timeout=15)
        _, log = node.communicate(timeout=15)
        assert "joined" in log.decode() and "lost the coordinator" in log.decode(), log
        assert b"waiting for 1 node(s)" in err and b"node 0 joined" in err, err.decode()
    finally:
        for p in (node, coordinator):
            _reap(p)


def test_node_with_other_keys_hears_authentication_failed(store, tmp_path):
    # its own key, but from another folder: it expects another coordinator key, and the
    # coordinator logs the failed handshake (no ZAP request is ever made for it)
    assert vastray("keys", "-o", "keys", "--node", "n", cwd=tmp_path).returncode == 0
    assert vastray("keys", "-o", "other", "--node", "n", cwd=tmp_path).returncode == 0
    port = free_port()
    node = subprocess.Popen([sys.executable, "-m", "vastray.cli", "node", "--coordinator",
                             f"tcp://127.0.0.1:{port}", "--timeout", "30", "--keys",
                             str(tmp_path / "other"), "--key-name", "n"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        out = vastray("render", store.path, "-o", "x.exr", *SMALL, "--nodes", "1", "--listen",
                      f"127.0.0.1:{port}", "--keys", "keys", "--node-timeout", "4", cwd=tmp_path)
        assert out.returncode == 3
        assert "no node joined within 4 s" in out.stderr, out.stderr
        assert "failed before authentication" in out.stderr, out.stderr
        _, log = node.communicate(timeout=20)
        assert node.returncode != 0
        assert "authentication" in log.decode(), log
    finally:
        _reap(node)


def _reap(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    if proc.stderr is not None and not proc.stderr.closed:
        proc.stderr.close()


def test_compare_of_identical_images_says_inf(store, tmp_path):
    write_exr(tmp_path / "ref.exr", np.zeros((24, 32, 3), np.float32))
    out = vastray("compare", tmp_path / "ref.exr", tmp_path / "ref.exr", cwd=tmp_path)
    assert out.returncode == 0 and "psnr_db=inf" in out.stdout


def test_keys_are_never_replaced_silently(tmp_path):
    assert vastray("keys", "-o", "k", cwd=tmp_path).returncode == 0
    key = tmp_path / "k" / COORDINATOR_KEY
    before = key.read_bytes()
    out = vastray("keys", "-o", "k", cwd=tmp_path)
    assert out.returncode == 2 and "--force" in out.stderr
    assert key.read_bytes() == before
    assert vastray("keys", "-o", "k", "--keep-existing", cwd=tmp_path).returncode == 0
    assert key.read_bytes() == before  # docker compose's keys service, run again
    assert vastray("keys", "-o", "k", "--force", cwd=tmp_path).returncode == 0
    assert key.read_bytes() != before


def test_keys_into_a_file_is_refused_in_one_line(tmp_path):
    (tmp_path / "afile").write_text("mine")
    out = vastray("keys", "-o", "afile", "--node", "n", cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "afile: is a file" in out.stderr, out.stderr
    assert (tmp_path / "afile").read_text() == "mine"


def test_per_node_keys_admit_their_nodes_and_a_revoked_one_is_refused_and_logged(store,
                                                                                 tmp_path):
    assert vastray("keys", "-o", "keys", "--node", "alpha", "--node", "beta",
                   cwd=tmp_path).returncode == 0
    port = free_port()

    def node(*key_name):
        return subprocess.Popen([sys.executable, "-m", "vastray.cli", "node", "--coordinator",
                                 f"tcp://127.0.0.1:{port}", "--timeout", "30", "--keys",
                                 str(tmp_path / "keys"), *key_name],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    alpha = beta = anonymous = None
    coordinator = subprocess.Popen(
        [sys.executable, "-m", "vastray.cli", "render", str(store.path), "-o", "x.exr", *SMALL,
         "--nodes", "1", "--listen", f"127.0.0.1:{port}", "--keys", "keys",
         "--node-timeout", "40"], cwd=tmp_path, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE)
    try:
        time.sleep(3.0)  # the coordinator listens, its allow-list read with beta on it
        (tmp_path / "keys" / "public" / "beta.key").unlink()  # beta is shut out, at once
        beta = node("--key-name", "beta")
        # the node's own --timeout (30 s) decides; this wait only outlasts it (a refused
        # handshake reached a node on a busy CI machine after more than 30 s of its start-up)
        _, beta_log = beta.communicate(timeout=60)
        assert beta.returncode != 0 and b"authentication" in beta_log, beta_log
        # the same host without --key-name: its host name's key, which it has not
        anonymous = node()
        _, anonymous_log = anonymous.communicate(timeout=60)
        assert anonymous.returncode == 2 and b"no key for node" in anonymous_log, anonymous_log
        alpha = node("--key-name", "alpha")
        _, err = coordinator.communicate(timeout=60)
        _, alpha_log = alpha.communicate(timeout=30)
        assert coordinator.returncode == 0, err
        assert alpha.returncode == 0 and b"joined" in alpha_log, alpha_log
        assert b"the coordinator refused a connection from 127.0.0.1" in err, err
        assert b"not on the allow-list" in err, err
        assert (tmp_path / "x.exr").is_file()
    finally:
        for proc in (beta, anonymous, coordinator, alpha):
            if proc is not None:
                _reap(proc)


def test_memory_limit_bounds_the_cache_or_refuses_up_front(store, tmp_path):
    from vastray.preflight import (
        LIMIT_BASE_MARGIN,
        domain_build_bytes,
        domain_footprints,
        estimate_memory,
    )

    out = vastray("render", store.path, "-o", "x.exr", *SMALL, "--memory-limit", "64K",
                  cwd=tmp_path)
    assert out.returncode == 2 and "--memory-limit" in out.stderr and "too small" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.exr").exists()
    # room for the film, paths and outputs plus the two largest domains: the cache holds two
    two = sum(sorted(domain_footprints(store.domains))[-2:])
    # shadow rays per hit: one to the default directional light, --shadow-samples 2 to its sky;
    # the run reads --reference, which the estimate counts. One thread: the reference
    # renderer then holds the same 1536 paths at once as spec-ooc (with two it would hold half
    # of them, which leaves room for every domain of this tiny store)
    limit = (estimate_memory(32, 24, 32 * 24 * 2, 1 + 2, reference=True).total
             + LIMIT_BASE_MARGIN + domain_build_bytes(store.domains, reads_ahead=True) + two + 1)
    ref = vastray("render", store.path, "-o", "ref.exr", *SMALL, cwd=tmp_path)
    assert ref.returncode == 0
    out = vastray("render", store.path, "-o", "x.exr", "--report", "x.json", *SMALL,
                  "--memory-limit", str(limit), "--reference", "ref.exr", "--threads", "1",
                  cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "x.json").read_text())
    assert report["counters"]["cache_capacity"] == 2 < len(store.domains)
    assert report["scheduler"] == "spec-ooc"  # auto: the domains no longer all fit
    assert report["error"]["mse"] == 0
    assert report["counters"]["peak_rss_bytes"] > 0


def test_the_smallest_memory_limit_named_is_the_smallest_accepted(store, tmp_path):
    """A limit too small names the smallest that fits; that one is accepted and one MiB less
    is refused naming the same. (It once named a limit worked out for the in-core render,
    which the out-of-core plan then refused, naming a larger one.)"""
    def smallest(limit: str) -> int | None:
        out = vastray("render", store.path, "-o", "x.exr", *SMALL, "--memory-limit", limit,
                      cwd=tmp_path)
        found = re.search(r"the smallest that fits is --memory-limit (\d+)M", out.stderr)
        assert (out.returncode == 0) == (found is None), out.stderr
        return None if found is None else int(found.group(1))

    named = smallest("1K")
    assert named is not None
    assert smallest(f"{named}M") is None and (tmp_path / "x.exr").is_file()
    assert smallest(f"{named - 1}M") == named


def test_generate_and_info_as_a_user_runs_them(tmp_path):
    out = vastray("generate", "rm", "-o", "g.store", "--resolution", "24", "--grid", "2x1x1",
                  cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("g.store: rm at 24^3") and "2x1x1 grid" in out.stdout
    info = vastray("info", "g.store", cwd=tmp_path)
    assert info.returncode == 0 and "attributes: scalars" in info.stdout, info.stdout


def test_generate_with_a_seed_and_simplify_again_with_force_say_what_they_wrote(tmp_path):
    out = vastray("generate", "rm", "-o", "g.store", "--resolution", "24", "--grid", "2x2x1",
                  "--seed", "3", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("g.store: rm at 24^3") and "2x2x1 grid" in out.stdout
    first = vastray("simplify", "g.store", "--ratio", "0.2", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    again = vastray("simplify", "g.store", "--ratio", "0.2", cwd=tmp_path)
    assert again.returncode == 2 and "pass --force to replace it" in again.stderr
    forced = vastray("simplify", "g.store", "--ratio", "0.2", "--force", cwd=tmp_path)
    assert forced.returncode == 0, forced.stderr
    for run in (first, forced):
        assert run.stdout.startswith("g.store: simplified model of "), run.stdout
        assert "triangle rate" in run.stdout and "(asked 20.00%)" in run.stdout


def test_info_piped_into_head_ends_without_a_traceback(store, tmp_path):
    """`vastray info STORE | head -1`: the reader closes the pipe early."""
    info = subprocess.Popen([sys.executable, "-m", "vastray.cli", "info", str(store.path)],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    info.stdout.close()  # what head does once it has its lines: the next write fails
    with info.stderr:
        err = info.stderr.read().decode()
    assert info.wait(timeout=60) == 141
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


@pytest.mark.parametrize("args, says", [
    (["render", "-o", "a.exr", "--resolution", "0x0"], "--width W --height H"),
    (["render", "-o", "a.exr", "--wdth", "3"], "did you mean --width?"),
    (["render", "-o", "a.exr", "--width", "abc"], "--width: expected a whole number, got 'abc'"),
    (["render", "--spp", "4"], "required: -o/--output"),
    (["render", "-o", "a.exr", "--nodes", "1", "--listen", "127.0.0.1:abc"],
     "--listen: expected HOST:PORT with a port in 0..65535"),  # a traceback once
    (["render", "-o", "a.exr", "--nodes", "1", "--listen", "127.0.0.1:99999"],
     "--listen: expected HOST:PORT"),  # bound port 34463 and waited for nodes that never came
    (["render", "-o", "a.exr", "--integrator", "ao", "--shadow-samples", "0"],
     "--shadow-samples: must be at least 1"),  # a black image once
    (["render", "-o", "a.exr", "--cache", "%"], "--cache: expected N domains or P% of them"),
    (["render", "-o", "a.exr", "--spp", "1000000000", "--time-limit", "2"],
     "--spp: at most 1,048,576"),  # planned 6e7 passes up front: 6.5 GB, 39 s (1e12: never)
    (["data", "fetch", "--bogus"], "unrecognized arguments: --bogus"),
])
def test_argument_errors_are_two_lines_naming_the_command_and_the_fix(tmp_path, args, says):
    out = vastray(*args, cwd=tmp_path)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    prog = "vastray " + " ".join(a for a in args[:2] if not a.startswith("-"))
    assert len(lines) == 2, out.stderr
    assert lines[0].startswith(f"{prog}: error: ") and says in lines[0], lines
    assert lines[1] == f"(`{prog} --help` lists the options)"
    assert not list(tmp_path.iterdir())


def test_one_overwrite_rule_files_named_are_replaced_and_said_so_folders_need_force(store,
                                                                                     tmp_path):
    """The file a user names with -o/--png/--report is replaced, as renderers do, and the last
    line says so; a folder (a store, a key folder) is replaced only with --force."""
    first = vastray("render", store.path, "-o", "a.exr", "--report", "a.json", *SMALL,
                    cwd=tmp_path)
    assert first.returncode == 0 and "replaced" not in first.stderr
    again = vastray("render", store.path, "-o", "a.exr", "--report", "a.json", *SMALL,
                    cwd=tmp_path)
    assert again.returncode == 0
    assert again.stderr.strip().splitlines()[-1].endswith("; replaced the existing a.exr, a.json")
    for command in (["generate", "rm", "-o", "g.store", "--resolution", "12"],
                    ["keys", "-o", "keys"]):
        assert vastray(*command, cwd=tmp_path).returncode == 0
        refused = vastray(*command, cwd=tmp_path)
        assert refused.returncode == 2 and "--force" in refused.stderr, refused.stderr
        assert vastray(*command, "--force", cwd=tmp_path).returncode == 0


@pytest.mark.parametrize("case", ["checkpoint_on_output", "checkpoint_on_a_user_file",
                                  "checkpoint_in_store", "report_in_store", "image_in_store",
                                  "output_on_reference", "report_not_json"])
def test_a_render_never_writes_over_what_it_reads_or_keeps(tmp_path, case):
    """Each of these once succeeded and destroyed a file: a checkpoint written over the image,
    a user's notes or the store's manifest and then removed at the end; a report over the
    store's manifest (the store unreadable after); the output over its own --reference.
    Now each is refused before any work, in one line, and every file is as it was."""
    store = write_store(tmp_path / "s.store", bumpy_scene(), grid=(2, 1, 1))
    manifest = (store.path / "manifest.json").read_bytes()
    (tmp_path / "notes.txt").write_text("mine")
    write_exr(tmp_path / "ref.exr", np.ones((24, 32, 3), np.float32))
    reference = (tmp_path / "ref.exr").read_bytes()
    extra = {
        "checkpoint_on_output": ["-o", "out.exr", "--checkpoint", "out.exr"],
        "checkpoint_on_a_user_file": ["-o", "out.exr", "--checkpoint", "notes.txt",
                                      "--checkpoint-every", "0.001"],
        "checkpoint_in_store": ["-o", "out.exr", "--checkpoint", "s.store/manifest.json"],
        "report_in_store": ["-o", "out.exr", "--report", "s.store/manifest.json"],
        "image_in_store": ["-o", "s.store/out.exr"],
        "output_on_reference": ["-o", "ref.exr", "--reference", "ref.exr"],
        "report_not_json": ["-o", "out.exr", "--report", "out.npy"],
    }[case]
    out = vastray("render", "s.store", *extra, *SMALL, cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    err = out.stderr.strip()
    assert err.startswith("vastray render: error:") and len(err.splitlines()) == 1, err
    says = {"checkpoint_on_output": "--checkpoint names one of the render's outputs",
            "checkpoint_on_a_user_file": "exists and is not a vastray checkpoint",
            "output_on_reference": "is the --reference image",
            "report_not_json": "ending in .json"}.get(case, "is inside the store being rendered")
    assert says in err
    assert (store.path / "manifest.json").read_bytes() == manifest
    assert (tmp_path / "notes.txt").read_text() == "mine"
    assert (tmp_path / "ref.exr").read_bytes() == reference
    assert not (tmp_path / "out.exr").exists() and not (store.path / "out.exr").exists()


def test_a_damaged_npy_or_missing_checkpoint_is_one_line_not_a_traceback(tmp_path):
    good = np.zeros((24, 32, 3), np.float32)
    np.save(tmp_path / "good.npy", good)
    (tmp_path / "cut.npy").write_bytes((tmp_path / "good.npy").read_bytes()[:500])
    np.save(tmp_path / "objects.npy", np.array([{}], dtype=object), allow_pickle=True)
    write_exr(tmp_path / "good.exr", np.random.default_rng(1).random((24, 32, 3), np.float32))
    whole = (tmp_path / "good.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(whole[:len(whole) // 2])
    for name, says in (("cut.npy", "not a readable .npy image"),
                       ("objects.npy", "not a readable .npy image"),
                       ("cut.exr", "not a readable OpenEXR image")):  # and OpenEXR's own lines
        out = vastray("compare", "good.npy", name, cwd=tmp_path)
        err = out.stderr.strip()
        assert out.returncode == 2 and len(err.splitlines()) == 1 and not out.stdout, err
        assert err.startswith(f"vastray compare: error: {name}: {says}"), err
    out = vastray("render", "--resume", "missing.npz", cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip() == "vastray render: error: missing.npz: checkpoint not found"


@pytest.mark.parametrize("args, says", [
    (["--coordinator", ""], "node ?: error: --coordinator is empty"),  # a TypeError once
    (["--rendezvous", "binary.addr"],
     "node ?: error: binary.addr: cannot be read as a coordinator's address"),
])
def test_a_node_given_a_bad_address_says_so_in_one_line(tmp_path, args, says):
    (tmp_path / "binary.addr").write_bytes(b"\x00\xff\xfe")  # a UnicodeDecodeError once
    out = vastray("node", *args, "--timeout", "5", cwd=tmp_path)
    assert out.returncode == 2 and out.stderr.strip() == out.stderr.strip().splitlines()[0]
    assert out.stderr.startswith(says), out.stderr


def test_a_node_timeout_must_be_positive(tmp_path):
    out = vastray("node", "--coordinator", "tcp://127.0.0.1:1", "--timeout", "-3", cwd=tmp_path)
    assert out.returncode == 2 and "--timeout: must be a positive finite number" in out.stderr


def test_a_listening_coordinator_names_its_address_even_quiet(store, tmp_path):
    """With ``--listen HOST:0`` the waiting line is the one place the port is said: ``--quiet``
    once hid it, and the nodes could not be told where to join. A rendezvous file's folder
    is never created (it was, silently, by the write)."""
    out = vastray("render", store.path, "-o", "x.exr", *SMALL, "--nodes", "1", "--listen",
                  "127.0.0.1:0", "--rendezvous", "missing/job.addr", cwd=tmp_path)
    assert out.returncode == 2 and "--rendezvous's folder missing does not exist" in out.stderr
    assert not (tmp_path / "missing").exists()
    out = vastray("render", store.path, "-o", "x.exr", *SMALL, "--nodes", "1", "--listen",
                  "127.0.0.1:0", "--node-timeout", "2", "--quiet", cwd=tmp_path)
    assert out.returncode == 3  # no node came
    assert re.search(r"^waiting for 1 node\(s\) on tcp://127\.0\.0\.1:\d+$", out.stderr,
                     re.MULTILINE), out.stderr


def test_data_fetch_into_a_file_or_from_a_missing_mirror_is_one_line(tmp_path):
    (tmp_path / "file.txt").write_text("junk")
    (tmp_path / "empty").mkdir()
    for args, says in ((["-o", "file.txt", "--from", "empty"], "file.txt: -o is a file"),
                       (["-o", "s", "--from", "nope"], "nope: --from: no such folder")):
        out = vastray("data", "fetch", *args, cwd=tmp_path)
        err = out.stderr.strip()
        assert out.returncode == 2 and err.startswith("vastray data: error: "), err
        assert says in err and len(err.splitlines()) == 1, err
    assert (tmp_path / "file.txt").read_text() == "junk" and not (tmp_path / "s").exists()


@pytest.mark.parametrize("nodes, says", [(["../evil"], "node key name '../evil'"),
                                          (["a", "a"], "--node a is given twice")])
def test_keys_checks_every_name_before_writing_anything(tmp_path, nodes, says):
    """A bad name once left a key folder with a coordinator key; a repeated one a node on the
    allow-list without its bundle."""
    out = vastray("keys", "-o", "k", *[arg for n in nodes for arg in ("--node", n)],
                  cwd=tmp_path)
    assert out.returncode == 2 and says in out.stderr, out.stderr
    assert not (tmp_path / "k").exists()
