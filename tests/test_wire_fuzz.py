"""A wire no message can break: a live render is flooded with malformed, truncated, oversized,
wrong-role and random messages, and forged films and dones; it completes with the reference
image, and the nodes' reports count what they dropped.

The flood comes from a process of the render's own user (it reads the join secret, as a node
would): it passes the handshake, so every message meets the checks behind it. A stranger's
connections (no secret, a wrong one) are refused at the handshake and counted.

Hypothesis draws the messages first (drawing is the slow part); then a render starts and the
whole flood is sent while it runs."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vastray.actors import protocol
from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.management import routing_id
from vastray.render.driver import render
from vastray.render.film import BATCHES, CHANNELS
from vastray.render.scene_config import load_scene_config
from vastray.transport.codec import encode
from vastray.transport.join_secret import read_join_secret

from scenes import POINT_AND_SKY_TOML, bumpy_scene, free_port, member_actors, write_store
from scenes import settings as render_settings

#: Messages per hypothesis example, and examples: 10,000 messages in all.
PER_EXAMPLE, EXAMPLES = 200, 50

KINDS = sorted(protocol.META) + ["", "x" * 60, "rays ", "FILM"]


def _header(kind, fields, meta, version=1, n=0):
    return msgpack.packb({"v": version, "kind": kind, "n": n, "fields": fields, "meta": meta},
                         use_bin_type=True)


frame_bytes = st.binary(max_size=64)
int64 = st.integers(-2**63, 2**63 - 1)  # what msgpack can carry
metas = st.dictionaries(st.sampled_from(["rank", "tile", "queue", "job", "paths", "probe",
                                         "finished", "endpoint"]),
                        st.one_of(int64, st.text(max_size=8), st.none(), st.booleans(),
                                  st.lists(int64, max_size=3)),
                        max_size=4)
field_specs = st.lists(st.tuples(st.sampled_from(["domain", "origin", "path", "sum", "count"]),
                                 st.sampled_from(["<f4", "<u4", "<i8", "|b1", "O", ">f8"]),
                                 st.lists(st.integers(-1, 2**62), max_size=3)), max_size=4)

messages = st.one_of(
    # random frames
    st.lists(frame_bytes, max_size=5),
    # headers that decode to nonsense: wrong versions, kinds, shapes, sizes, frame counts
    st.builds(lambda kind, fields, meta, version, extra: [
        _header(kind, [list(f) for f in fields], meta, version), *extra],
        st.sampled_from(KINDS), field_specs, metas, st.sampled_from([1, 1, 1, 0, 2, None]),
        st.lists(frame_bytes, max_size=4)),
    # well-formed messages of every kind with wrong meta or arrays (wrong role, bad schema)
    st.builds(lambda kind, meta, n: encode(kind, {"domain": np.zeros(n, np.int64)}
                                           if n >= 0 else {}, meta),
              st.sampled_from(KINDS), metas, st.integers(-1, 5)),
)


def draw_flood() -> list[list[bytes]]:
    """The flood: ``PER_EXAMPLE * EXAMPLES`` messages drawn by hypothesis (derandomized, so
    the same messages every run), each a list of frames."""
    flood: list[list[bytes]] = []

    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(batch=st.lists(messages, min_size=PER_EXAMPLE, max_size=PER_EXAMPLE))
    def draw(batch):
        flood.extend(batch)

    draw()
    return flood


@pytest.fixture(scope="module")
def flood() -> list[list[bytes]]:
    """Messages drawn once per module (and per test worker), whichever test asks first."""
    return draw_flood()


def test_the_flood_is_drawn_whole_and_holds_every_shape(flood):
    assert len(flood) == PER_EXAMPLE * EXAMPLES
    assert any(frames == [] for frames in flood)  # an empty message
    assert any(len(frames) >= 5 for frames in flood)  # more frames than any kind has


def _forged_film_and_done(n: int) -> list[list]:
    forged = encode(protocol.FILM, {"sum": np.full((n, 3), 1e6),
                                    "batch": np.zeros((n, BATCHES, CHANNELS)),
                                    "count": np.ones(n, np.int64),
                                    "depth": np.zeros(n, np.float32),
                                    "normal": np.zeros((n, 3), np.float32)}, {"rank": 0})
    done = encode(protocol.DONE, {}, {"rank": 0, "busy_s": 0.0, "reduce_s": 0.0,
                                      "counters": {}})
    return [[token, *frames] for token in (b"", b"0" * 16) for frames in (forged, done)]


@pytest.fixture(scope="module")
def flooded_render(tmp_path_factory, flood):
    """A 2-node render with nodes started as a user starts them elsewhere (`vastray node`);
    while it runs, node 0 gets the whole flood and the coordinator forged films and dones."""
    root = tmp_path_factory.mktemp("fuzz")
    store = write_store(root / "s", bumpy_scene(), kd=8)
    toml = root / "scene.toml"
    toml.write_text(POINT_AND_SKY_TOML)
    port = free_port()
    logs = [root / f"node{i}.log" for i in range(2)]
    nodes = []
    for log in logs:
        with open(log, "wb") as err:
            nodes.append(subprocess.Popen([sys.executable, "-m", "vastray.cli", "node",
                                           "--coordinator", f"tcp://127.0.0.1:{port}",
                                           "--timeout", "60"],
                                          stdout=subprocess.DEVNULL, stderr=err))
    st_ = render_settings(width=48, height=36, spp=48, integrator="pt")
    outcome = {}

    def run():
        try:
            outcome["result"] = render_distributed(store.path, toml, st_, 2,
                                                   options=JobOptions(scheduler="async",
                                                                      max_samples_in_flight=2000),
                                                   listen=f"127.0.0.1:{port}", timeout=60)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            outcome["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    endpoint = None
    deadline = time.monotonic() + 30
    while endpoint is None and time.monotonic() < deadline:
        found = re.search(r"listening for peers on (tcp://\S+)", logs[0].read_text())
        endpoint = found.group(1) if found else None
        time.sleep(0.05)
    ctx = zmq.Context()
    try:
        assert endpoint, "node 0 did not say where it listens"
        while "joined" not in logs[1].read_text() and time.monotonic() < deadline:
            time.sleep(0.05)  # both nodes have their job: the render runs
        secret = read_join_secret(port, 10)
        to_node = ctx.socket(zmq.DEALER)
        to_node.setsockopt(zmq.SNDHWM, 0)
        to_node.plain_username, to_node.plain_password = b"vastray", secret
        to_node.connect(endpoint)
        to_coordinator = ctx.socket(zmq.DEALER)
        to_coordinator.plain_username, to_coordinator.plain_password = b"vastray", secret
        to_coordinator.connect(f"tcp://127.0.0.1:{port}")
        strangers = [ctx.socket(zmq.DEALER) for _ in range(2)]  # no secret; a wrong one
        strangers[1].plain_username, strangers[1].plain_password = b"vastray", b"0" * 32
        for stranger in strangers:
            stranger.connect(endpoint)
            stranger.send_multipart([b"", *flood[0]] if flood[0] else [b""])
        sent = 0
        for i, frames in enumerate(flood):
            tokens = [b"", b"forged-token", np.random.default_rng(i).bytes(16)]
            for token in tokens[:1] if frames else tokens:
                to_node.send_multipart([token, *frames] if frames else [token])
                sent += 1
        for frames in _forged_film_and_done(st_.width * st_.height):
            to_coordinator.send_multipart(frames)
        time.sleep(0.5)  # let them arrive
        running = thread.is_alive()
        thread.join(timeout=120)
        # ranks are given in order of arrival: which one did the flooded process get?
        rank = int(re.search(r"as node (\d+) of", logs[0].read_text()).group(1))
        yield {"outcome": outcome, "store": store, "toml": toml, "settings": st_,
               "sent": sent, "running_after_flood": running, "rank": rank}
    finally:
        thread.join(timeout=120)
        for node in nodes:
            if node.poll() is None:
                node.kill()
            node.wait()
        ctx.destroy(linger=0)


def test_the_render_survives_the_flood_with_the_reference_image(flooded_render):
    assert flooded_render["sent"] >= 10_000
    assert flooded_render["running_after_flood"], "the render ended before the flood did"
    outcome = flooded_render["outcome"]
    assert "error" not in outcome, outcome.get("error")
    result = outcome["result"]
    reference = render(flooded_render["store"], load_scene_config(flooded_render["toml"]),
                       flooded_render["settings"], progress=False).film
    np.testing.assert_allclose(result.film.image(), reference.image(), rtol=1e-6, atol=1e-6)
    node0 = result.counters["per_node"][flooded_render["rank"]]["counters"]
    assert node0["rejected_messages"] == flooded_render["sent"], node0  # each one, by a rule
    assert node0.get("rejected_internal", 0) == 0, node0
    # the peer port only sends (a peer sends to the connection this node made to it): every
    # message a member's process sends it is dropped; the checks behind a peer's connection
    # meet the same flood in the next test
    assert node0["rejected_malformed"] == flooded_render["sent"], node0
    assert node0["refused_connections"] >= 2, node0  # the strangers, at the handshake
    # the forged films and dones: refused, and the image above is still the reference
    assert node0["coordinator_rejected_messages"] == 4


async def test_every_message_over_a_peers_connection_meets_the_checks(flood):
    # The flood again, now from a member's ROUTER over the connection node 0 made to it, behind
    # no token, a forged one, a random one and the pair's own: each message is delivered or
    # dropped by a rule, none crashes the receive path.
    with member_actors(2, domains=4) as (_, _, _, nodes):
        sent = 0
        identity = routing_id(nodes[1].peer_tokens[0])
        for i, frames in enumerate(flood):
            tokens = [b"", b"forged-token", np.random.default_rng(i).bytes(16),
                      nodes[1].peer_tokens[0]]
            for token in tokens:
                while True:  # until node 0 has connected, and whenever its queue is full
                    try:
                        await nodes[1].router.send_multipart([identity, token, *frames],
                                                             flags=zmq.NOBLOCK)
                        break
                    except zmq.ZMQError:
                        await asyncio.sleep(0.005)
                sent += 1

        def delivered():
            return sum(box.qsize() for box in nodes[0].mailboxes.values())

        deadline = time.monotonic() + 60
        while nodes[0].rejections.total + delivered() < sent and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        counts = nodes[0].rejections.counts
        assert nodes[0].rejections.total + delivered() == sent, (counts, delivered())
        assert "internal" not in counts, counts
        # foreign tokens are strangers; behind the pair's token the schemas refuse
        assert counts.get("stranger", 0) > len(flood) and counts.get("malformed", 0) > 0, counts
