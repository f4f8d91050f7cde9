"""A ZeroMQ proxy between a node and its peers, for fault injection (``bench/faults.py``).

A node started with ``bench/fault_node.py --peer-endpoint tcp://127.0.0.1:PORT`` tells its
peers to send there; this proxy binds that endpoint and forwards every message to the node's real peer
endpoint, which it reads from the node's log (``listening for peers on ...``; followed again
after a regroup, where the node binds a new one). On the way each message is

- ``delay``: held a random 0-``max_delay_s`` (uniform), keeping each sender's order, as TCP
  keeps the order of one connection (a message never overtakes an earlier one from the same
  peer; messages from different peers interleave as they fall due);
- ``drop``: ray batches (kind ``rays``) dropped with probability ``drop_fraction``; every
  other kind passes at once.

Only peer-to-peer traffic passes here (ray batches, films up the reduce tree, all-reduce
partials and broadcasts); the coordinator's connection to the node is untouched. Peers
authenticate to the proxy, and the proxy to the node, with the render's join secret (PLAIN),
which the proxy reads as a node of this user would.
"""

from __future__ import annotations

import heapq
import re
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import zmq
from zmq.auth.thread import ThreadAuthenticator

from vastray.transport.join_secret import read_join_secret

ENDPOINT_LINE = re.compile(r"listening for peers on (tcp://\S+)")


class PeerProxy(threading.Thread):
    """Forward messages from ``tcp://127.0.0.1:port`` to the node that logs to ``log``.

    Parameters
    ----------
    port : the port to bind on loopback (the endpoint the node advertises).
    log : the node's log file, where it names its real peer endpoint.
    mode : ``"delay"`` or ``"drop"``.
    coordinator_port : the port of the coordinator (without keys) whose join secret admits
        the proxy to the node.
    seed : seed of the delays and of the drops.
    """

    def __init__(self, port: int, log: Path, mode: str, coordinator_port: int, seed: int = 0,
                 max_delay_s: float = 0.05, drop_fraction: float = 0.01):
        super().__init__(daemon=True, name=f"proxy-{port}")
        if mode not in ("delay", "drop"):
            raise ValueError(f"mode must be 'delay' or 'drop', not {mode!r}")
        self.port, self.log, self.mode = port, Path(log), mode
        self.max_delay_s, self.drop_fraction = max_delay_s, drop_fraction
        self.rng = np.random.default_rng(seed)
        self.forwarded = self.dropped = 0
        self.stopping = threading.Event()
        self.ctx = zmq.Context()
        self.coordinator_port = coordinator_port
        self.front = self.ctx.socket(zmq.ROUTER)
        self.front.setsockopt(zmq.LINGER, 0)
        self.front.plain_server = True
        self.auth = ThreadAuthenticator(self.ctx)  # configured once the secret is known
        self.auth.start()
        self.front.bind(f"tcp://127.0.0.1:{port}")

    def stop(self) -> None:
        self.stopping.set()
        self.join(timeout=10)

    def run(self) -> None:
        secret = read_join_secret(self.coordinator_port, 60)
        self.auth.configure_plain(domain="*", passwords={"vastray": secret.decode()})
        back, target = None, None
        held: list[tuple[float, int, list]] = []  # (due, sequence, frames)
        last_due: dict[bytes, float] = {}
        sequence, next_look = 0, 0.0
        try:
            while not self.stopping.is_set():
                now = time.monotonic()
                if now >= next_look:  # where does the node listen now (a regroup moves it)?
                    found = ENDPOINT_LINE.findall(self._log_text())
                    if found and found[-1] != target:
                        if back is not None:
                            back.close(linger=0)
                        target = found[-1]
                        back = self.ctx.socket(zmq.DEALER)
                        back.setsockopt(zmq.LINGER, 0)
                        back.setsockopt(zmq.SNDHWM, 0)
                        back.plain_username = b"vastray"
                        back.plain_password = secret
                        back.connect(target)
                    next_look = now + 0.1
                while back is not None and held and held[0][0] <= now:
                    back.send_multipart(heapq.heappop(held)[2], copy=False)
                    self.forwarded += 1
                wait = 0.1 if back is None or not held else max(0.0, held[0][0] - now)
                if back is None or not self.front.poll(int(min(wait, 0.1) * 1000) + 1):
                    continue
                identity, *frames = self.front.recv_multipart(copy=False)
                sender = identity.bytes
                if self.mode == "drop":
                    if _kind(frames) == "rays" and self.rng.random() < self.drop_fraction:
                        self.dropped += 1
                        continue
                    due = now
                else:
                    due = max(last_due.get(sender, 0.0),
                              now + self.rng.uniform(0.0, self.max_delay_s))
                last_due[sender] = due
                heapq.heappush(held, (due, sequence, frames))
                sequence += 1
        finally:
            if back is not None:
                back.close(linger=0)
            self.front.close(linger=0)
            self.auth.stop()
            self.ctx.term()

    def _log_text(self) -> str:
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""


def _kind(frames: list) -> str | None:
    """The kind in a message's header (``[token, header, ...]``), or None."""
    try:
        header = msgpack.unpackb(frames[1].bytes, raw=False)
        return header.get("kind") if isinstance(header, dict) else None
    except (IndexError, ValueError, msgpack.UnpackException):
        return None
