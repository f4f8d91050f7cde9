"""A node that joins again (after its coordinator regroups) opens a new peer socket on the
same gate: watching it must not collide with what watched the last one.

pyzmq names a socket's monitor endpoint after its file descriptor (``inproc://monitor.s-FD``);
a closed socket's descriptor is reused by the next one, and the old monitor stayed bound while
the gate's task read it, so the node died with "Address already in use" on joining again
(only 1 of 2 survivors rejoined in ``test_node_loss``, once in several CI runs)."""

from __future__ import annotations

import asyncio

import zmq
import zmq.asyncio

from vastray.actors.management import ManagementActor
from vastray.transport.join_secret import new_secret
from vastray.transport.security import Credentials, Gate


def test_a_gate_watches_a_socket_whose_descriptor_names_a_bound_endpoint():
    # the race, made certain: the last socket's monitor still bound under the name pyzmq
    # gives a monitor of this descriptor
    async def main() -> None:
        ctx = zmq.asyncio.Context()
        gate = Gate(ctx, secret=new_secret(), what="test")
        router = ctx.socket(zmq.ROUTER)
        stale = ctx.socket(zmq.PAIR)
        try:
            router.bind_to_random_port("tcp://127.0.0.1")
            stale.bind(f"inproc://monitor.s-{router.FD}")
            watcher = gate.watch(router, "a peer port")  # raised EADDRINUSE before the fix
            await asyncio.sleep(0)
            assert not watcher.done()
            watcher.cancel()
        finally:
            stale.close(linger=0)
            router.close(linger=0)
            gate.close()
            ctx.destroy(linger=0)

    asyncio.run(main())


def test_a_node_opens_its_peer_port_again_and_again_on_one_gate():
    # what run_node does between jobs: a ManagementActor per job, closed before the next
    async def main() -> None:
        ctx = zmq.asyncio.Context()
        secret = new_secret()
        gate = Gate(ctx, secret=secret, what="test")
        coordinator = ctx.socket(zmq.ROUTER)
        port = coordinator.bind_to_random_port("tcp://127.0.0.1")
        try:
            for _ in range(20):
                actor = ManagementActor(ctx, f"tcp://127.0.0.1:{port}", "127.0.0.1",
                                        "127.0.0.1", 5.0, Credentials(secret=secret), gate)
                await asyncio.sleep(0)
                actor.close()
                await asyncio.sleep(0)
            await asyncio.sleep(0.5)  # a cancelled watcher's thread ends on its monitor's stop
            assert len(gate._tasks) <= 1  # the ZAP server
            assert sum(not w.done() for w in gate._watchers) <= 1  # none left per old job
        finally:
            coordinator.close(linger=0)
            gate.close()
            ctx.destroy(linger=0)

    asyncio.run(main())
