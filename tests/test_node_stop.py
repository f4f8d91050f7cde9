"""A node stops at once, in one line, on Ctrl-C or SIGTERM, even while it is still waiting for
its coordinator: the wait for the join secret ran on a thread that the event loop's shutdown
joined, so a waiting node ignored both signals until its timeout (120 s), then printed a
traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from scenes import free_port


@pytest.mark.parametrize("sig, status, said", [(signal.SIGTERM, 143, "terminated"),
                                               (signal.SIGINT, 130, "interrupted")])
def test_a_node_waiting_for_its_coordinator_stops_at_once_in_one_line(tmp_path, sig, status,
                                                                      said):
    env = {**os.environ, "VASTRAY_RUNTIME_DIR": str(tmp_path)}  # no coordinator's secret there
    node = subprocess.Popen(
        [sys.executable, "-m", "vastray", "-v", "node", "--coordinator",
         f"tcp://127.0.0.1:{free_port()}", "--timeout", "600"],
        stderr=subprocess.PIPE, text=True, env=env)
    try:
        first = node.stderr.readline()  # logged once its signal handlers are in place
        assert "waiting up to 600 s for a coordinator" in first, first
        stopped = time.monotonic()
        node.send_signal(sig)
        rest = node.stderr.read()
        node.wait(timeout=60)
    finally:
        node.kill()
        node.wait()
        node.stderr.close()
    assert time.monotonic() - stopped < 30  # not the 600 s timeout
    assert node.returncode == status, rest
    # one line, no traceback (beside the warm-up's one line, had it finished before the
    # signal: a node warms its kernels while it waits)
    said_lines = [line for line in rest.strip().splitlines()
                  if not line.startswith("node ?: render kernels warm (")]
    assert said_lines == [f"node ?: {said}"], rest


def test_sigterm_inside_an_event_loop_cancels_it_cleanly_then_raises_terminated():
    # A SIGTERM raised by the handler inside a running loop can land in the loop's own
    # callbacks and leave a future never completed (a coordinator stopped mid-animation hung
    # in Runner.close); under `stoppable` it cancels the main task instead, whose clean-up
    # still awaits (here: an executor job), and Terminated comes out after it.
    import asyncio

    from vastray.processes import Terminated, raise_terminated, stoppable

    cleaned = []

    async def main():
        loop = asyncio.get_running_loop()
        loop.call_later(0.2, os.kill, os.getpid(), signal.SIGTERM)
        try:
            await asyncio.sleep(60)
        finally:
            cleaned.append(await loop.run_in_executor(None, sum, [1, 2]))

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        started = time.monotonic()
        with pytest.raises(Terminated):
            asyncio.run(stoppable(main()))
        assert time.monotonic() - started < 30
        assert cleaned == [3]  # the clean-up ran whole, its await included
        # a second SIGTERM (`timeout` signals the group too) is ignored, not fatal
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_without_the_cli_handler_stoppable_only_awaits():
    import asyncio

    from vastray.processes import stoppable

    async def main():
        return 7

    assert asyncio.run(stoppable(main())) == 7
