"""Who may join a job and speak in it: the attacks of a probe, each refused.

- without keys, a process that does not hold the render's join secret never gets the job;
- a peer message is bound to its sender by the token only that pair of nodes shares: a film
  only from a tree child that owes it, once; a rank spoken for by another is refused;
- a ray batch naming a domain the job does not have is dropped and counted, never fatal.
Real ZeroMQ sockets and real processes throughout."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest
import zmq
import zmq.asyncio

from vastray.actors import protocol
from vastray.actors.attempt import pair_tokens
from vastray.actors.coordinator import render_distributed
from vastray.actors.film_wire import film_frames
from vastray.actors.management import routing_id
from vastray.actors.node_failure import NodeFailure
from vastray.render.film import Film
from vastray.schedule.paths import RADIANCE_FIELDS
from vastray.transport.codec import FRAME_LIMIT, PEER_FRAME_LIMIT, encode
from vastray.transport.join_secret import read_join_secret

from scenes import POINT_AND_SKY_TOML, bumpy_scene, free_port, member_actors, settings, write_store


def _rays(n: int, domain: int, rank: int) -> list:
    arrays = {"domain": np.full(n, domain, np.int64), "path": np.arange(n, dtype=np.int64),
              "depth": np.zeros(n, np.uint8), "origin": np.zeros((n, 3), np.float32),
              "direction": np.ones((n, 3), np.float32), "beta": np.ones((n, 3))}
    assert set(RADIANCE_FIELDS) <= set(arrays)
    return encode(protocol.RAYS, arrays, {"rank": rank, "tile": 0, "queue": "radiance"})


async def _send_as(node, to: int, token: bytes, frames: list) -> None:
    """Send ``frames`` from ``node``'s peer port to node ``to`` behind ``token`` (any token:
    an attacking member's), once ``to`` has connected."""
    identity = routing_id(node.peer_tokens[to])
    deadline = time.monotonic() + 10
    while True:
        try:
            await node.router.send_multipart([identity, token, *frames], flags=zmq.NOBLOCK)
            return
        except zmq.ZMQError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.01)


async def test_peer_messages_are_bound_to_the_rank_whose_token_they_carry():
    film = film_frames(Film(4, 3), {"rank": 1, "ordinal": 0})
    with member_actors(4, domains=8) as (_, _, _, nodes):
        node0 = nodes[0]  # children 1 and 2; node 3 is node 1's child
        token = {r: node0.peer_tokens[r] for r in range(4)}
        sends = [  # (sending node, token, message): members, so every message meets checks
            (3, token[3], film_frames(Film(4, 3), {"rank": 3, "ordinal": 0})),  # not a child
            (2, token[2], film),                       # node 2 speaking for node 1
            (1, token[1], film),                       # node 1's film: taken
            (1, token[1], film),                       # ... once
            (1, token[1], film_frames(Film(4, 3), {"rank": 1, "ordinal": 2})),  # no unit 2
            (2, token[2], film_frames(Film(4, 3), {"rank": 2, "ordinal": -1})),  # nor unit -1
            (2, token[2], film_frames(Film(4, 3), {"rank": 2, "ordinal": 1})),  # a later unit's
            (2, token[2], encode(protocol.EXCHANGE, {}, {"rank": 2, "call": 0, "step": 0})),  # 1's step
            (2, token[2], _rays(5, 10**6, 2)),         # a domain the job does not have
            (2, token[2], _rays(5, 7, 2)),             # one it has
            (2, pair_tokens(1)[0][0], _rays(5, 7, 2)),  # a token of no pair of this job
            (2, node0.token, _rays(5, 7, 2)),          # the coordinator channel's token
            (2, token[1], _rays(5, 7, 1)),             # node 1's token over node 2's connection
        ]
        for sender, sent_token, frames in sends:
            await _send_as(nodes[sender], 0, sent_token, frames)
        await _until(lambda: node0.rejections.total >= 10)
        films = node0.mailbox(protocol.FILM)
        assert films.qsize() == 2
        assert [(m.meta["rank"], m.meta["ordinal"]) for m in (
            films.get_nowait(), films.get_nowait())] == [(1, 0), (2, 1)]
        assert node0.mailbox(protocol.EXCHANGE).qsize() == 0
        rays = node0.mailbox(protocol.RAYS)
        assert rays.qsize() == 1 and int(rays.get_nowait().arrays["domain"][0]) == 7
        assert node0.rejections.counts == {"malformed": 7, "stranger": 2,
                                           "impersonation": 1}, node0.rejections.counts


async def test_ray_batches_arrive_in_large_frames_on_the_connections_a_node_made():
    # The member path: a node receives from a peer on the socket it connected to that peer,
    # which takes frames of PEER_FRAME_LIMIT; its listening port takes FRAME_LIMIT only.
    with member_actors(2, domains=8) as (_, _, _, nodes):
        n = 3 * FRAME_LIMIT // 12 + 7  # origin: 12 bytes a ray, three small frames' worth
        frames = encode(protocol.RAYS, {"domain": np.full(n, 3, np.int64),
                                        "path": np.arange(n, dtype=np.int64),
                                        "depth": np.zeros(n, np.uint8),
                                        "origin": np.zeros((n, 3), np.float32),
                                        "direction": np.ones((n, 3), np.float32),
                                        "beta": np.ones((n, 3))},
                        {"rank": 1, "tile": 0, "queue": "radiance"}, PEER_FRAME_LIMIT)
        assert max(memoryview(f).nbytes for f in frames) > FRAME_LIMIT
        await nodes[1].to_peer(0, frames)
        message = await nodes[0].receive(protocol.RAYS, "rays")
        assert message.n == n and float(message.arrays["direction"].sum()) == 3 * n
        assert nodes[0].inbound[1].getsockopt(zmq.MAXMSGSIZE) > PEER_FRAME_LIMIT
        assert nodes[0].router.getsockopt(zmq.MAXMSGSIZE) <= FRAME_LIMIT + 1024
        assert nodes[0].rejections.total == 0


async def _until(condition, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        await asyncio.sleep(0.05)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("membership")
    store = write_store(root / "s", bumpy_scene(), kd=4)
    (root / "scene.toml").write_text(POINT_AND_SKY_TOML)
    return store, root / "scene.toml"


def test_without_keys_a_hello_without_the_join_secret_never_gets_the_job(scene):
    # The probe's first attack: on loopback, without keys, a process sent a hello with an
    # empty token and received the job 0.05 s later. Now its handshake fails: no job.
    store, toml = scene
    port = free_port()
    outcome = {}

    def run():
        try:
            render_distributed(store.path, toml, settings(width=8, height=6), 1,
                               listen=f"127.0.0.1:{port}", timeout=4)
        except NodeFailure as exc:
            outcome["error"] = str(exc)

    thread = threading.Thread(target=run)
    thread.start()
    ctx = zmq.Context()
    try:
        secret = read_join_secret(port, 10)  # the coordinator runs
        intruders = [ctx.socket(zmq.DEALER) for _ in range(2)]
        intruders[1].plain_username, intruders[1].plain_password = b"vastray", b"0" * 32
        hello = encode(protocol.HELLO, {}, {"rank": 0, "endpoint": "tcp://127.0.0.1:1"})
        for intruder in intruders:
            intruder.connect(f"tcp://127.0.0.1:{port}")
            intruder.send_multipart([b"", *hello])
        thread.join(timeout=30)
        assert "no node joined within 4 s" in outcome["error"], outcome
        assert not any(i.poll(100) for i in intruders)  # nothing ever came back
        assert secret not in b"".join(hello)
    finally:
        thread.join(timeout=30)
        ctx.destroy(linger=0)


async def test_with_keys_only_the_rank_a_token_names_can_speak_or_listen_with_it(tmp_path):
    # With keys a node receives from peer r only on the connection it made to r, whose key the
    # handshake checked: node 2 with the token node 0 shares with node 1 is refused, and a
    # process with a key not in the job cannot connect to take node 1's traffic.
    from vastray.transport.keys import add_node_key, generate_keys, load_node_keys

    generate_keys(tmp_path)
    for name in ("n0", "n1", "n2", "outsider"):
        add_node_key(tmp_path, name)
    film = film_frames(Film(4, 3), {"rank": 1, "ordinal": 0})
    with member_actors(3, domains=4, keys=tmp_path) as (ctx, _, gate, nodes):
        token = nodes[0].peer_tokens[1]
        await _send_as(nodes[2], 0, token, film)  # node 2's connection, node 1's token
        await _send_as(nodes[1], 0, token, film)  # node 1's own
        await _until(lambda: nodes[0].rejections.total >= 1
                     and nodes[0].mailbox(protocol.FILM).qsize() >= 1)
        assert nodes[0].rejections.counts == {"impersonation": 1}, nodes[0].rejections.counts
        assert nodes[0].mailbox(protocol.FILM).qsize() == 1
        outsider = ctx.socket(zmq.DEALER)  # in the key folder, not in the job
        key = load_node_keys(tmp_path, "outsider")
        outsider.curve_secretkey, outsider.curve_publickey = key.secret, key.public
        outsider.curve_serverkey = nodes[0].peer_keys[0]
        outsider.setsockopt(zmq.ROUTING_ID, routing_id(token))
        outsider.connect(nodes[0].endpoint)
        await _until(lambda: gate.refusals >= 1)
        # goes to node 1 (node 0 is its partner at step 0), never to the outsider
        await nodes[0].to_peer(1, encode(protocol.EXCHANGE, {}, {"rank": 0, "call": 0,
                                                                  "step": 0}))
        assert not await outsider.poll(300)
        assert (await nodes[1].receive(protocol.EXCHANGE, "partial")).meta["rank"] == 0
        outsider.close(linger=0)


async def test_a_message_retried_is_not_overtaken_by_a_later_one_to_the_same_peer():
    # A send to a peer whose queue is full is retried; a later message to the same peer must
    # wait for it (each pair's messages stay in order, as on the one socket a pair had before
    # the peer sockets were reversed).
    def partial(i):
        return encode(protocol.EXCHANGE, {"x": np.zeros(1)}, {"rank": 1, "call": i, "step": 0})

    with member_actors(2, domains=4) as (_, _, _, nodes):
        sender = nodes[1]
        await sender.to_peer(0, partial(0))  # node 0 has connected
        assert (await nodes[0].receive(protocol.EXCHANGE, "partial")).meta["call"] == 0
        first, real = partial(1), sender._send_now
        refusals = [3]

        async def full_at_first(message):  # node 0's queue is full for the first message
            if message[2] == first[0] and refusals[0] > 0:
                refusals[0] -= 1
                return False
            return await real(message)

        sender._send_now = full_at_first
        retried = asyncio.ensure_future(sender.to_peer(0, first))
        await asyncio.sleep(0)  # it was refused and waits to try again
        await asyncio.gather(sender.to_peer(0, partial(2)), retried)
        got = [(await nodes[0].receive(protocol.EXCHANGE, "partial")).meta["call"]
               for _ in range(2)]
        assert refusals == [0] and got == [1, 2]
