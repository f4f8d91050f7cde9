"""Damaged checkpoints, full disks and killed writers (issue 37, item 5): a damaged --resume
file is one line naming it, never a traceback; an output the disk cannot take never loses the
finished render, which goes to a rescue folder named in one line; temporaries of killed
writes are removed by the next render. Real CLI processes, real files, a real full tmpfs."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vastray.render.imageio import read_image

from scenes import POINT_AND_SKY_TOML, bumpy_scene, said_lines, write_store

SIZE = ["--width", "24", "--height", "16"]


def _cli(*args: str, tmpdir: Path | None = None) -> subprocess.CompletedProcess:
    """``vastray ARGS`` as users run it (no --quiet), with its temp folder at ``tmpdir``."""
    env = dict(os.environ)
    if tmpdir is not None:
        tmpdir.mkdir(exist_ok=True)
        env["TMPDIR"] = str(tmpdir)
    return subprocess.run([sys.executable, "-m", "vastray", *args], capture_output=True,
                          text=True, timeout=600, env=env)


def _one_line(run: subprocess.CompletedProcess) -> str:
    """The failed run's stderr, checked to be one line and no traceback."""
    assert run.returncode != 0, run.stderr
    assert "Traceback" not in run.stderr, run.stderr
    lines = said_lines(run.stderr)  # a busy machine's render may show its bar first
    assert len(lines) == 1, run.stderr
    return lines[0]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A small store, its scene, the render arguments and a normal render of 4 and 8 spp."""
    root = tmp_path_factory.mktemp("damaged")
    store = write_store(root / "kd4", bumpy_scene(), kd=4)
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    common = [str(store.path), "--scene", str(root / "scene.toml"), *SIZE]
    for spp in ("4", "8"):
        run = _cli("render", *common, "--spp", spp, "-o", str(root / f"whole{spp}.exr"),
                   "--png", str(root / f"whole{spp}.png"))
        assert run.returncode == 0, run.stderr
    return root, common


@pytest.fixture(scope="module")
def checkpoint(scene) -> bytes:
    """The bytes of a checkpoint of the 4-spp render (from which 8 spp resumes), written by
    the render command's own pieces."""
    from vastray.cli import build_parser
    from vastray.execute import start_progression
    from vastray.planning import plan_render
    from vastray.request import RenderRequest

    root, common = scene
    args = build_parser().parse_args(["render", *common, "--spp", "4", "--quiet", "-o",
                                      str(root / "part.exr")])
    plan = plan_render(RenderRequest.from_namespace(args))
    progression, checkpoints = start_progression(plan.request, plan, [root / "part.exr"])
    plan.render_one(plan.config, plan.settings, progression=progression)
    assert checkpoints.write()
    return checkpoints.path.read_bytes()


def _flip(data: bytes, offset: int) -> bytes:
    """``data`` with one bit of the byte at ``offset`` flipped."""
    damaged = bytearray(data)
    damaged[offset] ^= 1 << (offset % 8)
    return bytes(damaged)


def _damaged(kind: str, good: bytes) -> bytes:
    if kind == "empty":
        return b""
    if kind == "truncated-half":
        return good[:len(good) // 2]
    if kind == "truncated-last-byte":
        return good[:-1]
    if kind == "not-a-zip":
        return b"P3\n2 2\n255\n" + b"0 0 0 " * 4
    if kind == "foreign-npz":
        import io

        buffer = io.BytesIO()
        np.savez(buffer, sum=np.zeros((16, 24, 3)))
        return buffer.getvalue()
    where = float(kind.split(":")[1])
    return _flip(good, int(where * len(good)) if where >= 0 else len(good) + int(where))


DAMAGES = ["empty", "truncated-half", "truncated-last-byte", "not-a-zip", "foreign-npz",
           # bit flips through the file: zip header, arrays, central directory, seal
           *(f"flip:{where}" for where in (0.0, 0.01, 0.2, 0.5, 0.8, 0.97, -120, -80, -50, -1))]


def test_an_intact_checkpoint_resumes_to_the_uninterrupted_image(scene, checkpoint, tmp_path):
    # the control for the damaged ones below: the same file, unharmed, resumes
    root, common = scene
    ckpt = tmp_path / "run.checkpoint.npz"
    ckpt.write_bytes(checkpoint)
    run = _cli("render", *common, "--spp", "8", "-o", str(tmp_path / "run.exr"), "--resume",
               str(ckpt))
    assert run.returncode == 0, run.stderr
    np.testing.assert_array_equal(read_image(tmp_path / "run.exr"), read_image(root / "whole8.exr"))


@pytest.mark.parametrize("kind", DAMAGES)
def test_a_damaged_checkpoint_is_one_line_naming_it(scene, checkpoint, tmp_path, kind):
    root, common = scene
    ckpt = tmp_path / "run.checkpoint.npz"
    data = _damaged(kind, checkpoint)
    ckpt.write_bytes(data)
    run = _cli("render", *common, "--spp", "8", "-o", str(tmp_path / "run.exr"), "--resume",
               str(ckpt))
    line = _one_line(run)
    assert str(ckpt) in line, line
    assert ckpt.read_bytes() == data  # the user's file is left as it was
    assert not (tmp_path / "run.exr").exists()


def test_every_flipped_byte_of_a_checkpoint_is_refused(checkpoint, tmp_path):
    # in process, over the whole file: a flip anywhere is an InputError naming the file,
    # never another exception and never a silently different film
    from vastray.checkpoint import read_checkpoint
    from vastray.scene.errors import InputError

    ckpt = tmp_path / "c.npz"
    ckpt.write_bytes(checkpoint)
    with np.load(ckpt) as data:
        identity = json.loads(str(data["meta"]))["identity"]
    read_checkpoint(ckpt, identity)  # the intact file reads
    offsets = sorted({*range(0, len(checkpoint), 29), *range(len(checkpoint) - 400,
                                                             len(checkpoint))})
    for offset in offsets:
        ckpt.write_bytes(_flip(checkpoint, offset))
        with pytest.raises(InputError, match=re.escape(str(ckpt))):
            read_checkpoint(ckpt, identity)


@pytest.fixture
def full_disk(tmp_path):
    """A 64 KiB tmpfs mounted at ``tmp_path/full`` and filled to the last byte."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs (a real full disk) needs root")
    mount = tmp_path / "full"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {done.stderr.strip()}")
    try:
        with contextlib.suppress(OSError), open(mount / "filler", "wb", buffering=0) as fh:
            while True:
                fh.write(b"\0" * 4096)
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


@pytest.mark.parametrize("which", ["-o", "--png", "--report"])
def test_an_output_on_a_full_disk_keeps_the_render_in_a_rescue_folder(scene, full_disk,
                                                                      tmp_path, which):
    root, common = scene
    targets = {"-o": tmp_path / "run.exr", "--png": tmp_path / "run.png",
               "--report": tmp_path / "run.json"}
    targets[which] = full_disk / targets[which].name
    run = _cli("render", *common, "--spp", "4",
               *(arg for option, path in targets.items() for arg in (option, str(path))),
               tmpdir=tmp_path / "tmp")
    line = _one_line(run)
    assert str(targets[which]) in line and "No space left on device" in line, line
    kept = Path(re.search(r"written to (\S+) instead", line).group(1))
    assert kept.parent == tmp_path / "tmp"  # the temp folder
    np.testing.assert_array_equal(read_image(kept / "run.exr"), read_image(root / "whole4.exr"))
    np.testing.assert_array_equal(np.asarray(Image.open(kept / "run.png")),
                                  np.asarray(Image.open(root / "whole4.png")))
    assert json.loads((kept / "run.json").read_text())["settings"]["spp"] == 4
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]  # nothing partial
    assert not any(p.exists() for p in targets.values())  # all or none


def test_a_checkpoint_on_a_full_disk_goes_to_the_rescue_folder_and_the_render_goes_on(
        scene, full_disk, tmp_path):
    root, common = scene
    ckpt = full_disk / "run.checkpoint.npz"
    run = _cli("render", *common, "--spp", "4", "-o", str(tmp_path / "run.exr"),
               "--checkpoint", str(ckpt), "--checkpoint-every", "1e-9",
               tmpdir=tmp_path / "tmp")
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stderr
    warning = [line for line in said_lines(run.stderr) if line.startswith("warning:")]
    assert len(warning) == 1 and str(ckpt) in warning[0] and str(tmp_path / "tmp") in warning[0]
    np.testing.assert_array_equal(read_image(tmp_path / "run.exr"), read_image(root / "whole4.exr"))
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]
    assert list((tmp_path / "tmp").iterdir()) == []  # the finished render's checkpoint removed


def _dead_pid() -> int:
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    return int(gone.stdout)


def test_temporaries_of_killed_writes_are_removed_by_the_next_render(scene, tmp_path):
    root, common = scene
    dead = _dead_pid()
    ckpt = tmp_path / "run.checkpoint.npz"
    orphans = [tmp_path / f".run.checkpoint.npz.{dead}.abcd1234.npz",  # a checkpoint write
               # the image's temporary inside the render's staged temporary of -o
               tmp_path / f"..run.exr.{dead}.abcd1234.exr.{dead}.efgh5678.exr"]
    live = tmp_path / f".run.checkpoint.npz.{os.getpid()}.ijkl9012.npz"  # a running writer's
    for path in (*orphans, live):
        path.write_bytes(b"partial")
    run = _cli("render", *common, "--spp", "4", "-o", str(tmp_path / "run.exr"),
               "--checkpoint", str(ckpt))
    assert run.returncode == 0, run.stderr
    assert not any(p.exists() for p in orphans)
    assert live.exists()


KILLED_WRITER = """
import sys
from vastray.checkpoint import write_checkpoint
from vastray.render.film import Film
from vastray.render.progressive import Progression, StopRules
progression = Progression(800, 600, StopRules(1))
progression.next_pass()
progression.add_pass(0, Film(800, 600))
while True:
    write_checkpoint(sys.argv[1], progression, {"settings": {}})
"""


def test_a_checkpoint_writer_killed_midway_leaves_nothing_after_the_next_render(scene,
                                                                                tmp_path):
    root, common = scene
    ckpt = tmp_path / "run.checkpoint.npz"
    for _ in range(20):  # until the kill lands inside a write (it nearly always does)
        writer = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(ckpt)])
        hidden = f".{ckpt.name}.{writer.pid}."
        deadline = time.monotonic() + 300
        try:
            while not any(p.name.startswith(hidden) for p in tmp_path.iterdir()):
                assert writer.poll() is None and time.monotonic() < deadline
                time.sleep(0.01)
        finally:
            writer.send_signal(signal.SIGKILL)
            writer.wait(timeout=60)
        if any(p.name.startswith(hidden) for p in tmp_path.iterdir()):
            break
    else:
        pytest.fail("no kill landed inside a checkpoint write")
    run = _cli("render", *common, "--spp", "4", "-o", str(tmp_path / "run.exr"),
               "--checkpoint", str(ckpt))
    assert run.returncode == 0, run.stderr
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_an_animation_on_a_full_disk_keeps_the_frames_done_in_a_rescue_folder(
        scene, full_disk, tmp_path):
    # room for two frames' small images (a tmpfs page each): the third fails, and the frames
    # written so far (staged beside their targets, all or none) go to the rescue folder
    root, common = scene
    small = [*common, "--width", "8", "--height", "8", "--spp", "4", "--frames", "3"]
    (tmp_path / "normal").mkdir()  # an output's folder is never created (it must exist)
    normal = _cli("render", *small, "-o", str(tmp_path / "normal" / "an.exr"))
    assert normal.returncode == 0, normal.stderr
    os.truncate(full_disk / "filler", (full_disk / "filler").stat().st_size - 2 * 4096)
    run = _cli("render", *small, "-o", str(full_disk / "an.exr"), "--report",
               str(tmp_path / "an.json"), tmpdir=tmp_path / "tmp")
    assert run.returncode != 0 and "Traceback" not in run.stderr, run.stderr
    line = run.stderr.strip().splitlines()[-1]
    assert str(full_disk / "an_0002.exr") in line and "No space left" in line, run.stderr
    kept = Path(re.search(r"written to (\S+) instead", line).group(1))
    for frame in range(3):
        np.testing.assert_array_equal(read_image(kept / f"an_{frame:04d}.exr"),
                                      read_image(tmp_path / "normal" / f"an_{frame:04d}.exr"))
        assert json.loads((kept / f"an_{frame:04d}.json").read_text())["frame"] == frame
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]
    assert not list(tmp_path.glob("an*.json"))
