"""Who may connect: every listening socket admits a peer at the ZeroMQ handshake or not at all.

Two ways to be a member of a job:

- **Keys** (``vastray keys``, ``transport.keys``; needed beyond loopback). The coordinator
  has a key pair of its own (``coordinator.key``; its public half in ``coordinator.pub``),
  each node has its own (``nodes/NAME.key``), and ``public/`` is the allow-list of node
  public keys. Sockets speak
  CURVE: encrypted, and a client is admitted only with a key on the allow-list, read again at
  every handshake (deleting ``public/NAME.key`` shuts NAME out of every later connection).
  No node holds a secret that lets another node, or anyone else, in.
- **No keys** (loopback only). Sockets speak PLAIN with a per-render *join secret*: the
  coordinator hands it to the nodes it starts through an inherited pipe, and for nodes started
  by hand (``--listen`` on loopback) writes it to a file only its user can read
  (``transport.join_secret``). Other users of the machine cannot join.

The handshake is also where memory is bounded: a peer that has not authenticated can make a
socket hold at most ``FRAME_LIMIT`` bytes per connection (``MAXMSGSIZE``; 128 KiB, larger
messages are sent as several frames by the codec), for at most ``HANDSHAKE_S``
(``HANDSHAKE_IVL``), on at most ``PENDING_LIMIT`` connections at once (``Gate.watch``'s
``Doorkeeper``): about 37 MB in all, however many connections an outsider opens.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import secrets
from collections.abc import Callable
from dataclasses import dataclass

import zmq
import zmq.asyncio
from zmq.utils import z85

from vastray.scene.errors import InputError
from vastray.transport.codec import FRAME_LIMIT
from vastray.transport.doorkeeper import Doorkeeper
from vastray.transport.keys import CoordinatorKeys, NodeKeys

#: Seconds a connection may take to authenticate before ZeroMQ drops it.
HANDSHAKE_S = 10.0
#: PLAIN user name (the password is what matters).
PLAIN_USER = b"vastray"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Credentials:
    """How this process authenticates: by ``keys`` (CURVE) or by a join ``secret`` (PLAIN)."""

    secret: bytes | None = None
    keys: CoordinatorKeys | NodeKeys | None = None

    @property
    def curve(self) -> bool:
        return self.keys is not None


#: Bytes CURVE adds to a frame on the wire (a MESSAGE command: its name, a nonce, the box's
#: MAC and flags: 33 bytes in libzmq 4.3), with room to spare. ZeroMQ checks ``MAXMSGSIZE``
#: against the encrypted frame, so a socket that took only ``FRAME_LIMIT`` dropped every
#: connection a full-size frame came over (a keyed render's film: the node reconnected, and
#: the coordinator took it for a stranger).
FRAME_OVERHEAD = 1024


def bound(sock: zmq.Socket, hwm: int = 64) -> None:
    """Bounds every vastray socket keeps: frames of at most ``FRAME_LIMIT`` bytes (a larger
    one ends the connection before it is held), a handshake of at most ``HANDSHAKE_S``, and
    ``hwm`` messages queued each way per connection."""
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, FRAME_LIMIT + FRAME_OVERHEAD)
    sock.setsockopt(zmq.HANDSHAKE_IVL, int(HANDSHAKE_S * 1000))
    sock.setsockopt(zmq.RCVHWM, hwm)
    sock.setsockopt(zmq.SNDHWM, hwm)


def serve(sock: zmq.Socket, credentials: Credentials) -> None:
    """Make a listening socket authenticate every connection (call before bind)."""
    bound(sock)
    keys = credentials.keys
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_server = True
    else:
        sock.plain_server = True


def connect_as(sock: zmq.Socket, credentials: Credentials, server_key: bytes | None = None
               ) -> None:
    """Make a connecting socket present this process's credentials (call before connect);
    ``server_key``: the listener's public key (with keys)."""
    bound(sock)
    keys = credentials.keys
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_serverkey = server_key
    else:
        sock.plain_username = PLAIN_USER
        sock.plain_password = credentials.secret


def check_bind(host: str, credentials: Credentials | None) -> None:
    """Refuse to listen beyond loopback without keys."""
    if (credentials is None or credentials.keys is None) and not (
            host.startswith("127.") or host in ("localhost", "::1")):
        raise InputError(None, f"listening on {host} needs keys (--keys DIR from `vastray keys "
                               "-o DIR --node NAME`); without them only nodes of your user on "
                               "this machine may join, and vastray binds loopback only")


#: Numbers the monitor endpoints of watched sockets (``Gate.watch``).
_MONITORS = itertools.count()


class Gate:
    """The ZAP handler of one ZeroMQ context: admits a connection or refuses it at the
    handshake, and counts and logs refusals at a bounded rate (the first few, then every
    hundredth).

    Parameters
    ----------
    ctx : the asyncio context whose listening sockets it guards.
    secret : without keys, the PLAIN password that admits.
    allow : with keys, ``allow(z85_public_key) -> bool``. None until it is known (a node's
        peers before its job comes): a handshake then waits for ``open(allow)`` for up to
        half of ``HANDSHAKE_S``, since refusing it would end the connection for good.
    """

    def __init__(self, ctx: zmq.asyncio.Context, secret: bytes | None = None,
                 allow: Callable[[bytes], bool] | None = None, what: str = "this process"):
        self.secret, self.allow, self.what = secret, allow, what
        self.refusals = 0
        self.failed_handshakes = 0
        self._known = asyncio.Event()
        if allow is not None or secret is not None:
            self._known.set()
        self._pending = 0
        # A ROUTER, not the usual REP: a reply that waits for ``open`` holds back no other.
        self._sock = ctx.socket(zmq.ROUTER)
        self._sock.linger = 0
        self._sock.bind("inproc://zeromq.zap.01")
        self._tasks = [asyncio.ensure_future(self._serve())]
        self._watchers: list[Doorkeeper] = []

    def close_until_known(self) -> None:
        """Admit no key until the next ``open`` (a node's next job)."""
        self.allow = None
        self._known.clear()

    def open(self, allow: Callable[[bytes], bool]) -> None:
        """Set who is admitted (with keys) and answer the handshakes waiting for it."""
        self.allow = allow
        self._known.set()

    def admit(self, mechanism: bytes, credentials: list[bytes]) -> tuple[bool, bytes, str]:
        """(admitted, user id, reason) for one handshake."""
        if mechanism == b"PLAIN" and self.secret is not None and len(credentials) == 2:
            if secrets.compare_digest(credentials[1], self.secret):
                return True, b"member", "OK"
            return False, b"", "wrong join secret"
        if mechanism == b"CURVE" and self.allow is not None and len(credentials) == 1:
            key = z85.encode(credentials[0])
            if self.allow(key):
                return True, key, "OK"
            return False, b"", f"key {key[:8].decode()}... is not on the allow-list"
        return False, b"", f"{mechanism.decode('ascii', 'replace')[:20]} is not accepted here"

    async def _serve(self) -> None:
        while True:
            request = await self._sock.recv_multipart()
            if len(request) < 8 or request[1] != b"":
                continue  # not from libzmq's ZAP client
            if not self._known.is_set() and self._pending < 64:
                self._pending += 1
                self._tasks.append(asyncio.ensure_future(self._later(request)))
            else:
                await self._answer(request)

    async def _later(self, request: list[bytes]) -> None:
        try:
            await asyncio.wait_for(self._known.wait(), HANDSHAKE_S / 2)
        except TimeoutError:
            pass
        finally:
            self._pending -= 1
        await self._answer(request)

    async def _answer(self, request: list[bytes]) -> None:
        routing, _, version, request_id, _domain, address, _identity, mechanism = request[:8]
        try:
            ok, user, reason = self.admit(mechanism, request[8:])
        except Exception as exc:  # noqa: BLE001 - the gate never dies; refuse
            ok, user, reason = False, b"", f"bad request ({type(exc).__name__}: {exc})"
        if not ok:
            self.refusals += 1
            if self.refusals <= 5 or self.refusals % 100 == 0:
                log.warning("%s refused a connection from %s: %s (%d refused so far)",
                            self.what, address.decode("utf-8", "replace"), reason,
                            self.refusals)
        await self._sock.send_multipart([routing, b"", version, request_id,
                                         b"200" if ok else b"400",
                                         b"OK" if ok else reason.encode()[:200], user, b""])

    def watch(self, sock: zmq.asyncio.Socket, where: str) -> Doorkeeper:
        """Bound and watch the connections of listening socket ``sock`` (call before it
        accepts any): at most ``PENDING_LIMIT`` of them in their handshake
        (``transport.doorkeeper``), and count and log handshakes that fail before any ZAP
        request (a CURVE client with no key or the wrong server key; a stranger's protocol).
        Returns the watcher: cancel it when ``sock`` closes (``close`` cancels every one
        left); set its ``where`` once the socket's port is known."""
        # A fresh endpoint each time: pyzmq's default is named after the socket's descriptor,
        # which the next socket reuses while the closed one's monitor may still be bound (a
        # node joining again after a regroup died on "Address already in use").
        watcher = Doorkeeper(sock, f"inproc://vastray-monitor-{next(_MONITORS)}", where,
                             HANDSHAKE_S, on_failed=lambda event: self._failed(event,
                                                                               watcher.where))
        self._watchers = [w for w in self._watchers if not w.done()] + [watcher]
        return watcher

    def _failed(self, event: dict, where: str) -> None:
        self.failed_handshakes += 1
        n = self.failed_handshakes
        if n <= 5 or n % 100 == 0:
            log.warning("a handshake on %s failed before authentication (%s; %d so far): a "
                        "client without keys, with another coordinator key, not speaking "
                        "ZeroMQ, or turned away", where,
                        "protocol error" if event["event"] & zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
                        else "no detail", n)

    def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for watcher in self._watchers:
            watcher.cancel()
        self._sock.close(linger=0)
