"""A node refused at the handshake says so, however late it starts listening for the refusal.

ZeroMQ never tries a refused CURVE handshake again: the refusal is one monitor event, raised by
the I/O thread as soon as the coordinator's ZAP handler answers. The node attached its monitor
after connecting, so on a busy machine (CI under ``-n auto``) the refusal came first, was lost,
and the revoked node waited out its 30 s timeout instead of saying "authentication failed"
(``test_key_bundles``, once). Real sockets, a real ZAP handler; the delay makes the race certain.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
import zmq
import zmq.asyncio

from vastray.actors.management import AuthenticationFailed, ManagementActor
from vastray.transport.keys import CoordinatorKeys, NodeKeys
from vastray.transport.security import Credentials, Gate, serve


def test_a_refusal_that_comes_before_the_node_watches_is_still_heard():
    async def main() -> None:
        server_ctx, node_ctx = zmq.asyncio.Context(), zmq.asyncio.Context()
        server_public, server_secret = zmq.curve_keypair()
        node_public, node_secret = zmq.curve_keypair()
        coordinator_keys = CoordinatorKeys(server_public, server_secret, Path("unused"))
        server_gate = Gate(server_ctx, allow=lambda key: False, what="the test coordinator")
        coordinator = server_ctx.socket(zmq.ROUTER)
        serve(coordinator, Credentials(keys=coordinator_keys))
        port = coordinator.bind_to_random_port("tcp://127.0.0.1")
        node_keys = NodeKeys("n2", node_public, node_secret, server_public)
        node_gate = Gate(node_ctx, what="the test node")
        actor = ManagementActor(node_ctx, f"tcp://127.0.0.1:{port}", "127.0.0.1", "127.0.0.1",
                                5.0, Credentials(keys=node_keys), node_gate)
        try:
            deadline = time.monotonic() + 10
            while server_gate.refusals == 0 and time.monotonic() < deadline:
                await asyncio.sleep(0.05)  # the coordinator's loop answers the ZAP request
            assert server_gate.refusals == 1
            await asyncio.sleep(0.3)  # the refusal has reached the node before it watches
            with pytest.raises(AuthenticationFailed, match="allow-list"):
                await asyncio.wait_for(actor.watch_handshake("the coordinator"), 5)
        finally:
            actor.close()
            coordinator.close(linger=0)
            for gate, ctx in ((server_gate, server_ctx), (node_gate, node_ctx)):
                gate.close()
                ctx.destroy(linger=0)

    asyncio.run(main())
