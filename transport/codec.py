"""Wire format of ray batches and other array messages: a msgpack header plus one raw frame per
array, sent with ``copy=False`` and decoded without copying. Never pickle.

Header (msgpack map)::

    {"v": 1, "kind": "rays", "n": 4096,
     "fields": [["origin", "<f4", [4096, 3]], ["pixel", "<u4", [4096]], ...],
     "meta": {...}}                     # small msgpack-able dict (ids, counters)

followed by one frame per field, in order, each exactly ``prod(shape) * itemsize`` bytes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgpack
import numpy as np

VERSION = 1
#: Largest message accepted by default (header + frames).
MAX_MESSAGE_BYTES = 1 << 30
MAX_FIELDS = 64
MAX_HEADER_BYTES = 1 << 20
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


def encode(kind: str, arrays: dict[str, np.ndarray], meta: dict | None = None) -> list:
    """Frames of a message: ``[header, frame, ...]`` (frames are zero-copy buffers).

    Parameters
    ----------
    kind : what the message is ("rays", "film", "reduce", ...).
    arrays : name -> array; arrays are made C-contiguous little-endian if they are not.
    meta : small msgpack-able dictionary.
    """
    if len(arrays) > MAX_FIELDS:
        raise CodecError(f"{len(arrays)} fields; at most {MAX_FIELDS}")
    fields, frames = [], []
    for name, array in arrays.items():
        a = np.ascontiguousarray(array)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        if a.dtype.str not in ALLOWED_DTYPES:
            raise CodecError(f"field {name!r}: dtype {a.dtype} cannot be sent")
        fields.append([name, a.dtype.str, list(a.shape)])
        frames.append(memoryview(a).cast("B") if a.size else b"")
    n = len(next(iter(arrays.values()))) if arrays else 0
    header = msgpack.packb({"v": VERSION, "kind": kind, "n": n, "fields": fields,
                            "meta": meta or {}}, use_bin_type=True)
    return [header, *frames]


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
    if len(buffers) != 1 + len(fields):
        raise CodecError(f"header lists {len(fields)} fields but {len(buffers) - 1} frames came")
    arrays, total = {}, header_bytes
    for spec, buf in zip(fields, buffers[1:], strict=True):
        name, dtype, shape = _field(spec)
        expected = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        total += expected
        if total > max_bytes:
            raise CodecError(f"message exceeds {max_bytes} bytes")
        view = memoryview(buf)
        if view.nbytes != expected:
            raise CodecError(f"field {name!r}: frame has {view.nbytes} bytes, header says "
                             f"{expected}")
        if name in arrays:
            raise CodecError(f"field {name!r} appears twice")
        arrays[name] = np.frombuffer(view, dtype=dtype).reshape(shape) if expected else \
            np.zeros(shape, dtype)
    return Message(kind, arrays, meta)


def _field(spec) -> tuple[str, np.dtype, tuple[int, ...]]:
    if not (isinstance(spec, list) and len(spec) == 3 and isinstance(spec[0], str)
            and isinstance(spec[1], str) and isinstance(spec[2], list)):
        raise CodecError(f"malformed field entry {spec!r}")
    name, dtype, shape = spec
    if dtype not in ALLOWED_DTYPES:
        raise CodecError(f"field {name!r}: dtype {dtype!r} not allowed")
    if len(shape) > 4 or not all(type(s) is int and 0 <= s < (1 << 40) for s in shape):
        raise CodecError(f"field {name!r}: bad shape {shape!r}")
    return name, np.dtype(dtype), tuple(shape)
