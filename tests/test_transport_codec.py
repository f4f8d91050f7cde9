"""Wire codec: round trips without copies, and rejection of malformed or oversized frames."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zmq

from vastray.transport.codec import PACK_LIMIT, VERSION, CodecError, decode, encode


def ray_batch(n=1000):
    rng = np.random.default_rng(0)
    return {
        "origin": rng.random((n, 3), dtype=np.float32),
        "direction": rng.random((n, 3), dtype=np.float32),
        "t_max": np.full(n, np.inf, np.float32),
        "pixel": rng.integers(0, 1 << 20, n).astype(np.uint32),
        "depth": rng.integers(0, 4, n).astype(np.uint8),
        "beta": rng.random((n, 3)),
        "occluded": rng.random(n) > 0.5,
    }


def test_round_trip_keeps_values_dtypes_and_shapes():
    arrays = ray_batch()
    message = decode(encode("rays", arrays, {"tile": 3}))
    assert message.kind == "rays" and message.meta == {"tile": 3} and message.n == 1000
    for name, a in arrays.items():
        assert message.arrays[name].dtype == a.dtype
        np.testing.assert_array_equal(message.arrays[name], a)


def test_empty_batch_and_big_endian_input():
    message = decode(encode("rays", {"t": np.zeros(0, np.float32),
                                     "x": np.arange(4, dtype=">f8")}))
    assert message.arrays["t"].shape == (0,)
    np.testing.assert_array_equal(message.arrays["x"], np.arange(4.0))


def test_decode_does_not_copy():
    frames = [bytes(f) for f in encode("rays", ray_batch(10))]
    message = decode(frames)
    assert not message.arrays["origin"].flags.owndata
    assert not message.arrays["origin"].flags.writeable


def test_a_small_message_is_one_frame_and_a_large_one_a_frame_per_field():
    small, large = ray_batch(10), ray_batch(2000)
    assert sum(a.nbytes for a in large.values()) > PACK_LIMIT
    assert len(encode("rays", small)) == 2
    assert len(encode("rays", large)) == 1 + len(large)
    for arrays in (small, large):
        message = decode([bytes(f) for f in encode("rays", arrays, {"tile": 1})])
        assert list(message.arrays) == list(arrays)
        for name, a in arrays.items():
            assert message.arrays[name].dtype == a.dtype
            np.testing.assert_array_equal(message.arrays[name], a)


def test_packed_fields_are_aligned_views_and_empty_fields_survive():
    arrays = {"depth": np.arange(3, dtype=np.uint8), "t": np.zeros(0, np.float32),
              "beta": np.arange(6.0).reshape(3, 2)}
    frames = [bytes(f) for f in encode("rays", arrays)]
    assert len(frames) == 2 and len(frames[1]) == 8 + 0 + 48
    message = decode(frames)
    assert message.arrays["t"].shape == (0,)
    assert message.arrays["beta"].ctypes.data % 8 == 0
    assert not message.arrays["beta"].flags.owndata
    np.testing.assert_array_equal(message.arrays["beta"], arrays["beta"])


def test_objects_cannot_be_sent():
    with pytest.raises(CodecError, match="cannot be sent"):
        encode("rays", {"x": np.array([object()], dtype=object)})


def _header(**changes):
    base = {"v": VERSION, "kind": "rays", "n": 2, "fields": [["t", "<f4", [2]]], "meta": {}}
    base.update(changes)
    return msgpack.packb(base)


@pytest.mark.parametrize("frames, match", [
    ([], "empty"),
    ([b"\xc1\xc1"], "not msgpack"),
    ([msgpack.packb([1, 2])], "not a map"),
    ([_header(v=99), b"\0" * 8], "wire version"),
    ([_header(), b"\0" * 8, b"extra"], "frames came"),
    ([_header()], "frames came"),
    ([_header(), b"\0" * 7], "header says 8"),
    ([_header(fields=[["t", "|O", [2]]]), b"\0" * 8], "not allowed"),
    ([_header(fields=[["t", "<f4", [-2]]]), b"\0" * 8], "bad shape"),
    ([_header(fields=[["t", "<f4"]]), b"\0" * 8], "malformed field"),
    ([_header(kind=5), b"\0" * 8], "needs kind"),
])
def test_malformed_messages_are_rejected(frames, match):
    with pytest.raises(CodecError, match=match):
        decode(frames)


def test_oversized_message_is_rejected_before_reading_frames():
    header = _header(fields=[["t", "<f8", [1 << 30]]])
    with pytest.raises(CodecError, match="exceeds"):
        decode([header, b""], max_bytes=1 << 20)


def test_zero_copy_over_real_zeromq_sockets():
    ctx = zmq.Context()
    try:
        a, b = ctx.socket(zmq.PAIR), ctx.socket(zmq.PAIR)
        a.setsockopt(zmq.LINGER, 0)
        b.setsockopt(zmq.LINGER, 0)
        port = a.bind_to_random_port("tcp://127.0.0.1")
        b.connect(f"tcp://127.0.0.1:{port}")
        arrays = ray_batch(50000)
        a.send_multipart(encode("rays", arrays), copy=False)
        assert b.poll(5000), "no message within 5 s"
        message = decode(b.recv_multipart(copy=False))
        np.testing.assert_array_equal(message.arrays["beta"], arrays["beta"])
    finally:
        ctx.destroy(linger=0)


@pytest.mark.parametrize("frames, match", [
    ([_header(packed=True, fields=[["t", "<f4", [2]], ["u", "|u1", [2]]]), b"\0" * 15],
     "packed frame has 15 bytes, header says 16"),
    ([_header(packed=True), b"\0" * 8, b"\0"], "one frame but 2"),
    ([_header(packed=True, fields=[["t", "<f4", [2], 2]]), b"\0" * 8], "no split fields"),
    ([_header(packed=True, fields=[["t", "<f4", [2]], ["t", "<f4", [2]]]), b"\0" * 16],
     "appears twice"),
    ([_header(packed=1), b"\0" * 8], "true or false"),
])
def test_malformed_packed_messages_are_rejected(frames, match):
    with pytest.raises(CodecError, match=match):
        decode(frames)
