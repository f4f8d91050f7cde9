"""A listening socket as a node's peer port has it (``serve`` + ``Gate.watch``), in a process of
its own, for the pre-authentication memory tests.

    python flood_target.py plain|curve

Prints its port, then (with ``curve``) the z85 public keys of the server and of the one client
it admits and that client's secret, one per line; with ``plain`` the join secret in hex. Echoes
every message a member sends back to it, and on standard input's end prints how many
connections its doorkeeper turned away and exits.
"""

from __future__ import annotations

import asyncio
import sys

import zmq
import zmq.asyncio

from vastray.transport.join_secret import new_secret
from vastray.transport.keys import CoordinatorKeys
from vastray.transport.security import Credentials, Gate, serve


async def main(mechanism: str) -> None:
    ctx = zmq.asyncio.Context()
    if mechanism == "curve":
        public, secret = zmq.curve_keypair()
        client_public, client_secret = zmq.curve_keypair()
        gate = Gate(ctx, allow=lambda key: key == client_public, what="target")
        credentials = Credentials(keys=CoordinatorKeys(public=public, secret=secret,
                                                       allow_dir=None))
        said = [public, client_public, client_secret]
    else:
        secret = new_secret()
        gate = Gate(ctx, secret=secret, what="target")
        credentials = Credentials(secret=secret)
        said = [secret.hex().encode()]
    router = ctx.socket(zmq.ROUTER)
    serve(router, credentials)
    watcher = gate.watch(router, "target")
    port = router.bind_to_random_port("tcp://127.0.0.1")
    print(port, *(s.decode() for s in said), sep="\n", flush=True)

    async def echo() -> None:
        while True:
            frames = await router.recv_multipart()
            await router.send_multipart(frames)

    task = asyncio.ensure_future(echo())
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
    print(f"turned_away={watcher.turned_away} failed={gate.failed_handshakes}", flush=True)
    task.cancel()
    watcher.cancel()
    gate.close()
    router.close(linger=0)
    ctx.destroy(linger=0)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1]))
