"""A bound on the connections a listening socket holds before they authenticate.

ZeroMQ has no limit on how many connections a listener accepts, and each one may make it hold
a handshake frame of up to ``MAXMSGSIZE`` bytes (``transport.codec.FRAME_LIMIT``) until the
handshake ends, at most ``HANDSHAKE_S`` later. So the memory an outsider can pin is
(connections it keeps pending) x (frame limit + ZeroMQ's ~24 KB per connection): 500 raw
connections of 4 MiB frames made a node hold 2 GB. Bounding the frame alone does not bound the
product; the ``Doorkeeper`` bounds the other factor.

How: it reads the listener's socket monitor in a thread of its own (so a render holding the
event loop does not delay it) and keeps the descriptors of connections accepted less than
``HANDSHAKE_S`` ago that are still open: every connection still in its handshake is among
them, since ZeroMQ drops a handshake that takes longer. Those less the handshakes that
succeeded in that time (the monitor does not say which connection succeeded, only that one
did; an outsider cannot succeed, so at worst a member's success lets one more outsider in)
are the pending ones. When a newly accepted connection would make more than ``limit`` pending,
it is shut down at once (``shutdown(2)`` on ZeroMQ's descriptor: ZeroMQ reads the end of the
stream and closes the connection as if the peer had). So members joining together are never
turned away for one another, however many.
A member turned away this way is reconnected by ZeroMQ a moment later and admitted once the
flood's connections have ended (each within ``HANDSHAKE_S``); connections that have
authenticated are never touched after ``HANDSHAKE_S``.

The monitor reports a descriptor, not a connection, and a descriptor number is reused once
closed: before a shutdown the descriptor is checked to be a connected TCP socket on this
listener's port, so what is shut down is at worst another connection this listener accepted
in the same instant, never a file or an outgoing connection.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections import OrderedDict, deque

import zmq
from zmq.utils.monitor import parse_monitor_message

log = logging.getLogger(__name__)

#: Connections a listener holds in their handshake (each may hold up to the frame limit before
#: it authenticates: 160 of them held 35-37 MB, measured with 1,000 connections).
PENDING_LIMIT = 160

_EVENTS = (zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED
           | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL)
_FAILED = zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL


class Doorkeeper:
    """Watches one listening socket: counts handshakes that fail before authentication and
    turns away connections beyond ``limit`` young ones.

    Parameters
    ----------
    sock : the listening socket (any pyzmq socket; its monitor is set here, on the caller's
        thread, which must be the socket's).
    where : how log lines name the socket.
    window : seconds a connection counts as young (the handshake's time limit).
    limit : most young connections held at once.
    on_failed : called (in the doorkeeper's thread) with the event of each failed handshake.
    """

    def __init__(self, sock: zmq.Socket, monitor_address: str, where: str, window: float,
                 limit: int = PENDING_LIMIT, on_failed=None):
        self.where, self.window, self.limit = where, window, limit
        self.turned_away = 0
        self._on_failed = on_failed
        self._young: OrderedDict[int, float] = OrderedDict()  # descriptor -> accepted at
        self._succeeded: deque[float] = deque()  # when handshakes succeeded
        self._sock = sock
        sock.monitor(monitor_address, _EVENTS)
        # A blocking socket of the same context, read by the thread alone.
        self._pair = zmq.Context.shadow(sock.context.underlying).socket(zmq.PAIR)
        self._pair.linger = 0
        self._pair.connect(monitor_address)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"doorkeeper {where}",
                                         daemon=True)
        self._thread.start()

    def done(self) -> bool:
        return not self._thread.is_alive()

    def cancel(self) -> None:
        """Stop watching (call on the socket's thread; the socket may be closed already)."""
        self._stop.set()
        if not self._sock.closed:
            try:
                self._sock.disable_monitor()
            except zmq.ZMQError:
                pass

    def _run(self) -> None:
        pair = self._pair
        try:
            while not self._stop.is_set():
                if not pair.poll(200):
                    continue
                # Every event queued so far, its successes counted first: a connection whose
                # ACCEPTED is read late may have authenticated meanwhile (its success is
                # queued behind), and turning it away then would lose what it already sent.
                # Counting successes early never admits more than the limit of connections
                # that have not authenticated: each one counted is a real success.
                events = [parse_monitor_message(pair.recv_multipart())]
                while len(events) < 1024 and pair.poll(0):
                    events.append(parse_monitor_message(pair.recv_multipart()))
                events.sort(key=lambda e: e["event"] != zmq.EVENT_HANDSHAKE_SUCCEEDED)
                if any(e["event"] == zmq.EVENT_MONITOR_STOPPED for e in events):
                    break
                for event in events:
                    try:
                        self._take(event)
                    except Exception:  # noqa: BLE001 - keep reading: unread events pile up
                        log.exception("%s: a monitor event could not be taken", self.where)
        except zmq.ZMQError:
            pass  # the context was terminated: the process is closing its sockets
        finally:
            pair.close(linger=0)

    def _take(self, event: dict) -> None:
        kind, fd = event["event"], event["value"]
        if kind == zmq.EVENT_ACCEPTED:
            now = time.monotonic()
            while self._young and next(iter(self._young.values())) < now - self.window:
                self._young.popitem(last=False)
            while self._succeeded and self._succeeded[0] < now - self.window:
                self._succeeded.popleft()
            if len(self._young) - len(self._succeeded) >= self.limit:
                self._turn_away(fd, event["endpoint"])
            else:
                self._young[fd] = now
        elif kind == zmq.EVENT_HANDSHAKE_SUCCEEDED:
            self._succeeded.append(time.monotonic())
        elif kind == zmq.EVENT_DISCONNECTED:
            self._young.pop(fd, None)
        elif kind & _FAILED and self._on_failed is not None:
            self._on_failed(event)

    def _turn_away(self, fd: int, endpoint: bytes) -> None:
        try:
            port = int(endpoint.decode("ascii", "replace").rpartition(":")[2])
        except ValueError:
            return  # not a TCP endpoint
        try:
            dup = os.dup(fd)
        except OSError:
            return  # closed already
        try:
            conn = socket.socket(fileno=dup)
        except OSError:
            os.close(dup)
            return  # not a socket any more
        try:
            if conn.type == socket.SOCK_STREAM and conn.getsockname()[1] == port:
                conn.getpeername()  # connected (not a listener): raises otherwise
                conn.shutdown(socket.SHUT_RDWR)
                self.turned_away += 1
                n = self.turned_away
                if n <= 5 or n % 1000 == 0:
                    log.warning("%s holds %d connections that may still be authenticating: "
                                "turned one away (%d so far; a member is reconnected by "
                                "ZeroMQ)", self.where, self.limit, n)
        except OSError:
            pass  # not this listener's connection any more
        finally:
            conn.close()  # the duplicate only: ZeroMQ closes its own descriptor
