"""Wire format of ray batches and other array messages: a msgpack header plus one raw frame per
array, sent with ``copy=False`` and decoded without copying. Never pickle.

Header (msgpack map)::

    {"v": 2, "kind": "rays", "n": 4096,
     "fields": [["origin", "<f4", [4096, 3]], ["pixel", "<u4", [4096]], ...],
     "meta": {...},                     # small msgpack-able dict (ids, counters)
     "packed": false}

followed by one frame per field, in order, each exactly ``prod(shape) * itemsize`` bytes. A
field larger than ``FRAME_LIMIT`` goes as several frames in a row (its entry then has a fourth
element, the frame count), so that every socket can refuse frames larger than that before it
holds them (``ZMQ_MAXMSGSIZE``, which ZeroMQ checks per frame). Every part but the last of a
split field has the same size.

A message whose fields hold at most ``PACK_LIMIT`` bytes in all goes instead as one frame
(``"packed": true``): the fields in order, each starting at the next multiple of
``PACK_ALIGN`` bytes, zero padding between. Every frame costs both ends a call into ZeroMQ
and a Python object (a 100-ray batch of 15 fields took 0.11 ms more a round trip as 16 frames
than as 2), while copying a few kilobytes costs microseconds; large fields stay zero-copy.

Two limits: ``FRAME_LIMIT`` on every socket a stranger can reach (a listening socket reads a
handshake frame whole before it checks anything), and ``PEER_FRAME_LIMIT`` on the sockets
ray batches and films between nodes arrive on: a node *connects* to each peer to receive from
it (``actors.management``), and a connecting socket admits no stranger, so its frames may be
large. Fewer, larger frames are what keep the member path at raw ZeroMQ's speed: a field cut
into 128 KiB frames must be copied back into one buffer on arrival.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgpack
import numpy as np

#: 2: small messages packed into one frame (``"packed"``).
VERSION = 2
#: Largest message accepted by default (header + frames).
MAX_MESSAGE_BYTES = 1 << 30
MAX_FIELDS = 64
#: Largest frame on the wire: fields beyond it are split (see the module docstring). It is
#: also the most a connection that has not authenticated can make a socket hold (ZeroMQ reads
#: a handshake frame whole before it checks it), so it is small; 128 KiB frames move ray
#: batches as fast as 4 MiB ones (``bench/distributed.py``'s ``transport_ratio``).
FRAME_LIMIT = 128 << 10
#: Largest frame between members, on a socket that connected to its sender (see above).
PEER_FRAME_LIMIT = 64 << 20
#: Largest message (its fields' bytes) sent packed into one frame.
PACK_LIMIT = 64 << 10
#: Each field of a packed frame starts at a multiple of this many bytes (any dtype's size).
PACK_ALIGN = 8
#: Most frames one field may be split into (a 1 GiB message at most).
MAX_PARTS = MAX_MESSAGE_BYTES // FRAME_LIMIT
#: The header is one frame.
MAX_HEADER_BYTES = FRAME_LIMIT
#: Plain little-endian numeric types only: nothing that needs pickling or alignment tricks.
ALLOWED_DTYPES = frozenset({"|b1", "|u1", "<u2", "<u4", "<u8", "|i1", "<i2", "<i4", "<i8",
                            "<f4", "<f8"})


class CodecError(ValueError):
    """A malformed, unsupported or oversized message."""


@dataclass
class Message:
    """A decoded message: its kind, arrays (read-only views of the frames) and metadata."""

    kind: str
    arrays: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(next(iter(self.arrays.values()))) if self.arrays else 0


def frames_nbytes(frames: list) -> int:
    """Bytes of a message's frames on the wire (``encode``'s output)."""
    return sum(memoryview(f).nbytes for f in frames)


def encode(kind: str, arrays: dict[str, np.ndarray], meta: dict | None = None,
           frame_limit: int = FRAME_LIMIT) -> list:
    """Frames of a message: ``[header, frame, ...]`` (frames are zero-copy buffers).

    Parameters
    ----------
    kind : what the message is ("rays", "film", "reduce", ...).
    arrays : name -> array; arrays are made C-contiguous little-endian if they are not.
    meta : small msgpack-able dictionary.
    frame_limit : largest frame; larger fields are split. ``PEER_FRAME_LIMIT`` only for a
        message to a peer (``ManagementActor.to_peer``): every other socket refuses frames over
        ``FRAME_LIMIT``.
    """
    if not FRAME_LIMIT <= frame_limit <= PEER_FRAME_LIMIT:
        raise CodecError(f"frame limit {frame_limit} outside {FRAME_LIMIT}..{PEER_FRAME_LIMIT}")
    if len(arrays) > MAX_FIELDS:
        raise CodecError(f"{len(arrays)} fields; at most {MAX_FIELDS}")
    fields, views = [], []
    for name, array in arrays.items():
        a = np.ascontiguousarray(array)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        if a.dtype.str not in ALLOWED_DTYPES:
            raise CodecError(f"field {name!r}: dtype {a.dtype} cannot be sent")
        fields.append([name, a.dtype.str, list(a.shape)])
        views.append(memoryview(a).cast("B") if a.size else b"")
    packed = len(views) > 1 and sum(len(v) for v in views) <= PACK_LIMIT
    if packed:
        frames = [_pack(views)]
    else:
        frames = []
        for entry, view in zip(fields, views, strict=True):
            if len(view) > frame_limit:
                parts = [view[i:i + frame_limit] for i in range(0, len(view), frame_limit)]
                entry.append(len(parts))
                frames.extend(parts)
            else:
                frames.append(view)
    n = len(next(iter(arrays.values()))) if arrays else 0
    header = msgpack.packb({"v": VERSION, "kind": kind, "n": n, "fields": fields,
                            "meta": meta or {}, "packed": packed}, use_bin_type=True)
    if len(header) > MAX_HEADER_BYTES:
        raise CodecError(f"{kind} header of {len(header)} bytes exceeds {MAX_HEADER_BYTES}: "
                         "send large data as arrays, not in meta")
    return [header, *frames]


def _pack(views: list) -> bytes:
    """One frame holding ``views`` in order, each at the next multiple of ``PACK_ALIGN``."""
    pieces = []
    for view in views:
        pieces.append(view)
        pieces.append(_PADDING[-len(view) % PACK_ALIGN])
    return b"".join(pieces)


_PADDING = [bytes(n) for n in range(PACK_ALIGN)]


def _aligned(nbytes: int) -> int:
    return -(-nbytes // PACK_ALIGN) * PACK_ALIGN


def decode(frames: list, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Check and decode ``[header, frame, ...]`` (bytes, memoryviews or zmq Frames).

    Raises
    ------
    CodecError
        For anything not exactly as ``encode`` makes it, or larger than ``max_bytes``.
    """
    if not frames:
        raise CodecError("empty message")
    buffers = [f.buffer if hasattr(f, "buffer") else f for f in frames]
    header_bytes = memoryview(buffers[0]).nbytes
    if header_bytes > MAX_HEADER_BYTES:
        raise CodecError(f"header of {header_bytes} bytes exceeds {MAX_HEADER_BYTES}")
    try:
        header = msgpack.unpackb(buffers[0], raw=False, strict_map_key=True)
    except (msgpack.UnpackException, ValueError, TypeError) as exc:
        raise CodecError(f"header is not msgpack ({exc})") from None
    if not isinstance(header, dict):
        raise CodecError("header is not a map")
    if header.get("v") != VERSION:
        raise CodecError(f"wire version {header.get('v')!r}; this node speaks {VERSION}")
    kind, fields, meta = header.get("kind"), header.get("fields"), header.get("meta", {})
    if not isinstance(kind, str) or not isinstance(fields, list) or not isinstance(meta, dict):
        raise CodecError("header needs kind (str), fields (list) and meta (map)")
    if len(kind) > 64:
        raise CodecError("kind longer than 64 characters")
    if len(fields) > MAX_FIELDS:
        raise CodecError(f"{len(fields)} fields; at most {MAX_FIELDS}")
    packed = header.get("packed", False)
    if type(packed) is not bool:
        raise CodecError("header's packed must be true or false")
    specs = [_field(spec) for spec in fields]
    if packed:
        if any(parts != 1 for *_, parts in specs):
            raise CodecError("a packed message has no split fields")
        return Message(kind, _unpack(specs, buffers, header_bytes, max_bytes), meta)
    if len(buffers) != 1 + sum(parts for *_, parts in specs):
        raise CodecError(f"header lists {sum(p for *_, p in specs)} frames but "
                         f"{len(buffers) - 1} frames came")
    arrays, total, at = {}, header_bytes, 1
    split = []  # (name, dtype, shape, views) of fields sent as several frames
    for name, dtype, shape, parts in specs:
        expected = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        total += expected
        if total > max_bytes:
            raise CodecError(f"message exceeds {max_bytes} bytes")
        views = [memoryview(b) for b in buffers[at:at + parts]]
        at += parts
        got = sum(v.nbytes for v in views)
        if got != expected or (parts > 1 and any(v.nbytes != views[0].nbytes
                                                 for v in views[:-1])):
            raise CodecError(f"field {name!r}: frames have {got} bytes, header says "
                             f"{expected}")
        if name in arrays or any(name == other for other, *_ in split):
            raise CodecError(f"field {name!r} appears twice")
        if not expected:
            arrays[name] = np.zeros(shape, dtype)
        elif parts == 1:
            arrays[name] = np.frombuffer(views[0], dtype=dtype).reshape(shape)
        else:
            split.append((name, dtype, shape, views))
    if split:
        arrays.update(_join(split))
    return Message(kind, arrays, meta)


def _unpack(specs: list, buffers: list, header_bytes: int,
            max_bytes: int) -> dict[str, np.ndarray]:
    """The fields of a packed message: read-only views of its one frame."""
    if len(buffers) != 2:
        raise CodecError(f"a packed message is one frame but {len(buffers) - 1} frames came")
    frame = memoryview(buffers[1])
    sizes = [math.prod(shape) * dtype.itemsize for _, dtype, shape, _ in specs]
    expected = sum(_aligned(n) for n in sizes)
    if header_bytes + expected > max_bytes:
        raise CodecError(f"message exceeds {max_bytes} bytes")
    if frame.nbytes != expected:
        raise CodecError(f"packed frame has {frame.nbytes} bytes, header says {expected}")
    arrays, at = {}, 0
    for (name, dtype, shape, _), size in zip(specs, sizes, strict=True):
        if name in arrays:
            raise CodecError(f"field {name!r} appears twice")
        arrays[name] = np.frombuffer(frame, dtype, size // dtype.itemsize, at).reshape(shape)
        at += _aligned(size)
    return arrays


def _join(split: list) -> dict[str, np.ndarray]:
    """Fields sent as several frames, copied once into one buffer (one allocation a message:
    a fresh allocation per field costs more in page faults than the copy), each field at a
    64-byte aligned offset."""
    sizes = [sum(v.nbytes for v in views) for *_, views in split]
    starts = np.cumsum([0] + [-(-n // 64) * 64 for n in sizes])
    arena = np.empty(int(starts[-1]), np.uint8)
    joined = {}
    for (name, dtype, shape, views), start, size in zip(split, starts, sizes, strict=False):
        at = int(start)
        for view in views:
            arena[at:at + view.nbytes] = np.frombuffer(view, np.uint8)
            at += view.nbytes
        joined[name] = arena[int(start):int(start) + size].view(dtype).reshape(shape)
    return joined


def _field(spec) -> tuple[str, np.dtype, tuple[int, ...], int]:
    if not (type(spec) is list and 3 <= len(spec) <= 4 and type(spec[0]) is str
            and type(spec[1]) is str and type(spec[2]) is list):
        raise CodecError(f"malformed field entry {str(spec)[:80]}")
    name, dtype, shape = spec[:3]
    parts = spec[3] if len(spec) == 4 else 1
    if type(parts) is not int or not 1 <= parts <= MAX_PARTS:
        raise CodecError(f"field {name!r}: bad frame count {parts!r}")
    dtype = _DTYPES.get(dtype)
    if dtype is None:
        raise CodecError(f"field {name!r}: dtype {spec[1]!r} not allowed")
    if len(shape) > 4 or not all(type(s) is int and 0 <= s < (1 << 40) for s in shape):
        raise CodecError(f"field {name!r}: bad shape {shape!r}")
    return name, dtype, tuple(shape), parts


_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}
