"""The job options: one typed, frozen object; over the wire a versioned dict, checked on
receipt."""

from __future__ import annotations

import dataclasses

import msgpack
import pytest

from vastray.actors.job_options import VERSION, JobOptions, JobOptionsError


def test_options_cross_the_wire_unchanged():
    options = JobOptions(scheduler="temporal", cache=3, max_samples_in_flight=400,
                         load_bandwidth=[20.0, 10.0], simplified="portal", portal_interval=2,
                         portal_threshold=0.25, portal_resolution=8, portal_accuracy=True,
                         assignment="spatial", priority="queue")
    wire = msgpack.unpackb(msgpack.packb(options.to_wire()))
    assert wire["version"] == VERSION
    assert JobOptions.from_wire(wire) == options
    assert JobOptions.from_wire(JobOptions().to_wire()) == JobOptions()


def test_options_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        JobOptions().cache = 2


@pytest.mark.parametrize("change,message", [
    ({"version": VERSION + 1}, f"version {VERSION + 1} is not this node's"),
    ({"version": None}, "version None"),
    ({"cahce": 3}, r"unknown field\(s\) \['cahce'\]"),
    ({"cache": "3"}, "'cache' must be an integer or None"),
    ({"preload": 1}, "'preload' must be true or false"),
    ({"load_bandwidth": ["fast"]}, "MB/s numbers"),
    ({"scheduler": "galaxy"}, "unknown scheduler 'galaxy'"),
    ({"max_samples_in_flight": 0}, "at least 1"),
])
def test_a_wire_dict_of_another_version_or_shape_is_refused_by_name(change, message):
    wire = dict(JobOptions().to_wire(), **change)
    with pytest.raises(JobOptionsError, match=message):
        JobOptions.from_wire(wire)


def test_a_missing_field_or_a_non_dict_is_refused():
    wire = JobOptions().to_wire()
    del wire["threads"]
    with pytest.raises(JobOptionsError, match=r"lack field\(s\) \['threads'\]"):
        JobOptions.from_wire(wire)
    with pytest.raises(JobOptionsError, match="must be a dict"):
        JobOptions.from_wire([1, 2])


@pytest.mark.parametrize("options,message", [
    ({"scheduler": "image", "history_depth": 1}, "--history-depth bounds spec-ooc"),
    ({"scheduler": "image", "simplified": "portal"}, "--simplified works with"),
    ({"scheduler": "async", "simplified": "depth>0", "portal_accuracy": True},
     "--portal-accuracy"),
    ({"scheduler": "async", "priority": "queue"}, "--priority choose"),
    ({"scheduler": "image", "assignment": "sequential"}, "--assignment and --priority"),
    ({"scheduler": "reference", "max_samples_in_flight": 10}, "in-core reference"),
    ({"scheduler": "reference", "preload": False}, "in-core reference"),
    ({"load_bandwidth": 0.0}, "must be positive"),
    ({"scheduler": "reference", "resident_first": False}, "--scheduler reference has no such"),
    ({"scheduler": "temporal", "resident_first": False}, "--scheduler temporal has no such"),
    ({"scheduler": "spec-insitu", "resident_first": False}, "spec-insitu has no such"),
    ({"scheduler": "image", "max_batch_rays": 100}, "--scheduler image sends none"),
    ({"scheduler": "spec-insitu", "max_batch_rays": 100}, "spec-insitu sends none"),
])
def test_options_that_do_not_fit_the_scheduler_are_refused(options, message):
    with pytest.raises(JobOptionsError, match=message):
        JobOptions(**options)


def test_every_scheduler_that_consumes_an_option_accepts_it():
    from vastray.schedule.registry import Option, accepting

    for scheduler in accepting(Option.RESIDENT_FIRST):
        assert not JobOptions(scheduler=scheduler, resident_first=False).resident_first
    for scheduler in accepting(Option.MAX_BATCH_RAYS):
        assert JobOptions(scheduler=scheduler, max_batch_rays=100).max_batch_rays == 100


def test_load_bandwidth_is_cycled_over_the_ranks_in_bytes_per_second():
    assert JobOptions().load_bytes_per_second(3) is None
    options = JobOptions(load_bandwidth=[100, 50])
    assert [options.load_bytes_per_second(r) for r in range(3)] == [100e6, 50e6, 100e6]
    assert JobOptions(load_bandwidth=2).for_report()["load_bandwidth"] == 2.0


def test_a_node_refuses_a_job_of_another_options_version_and_says_why(tmp_path):
    """A real node process, given a job whose options carry another version, reports the
    failure to its coordinator with the reason (and renders nothing)."""
    import os
    import subprocess
    import sys

    import zmq
    from zmq.auth.thread import ThreadAuthenticator

    from vastray.actors import protocol
    from vastray.transport.codec import decode, encode

    ctx = zmq.Context()
    auth = ThreadAuthenticator(ctx)  # the test plays the coordinator: it admits its secret
    auth.start()
    auth.configure_plain(domain="*", passwords={"vastray": "0" * 32})
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    router.plain_server = True
    port = router.bind_to_random_port("tcp://127.0.0.1")
    read_end, write_end = os.pipe()  # the join secret, as a coordinator hands it over
    os.write(write_end, b"0" * 32)
    os.close(write_end)
    node = subprocess.Popen([sys.executable, "-m", "vastray.actors.node", "--coordinator",
                             f"tcp://127.0.0.1:{port}", "--rank", "0", "--timeout", "30",
                             "--secret-fd", str(read_end)], pass_fds=(read_end,),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(read_end)
    try:
        assert router.poll(30_000), "the node never said hello"
        identity, _, *hello = router.recv_multipart()
        assert decode(hello).kind == protocol.HELLO
        wire = dict(JobOptions().to_wire(), version=99)
        job = {"store": str(tmp_path), "settings": {}, "options": wire, "rank": 0, "size": 1,
               "endpoints": [decode(hello).meta["endpoint"]], "units": [[None, 0, 1]],
               "paced": False, "peer_tokens": [b"t" * 16], "keys": [], "domains": 1}
        router.send_multipart([identity, b"token", *encode(protocol.JOB, {}, job)])
        failed = None
        while failed is None and router.poll(30_000):
            _, token, *body = router.recv_multipart()
            message = decode(body)
            if message.kind == protocol.FAILED:
                failed = message.meta["error"]
        assert failed is not None and "job options version 99" in failed, failed
        assert node.wait(30) != 0
    finally:
        if node.poll() is None:
            node.kill()
        node.wait()
        router.close()
        auth.stop()
        ctx.term()


def test_a_domain_decomposition_job_s_default_tile_grows_with_its_nodes_past_16():
    from vastray.actors.job_options import (
        DEFAULT_NODE_TILE,
        MAX_JOB_TILE,
        MIN_NODE_SHARE,
        default_tile,
    )

    assert DEFAULT_NODE_TILE == 16 * MIN_NODE_SHARE
    for scheduler in ("domain", "dynamic", "async", "spec-insitu", "temporal"):
        assert default_tile(scheduler, 1) == default_tile(scheduler, 16) == DEFAULT_NODE_TILE
        assert default_tile(scheduler, 17) == 17 * MIN_NODE_SHARE
        assert default_tile(scheduler, 1024) == 1024 * MIN_NODE_SHARE == MAX_JOB_TILE
        assert default_tile(scheduler, 4096) == MAX_JOB_TILE  # path state a node bounded
    for scheduler in ("image", "spec-ooc"):  # a sort-first node's tile is its own
        assert default_tile(scheduler, 1024) == DEFAULT_NODE_TILE
    with pytest.raises(ValueError, match="at least 1 node"):
        default_tile("domain", 0)


def test_the_cli_s_nodes_job_takes_the_default_tile_for_its_node_count():
    from vastray.actors.job_options import MIN_NODE_SHARE
    from vastray.planning import job_options
    from vastray.request import RenderRequest

    assert job_options(RenderRequest(nodes=64), "domain", None).max_samples_in_flight \
        == 64 * MIN_NODE_SHARE
    assert job_options(RenderRequest(nodes=64), "image", None).max_samples_in_flight == 65536
    assert job_options(RenderRequest(nodes=64, max_samples_in_flight=1000), "domain",
                       None).max_samples_in_flight == 1000
