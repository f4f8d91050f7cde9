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
from vastray.actors.node_failure import NodeFailure
from vastray.render.film import Film
from vastray.schedule.paths import RADIANCE_FIELDS
from vastray.transport.codec import encode
from vastray.transport.join_secret import read_join_secret

from scenes import POINT_AND_SKY_TOML, bumpy_scene, member_actors, settings, write_store


def _rays(n: int, domain: int, rank: int) -> list:
    arrays = {"domain": np.full(n, domain, np.int64), "path": np.arange(n, dtype=np.int64),
              "depth": np.zeros(n, np.uint8), "origin": np.zeros((n, 3), np.float32),
              "direction": np.ones((n, 3), np.float32), "beta": np.ones((n, 3))}
    assert set(RADIANCE_FIELDS) <= set(arrays)
    return encode(protocol.RAYS, arrays, {"rank": rank, "tile": 0, "queue": "radiance"})


async def test_peer_messages_are_bound_to_the_rank_whose_token_they_carry():
    film = film_frames(Film(4, 3), {"rank": 1, "ordinal": 0})
    with member_actors(4, domains=8) as (ctx, _, gate, nodes):
        node0 = nodes[0]  # children 1 and 2; node 3 is node 1's child
        # a member's own connection (holds the join secret): its messages meet every check
        member = ctx.socket(zmq.DEALER)
        member.plain_username, member.plain_password = b"vastray", gate.secret
        member.connect(node0.endpoint)
        token = {r: node0.peer_tokens[r] for r in range(4)}
        sends = [
            [token[3], *film_frames(Film(4, 3), {"rank": 3, "ordinal": 0})],  # not a child
            [token[2], *film],                       # node 2 speaking for node 1
            [token[1], *film],                       # node 1's film: taken
            [token[1], *film],                       # ... once
            [token[1], *film_frames(Film(4, 3), {"rank": 1, "ordinal": 2})],  # no unit 2
            [token[2], *film_frames(Film(4, 3), {"rank": 2, "ordinal": -1})],  # nor unit -1
            [token[2], *film_frames(Film(4, 3), {"rank": 2, "ordinal": 1})],  # a later unit's
            [token[1], *encode(protocol.BROADCAST, {}, {"rank": 1})],  # node 0 has no parent
            [token[2], *_rays(5, 10**6, 2)],         # a domain the job does not have
            [token[2], *_rays(5, 7, 2)],             # one it has
            [pair_tokens(1)[0][0], *_rays(5, 7, 2)],  # a token of no pair of this job
            [node0.token, *_rays(5, 7, 2)],          # the coordinator channel's token
        ]
        for frames in sends:
            await member.send_multipart(frames)
        await _until(lambda: node0.rejections.total >= 9)
        films = node0.mailbox(protocol.FILM)
        assert films.qsize() == 2
        assert [(m.meta["rank"], m.meta["ordinal"]) for m in (
            films.get_nowait(), films.get_nowait())] == [(1, 0), (2, 1)]
        assert node0.mailbox(protocol.BROADCAST).qsize() == 0
        rays = node0.mailbox(protocol.RAYS)
        assert rays.qsize() == 1 and int(rays.get_nowait().arrays["domain"][0]) == 7
        assert node0.rejections.counts == {"malformed": 7, "stranger": 2}, \
            node0.rejections.counts
        member.close(linger=0)


async def test_a_connection_without_the_join_secret_is_refused_at_the_handshake():
    with member_actors(2) as (ctx, _, gate, nodes):
        strangers = [ctx.socket(zmq.DEALER) for _ in range(2)]
        strangers[1].plain_username, strangers[1].plain_password = b"vastray", b"f" * 32
        for stranger in strangers:
            stranger.connect(nodes[0].endpoint)
            await stranger.send_multipart([nodes[0].peer_tokens[1], *_rays(2, 1, 1)])
        await _until(lambda: gate.refusals + gate.failed_handshakes >= 2)
        assert gate.refusals == 1 and gate.failed_handshakes >= 1  # wrong secret; no secret
        await asyncio.sleep(0.3)
        assert nodes[0].mailbox(protocol.RAYS).qsize() == 0  # even with a pair's token
        assert nodes[0].rejections.total == 0  # nothing got as far as the checks
        for stranger in strangers:
            stranger.close(linger=0)


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


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_without_keys_a_hello_without_the_join_secret_never_gets_the_job(scene):
    # The probe's first attack: on loopback, without keys, a process sent a hello with an
    # empty token and received the job 0.05 s later. Now its handshake fails: no job.
    store, toml = scene
    port = _free_port()
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


async def test_with_keys_a_pair_token_is_taken_only_from_the_key_of_the_rank_it_names(tmp_path):
    # A token that leaked to another member (here: node 2's key with the token node 0 shares
    # with node 1) is refused: with keys, the CURVE key of the connection must be that rank's.
    from vastray.transport.keys import add_node_key, generate_keys, load_node_keys

    generate_keys(tmp_path)
    for rank in range(3):
        add_node_key(tmp_path, f"n{rank}")
    film = film_frames(Film(4, 3), {"rank": 1, "ordinal": 0})
    with member_actors(3, domains=4, keys=tmp_path) as (ctx, _, _, nodes):
        token, senders = nodes[0].peer_tokens[1], []
        for name in ("n2", "n1"):  # node 2's key first, then node 1's own
            key = load_node_keys(tmp_path, name)
            senders.append(ctx.socket(zmq.DEALER))
            senders[-1].curve_secretkey, senders[-1].curve_publickey = key.secret, key.public
            senders[-1].curve_serverkey = nodes[0].peer_keys[0]
            senders[-1].connect(nodes[0].endpoint)
            await senders[-1].send_multipart([token, *film])
        await _until(lambda: nodes[0].rejections.total >= 1
                     and nodes[0].mailbox(protocol.FILM).qsize() >= 1)
        assert nodes[0].rejections.counts == {"impersonation": 1}, nodes[0].rejections.counts
        assert nodes[0].mailbox(protocol.FILM).qsize() == 1
        for sock in senders:
            sock.close(linger=0)
