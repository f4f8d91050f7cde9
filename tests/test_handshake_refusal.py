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

from vastray.actors import protocol
from vastray.actors.management import AuthenticationFailed, ManagementActor
from vastray.actors.node import join
from vastray.transport.codec import encode
from vastray.transport.keys import CoordinatorKeys, NodeKeys
from vastray.transport.security import Credentials, Gate, serve


def _refused_node(check) -> None:
    """Run ``await check(actor)`` on a node actor whose key the coordinator's ZAP handler
    has already refused (the refusal has reached the node: real sockets, the delay makes the
    race certain)."""
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
                                NODE_TIMEOUT_S, Credentials(keys=node_keys), node_gate)
        try:
            deadline = time.monotonic() + 10
            while server_gate.refusals == 0 and time.monotonic() < deadline:
                await asyncio.sleep(0.05)  # the coordinator's loop answers the ZAP request
            assert server_gate.refusals == 1
            await asyncio.sleep(0.3)  # the refusal has reached the node before it watches
            await check(actor)
        finally:
            actor.close()
            coordinator.close(linger=0)
            for gate, ctx in ((server_gate, server_ctx), (node_gate, node_ctx)):
                gate.close()
                ctx.destroy(linger=0)

    asyncio.run(main())


#: The node's own timeout in these tests: far longer than the waits the tests allow, so that
#: a node that waits it out fails them.
NODE_TIMEOUT_S = 60.0


def test_a_refusal_that_comes_before_the_node_watches_is_still_heard():
    async def check(actor):
        with pytest.raises(AuthenticationFailed, match="allow-list"):
            await asyncio.wait_for(actor.watch_handshake("the coordinator"), 5)

    _refused_node(check)


def test_a_node_refused_before_its_hello_says_so_at_once():
    # ZeroMQ drops a refused connection: the hello, sent after the refusal, waits for a
    # connection that never comes; the join must hear the refusal meanwhile (CI, -n auto:
    # the revoked node of test_key_bundles said "TimeoutError" after its 30 s)
    async def check(actor):
        handshake = asyncio.ensure_future(actor.watch_handshake("the coordinator"))
        hello = encode(protocol.HELLO, {}, {"rank": 0, "endpoint": actor.endpoint})
        started = time.monotonic()
        try:
            with pytest.raises(AuthenticationFailed, match="allow-list"):
                await asyncio.wait_for(join(actor, hello, handshake), 10)
        finally:
            handshake.cancel()
        assert time.monotonic() - started < 5

    _refused_node(check)
