"""A closed stdout or stderr (`vastray info STORE | head -1`, `2>&1 | head`) ends a command
quietly with the status a shell expects; a pipe of the command's own that breaks is not taken
for one (issue 23, part 5). Real processes and real pipes throughout."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from vastray.render.imageio import read_exr

from scenes import bumpy_scene, write_store

VASTRAY = [sys.executable, "-m", "vastray.cli"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("pipes") / "s.store", bumpy_scene(), grid=(2, 1, 1))


def _run_with_closed(args: list[str], cwd, stream: str) -> tuple[int, str]:
    """Run vastray with its ``stream`` ("stdout" or "stderr") a pipe whose reader has gone
    before the command writes (vastray takes far longer to start than this takes to close):
    its exit status and what it wrote on the other stream."""
    proc = subprocess.Popen([*VASTRAY, *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    closed, other = ((proc.stdout, proc.stderr) if stream == "stdout"
                     else (proc.stderr, proc.stdout))
    closed.close()
    with other:
        said = other.read().decode()
    return proc.wait(timeout=120), said


@pytest.mark.parametrize("args, status", [
    (["--help"], 0), (["render", "--help"], 0), (["--version"], 0),  # argparse ignores it
    (["info", "{store}"], 141), (["verify", "{store}"], 141),
])
def test_a_command_whose_stdout_closes_ends_without_a_traceback(store, tmp_path, args, status):
    args = [a.format(store=store.path) for a in args]
    code, err = _run_with_closed(args, tmp_path, "stdout")
    assert code == status, err
    assert err == "", err  # no traceback, no "Exception ignored ... BrokenPipeError"


def test_a_render_whose_stdout_and_stderr_close_writes_its_image_and_exits_141(store, tmp_path):
    # `vastray render ... 2>&1 | head -1`: the image is written, the summary line has nowhere
    # to go (the render's own signal handlers for checkpoints stay as they were)
    proc = subprocess.Popen([*VASTRAY, "render", str(store.path), "-o", "a.exr", "--width",
                             "16", "--height", "12", "--spp", "1"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    proc.stdout.close()
    assert proc.wait(timeout=120) == 141
    assert (tmp_path / "a.exr").stat().st_size > 0


def test_a_render_whose_output_closes_mid_render_writes_its_image(store, tmp_path):
    # issue 42: `vastray render ... --nodes 4 2>&1 | head -1` died at the progress bar's first
    # write (141, no image): the bar shows after 2 s, so this render lasts longer than that
    # (the earlier test's render did only on a loaded machine, where it failed now and then).
    proc = subprocess.Popen([*VASTRAY, "-v", "render", str(store.path), "-o", "a.exr",
                             "--png", "a.png", "--width", "128", "--height", "96", "--spp", "64",
                             "--nodes", "2"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    proc.stdout.close()
    assert proc.wait(timeout=300) == 141  # what a shell reports: the output's reader left
    assert read_exr(tmp_path / "a.exr").shape == (96, 128, 3)
    assert (tmp_path / "a.png").stat().st_size > 0


def test_an_error_said_to_a_closed_stderr_keeps_its_exit_status(tmp_path):
    code, out = _run_with_closed(["info", "missing.store"], tmp_path, "stderr")
    assert code == 2 and out == ""


def test_a_broken_pipe_other_than_stdout_or_stderr_is_not_taken_for_a_closed_output():
    # The child's stdout and stderr are pipes the test reads; a pipe of its own without a
    # reader does not count, until its stderr becomes one.
    script = (
        "import os\n"
        "from vastray.cli import _closed_output\n"
        "r, w = os.pipe(); os.close(r)\n"
        "try:\n"
        "    os.write(w, b'x')\n"
        "except BrokenPipeError:\n"
        "    print('own pipe broken; closed output:', _closed_output(), flush=True)\n"
        "os.dup2(w, 2)\n"
        "print('stderr broken; closed output:', _closed_output(), flush=True)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert out.stdout.splitlines() == ["own pipe broken; closed output: False",
                                       "stderr broken; closed output: True"], out.stderr
