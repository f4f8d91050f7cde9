"""`vastray node` with faults injected, for ``bench/faults.py`` and the node-loss tests only.

    python bench/fault_node.py [--peer-endpoint tcp://HOST:PORT] [--slow-drop S] [--hang-trace] -- NODE-ARGS

runs ``vastray.actors.node.main(NODE-ARGS)`` after replacing some of the node's functions:

- ``--peer-endpoint``: the node tells its peers to send to this endpoint instead of its own,
  where a ``fault_proxy.PeerProxy`` that delays or drops messages forwards them to the node's
  real endpoint (the one it logs, ``listening for peers on ...``);
- ``--slow-drop S``: dropping a job when the coordinator calls a regroup takes S seconds more
  (a long trace or load still running); the coordinator is silent meanwhile, and the node must
  not take that silence for its loss.
- ``--hang-trace``: the first trace of a job's domain rays off the event loop's thread blocks for
  ever (a native call that never returns, a deadlock), while the event loop goes on beating:
  the coordinator must find the node hung by its CPU time, not by silence.

The production node reads no fault hooks: a stray environment variable cannot redirect its
peer traffic. Faults exist only in a process started through this launcher.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys

from vastray.actors import node

log = logging.getLogger("fault_node")

#: This file, for the tests and benchmarks that start nodes through it.
LAUNCHER = __file__


def install_faults(peer_endpoint: str | None = None, slow_drop_s: float = 0.0,
                   hang_trace: bool = False) -> None:
    """Replace the node functions the faults act through (see the module's docstring)."""
    if hang_trace:
        import threading

        from vastray.actors import domain_loop

        trace = domain_loop.ScheduleOrder.trace
        # the node's warm-up renders a tiny store on a thread before its hello: only the
        # job's traces hang
        warmed, warm_node = threading.Event(), node.warm_node

        def warm_then_hang() -> float:
            try:
                return warm_node()
            finally:
                warmed.set()

        node.warm_node = warm_then_hang

        def hung_trace(self, domain: int, bvh):
            if warmed.is_set() and threading.current_thread() is not threading.main_thread():
                log.warning("fault injection: the trace of domain %d never returns", domain)
                threading.Event().wait()
            return trace(self, domain, bvh)

        domain_loop.ScheduleOrder.trace = hung_trace
    if peer_endpoint is not None:
        def proxied_endpoint(management) -> str:
            log.warning("fault injection: peers are told to send to %s, not here",
                        peer_endpoint)
            return peer_endpoint

        node.peer_endpoint = proxied_endpoint
    if slow_drop_s > 0:
        drop_job = node.drop_job

        async def slow_drop(work) -> None:
            log.warning("fault injection: dropping the job takes %.1f s more", slow_drop_s)
            await asyncio.sleep(slow_drop_s)
            await drop_job(work)

        node.drop_job = slow_drop


def command(node_args: list[str], peer_endpoint: str | None = None,
            slow_drop_s: float = 0.0, hang_trace: bool = False) -> list[str]:
    """The command line that starts a node with these faults (for ``subprocess``)."""
    faults = ["--hang-trace"] if hang_trace else []
    if peer_endpoint is not None:
        faults += ["--peer-endpoint", peer_endpoint]
    if slow_drop_s > 0:
        faults += ["--slow-drop", str(slow_drop_s)]
    return [sys.executable, LAUNCHER, *faults, "--", *node_args]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--peer-endpoint", metavar="URL",
                        help="endpoint the node tells its peers to send to (a proxy's)")
    parser.add_argument("--slow-drop", type=float, default=0.0, metavar="S",
                        help="seconds more that dropping a regrouped job takes")
    parser.add_argument("--hang-trace", action="store_true",
                        help="the first trace off the event loop's thread never returns")
    parser.add_argument("node_args", nargs=argparse.REMAINDER,
                        help="-- then the arguments of `vastray node`")
    args = parser.parse_args(argv)
    node_args = args.node_args[1:] if args.node_args[:1] == ["--"] else args.node_args
    install_faults(args.peer_endpoint, args.slow_drop, args.hang_trace)
    return node.main(node_args)


if __name__ == "__main__":
    sys.exit(main())
