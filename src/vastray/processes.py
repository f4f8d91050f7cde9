"""Facts about processes: whether one still runs (what files and folders named after their
owner's pid, such as stale temporary images, node logs and join secrets, are judged by), and
this process's resident memory (now and at its peak) and bytes read from storage; and how a SIGTERM stops one
(``Terminated``, raised by the handler the CLI installs)."""

from __future__ import annotations

import asyncio
import os
import signal
import threading


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, Slurm, systemd): cleaned up exactly like Ctrl-C."""


def raise_terminated(signum, frame) -> None:
    """The SIGTERM handler: raise ``Terminated`` in the main thread, once."""
    # `timeout` signals the command and then its whole process group, so the same stop
    # arrives twice: a second Terminated would break into the clean-up the first started
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Terminated()


async def stoppable(main):
    """Await ``main`` so that a SIGTERM arriving meanwhile cancels it, as ``asyncio.Runner``
    does for Ctrl-C, and raise ``Terminated`` once its clean-up has run.

    Raised by ``raise_terminated`` while an event loop runs, ``Terminated`` can land inside
    one of the loop's own callbacks, such as the one that hands a finished executor job's
    result to its future; that future then never completes, and the loop's shutdown waits for
    it forever (seen: a coordinator stopped mid-animation hung in ``Runner.close``). Outside
    the main thread, or where the CLI's SIGTERM handler is not installed, ``main`` is simply
    awaited.
    """
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGTERM) is not raise_terminated):
        return await main
    loop, task = asyncio.get_running_loop(), asyncio.current_task()
    stopped = False

    def stop() -> None:
        nonlocal stopped
        if not stopped:  # `timeout` signals twice: the second must not cut the clean-up short
            stopped = True
            task.cancel()

    # The handler only schedules ``stop`` on the loop (it never raises into a callback). Not
    # ``loop.add_signal_handler``: its removal leaves SIG_DFL for a moment before the next
    # disposition is set, and the second SIGTERM `timeout` sends, landing there, killed the
    # process in its clean-up (exit -15 instead of 143, seen in CI): here every change of
    # disposition is one ``signal.signal`` call, with no default action between.
    signal.signal(signal.SIGTERM, lambda signum, frame: loop.call_soon_threadsafe(stop))
    try:
        return await main
    except asyncio.CancelledError:
        if stopped:
            raise Terminated() from None
        raise
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN if stopped else raise_terminated)


def running(pid: int) -> bool:
    """Whether process ``pid`` exists (ours or another user's)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def proc_bytes(path: str, field: str, unit: int = 1024) -> int | None:
    """A ``FIELD:  N`` line of a ``/proc`` file in bytes: N times ``unit`` (1024 for the kB
    of ``/proc/meminfo`` and ``/proc/PID/status``, 1 for the bytes of ``/proc/PID/io``);
    None where the file or the field is missing."""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith(f"{field}:"):
                    return int(line.split()[1]) * unit
    except OSError:
        pass
    return None


def peak_rss_bytes() -> int:
    """This process's peak resident memory since it started its program.

    ``VmHWM``, the peak of its own address space: ``getrusage``'s ``ru_maxrss`` also keeps the
    peak of the process it was forked from (Linux carries it across ``exec``), so a node
    started by a 250 MB coordinator would report at least 250 MB. ``ru_maxrss`` where there
    is no ``/proc``.
    """
    peak = proc_bytes("/proc/self/status", "VmHWM")
    if peak is not None:
        return peak
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def rss_bytes() -> int:
    """This process's resident memory now (``VmRSS``); 0 where there is no ``/proc``."""
    return proc_bytes("/proc/self/status", "VmRSS") or 0


def disk_read_bytes() -> int | None:
    """Bytes this process has had read from storage so far (``read_bytes`` of
    ``/proc/self/io``: reads the page cache served are not counted); None where the kernel
    does not say."""
    return proc_bytes("/proc/self/io", "read_bytes", unit=1)
