"""A node's management actor: its ZeroMQ endpoint. It owns the node's sockets, routes what
arrives into mailboxes by kind, checks who sent what, and sends to the coordinator and to
peers."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import time

import zmq
import zmq.asyncio
from zmq.utils.monitor import parse_monitor_message

from vastray.actors import protocol
from vastray.actors.liveness import BUSY_GRACE, CpuWitness
from vastray.transport.codec import PEER_FRAME_LIMIT, CodecError, decode
from vastray.transport.security import FRAME_OVERHEAD, Credentials, Gate, connect_as, serve

log = logging.getLogger(__name__)

#: Numbers the monitor endpoints of coordinator sockets: a fresh one each job, since pyzmq's
#: default names it after the socket's descriptor, which the next job's socket may reuse.
_HANDSHAKE_MONITORS = itertools.count()


class AuthenticationFailed(RuntimeError):
    """The coordinator refused this node's CURVE handshake."""


class _Mailbox(asyncio.Queue):
    """An unbounded mailbox that knows how many bytes of messages it holds."""

    def _init(self, maxsize):
        super()._init(maxsize)
        self.nbytes = 0

    def _put(self, item):
        super()._put(item)
        self.nbytes += item_nbytes(item)

    def _get(self):
        item = super()._get()
        self.nbytes -= item_nbytes(item)
        return item


def item_nbytes(message) -> int:
    return sum(a.nbytes for a in message.arrays.values())


class ManagementActor:
    """Owns the node's sockets: a ROUTER for peers, a DEALER to the coordinator, and a DEALER
    connected to each peer's ROUTER. Incoming messages go to mailboxes by kind.

    Data flows from a ROUTER to the DEALERs connected to it: a node sends to peer r on its own
    ROUTER, to the connection r made (its routing id names the pair's token), and receives
    from peer r on the DEALER it connected to r. So the only listening socket, the one a
    stranger can reach, takes small frames (``FRAME_LIMIT``: what an unauthenticated
    connection can make it hold), while ray batches and films arrive in large frames
    (``PEER_FRAME_LIMIT``) on connecting sockets, which admit no stranger: a field cut into
    128 KiB frames had to be copied back together on arrival, and ray batches between nodes
    moved at 0.6 of raw ZeroMQ's speed (issue 37).

    The receive path never waits and never dies: a mailbox has no count limit, so a kind whose
    reader is busy never holds back another kind, and a node sending to a peer is never
    blocked by a peer that is itself blocked sending (the deadlock of bounded mailboxes).

    Who may send is settled in layers. The handshake admits only members of the job (the join
    secret, or with keys a key on the allow-list for the coordinator and a member's key for
    peers); nothing else ever reaches this code. Each peer message then carries the token
    this node shares with its sender alone (``peer_tokens``, from the job), which names the
    sender's rank; the rank in the message must be that one, and so must the rank the
    connection it came over was made to (with keys, whose CURVE key the handshake checked),
    and the kind must be one that rank may send now (``protocol.check_peer_kind``: a film
    only from a tree child, once per unit; an all-reduce partial only from its step's
    butterfly partner). Ray batches name only domains of the job. A message that fails any
    check is dropped, logged at a bounded rate and counted in ``rejections`` (the node's report).

    Parameters
    ----------
    credentials : this node's keys, or the join secret.
    """

    def __init__(self, ctx: zmq.asyncio.Context, coordinator: str, bind_host: str,
                 advertise: str, timeout: float, credentials: Credentials, gate: Gate):
        self.ctx = ctx
        self.timeout = timeout
        self.credentials = credentials
        self.gate = gate
        self.token: bytes | None = None  # the coordinator channel's, from the job
        self.rejections = protocol.Rejections()
        self.router = ctx.socket(zmq.ROUTER)
        serve(self.router, credentials)
        # a send to a peer not (yet) connected, or whose queue is full, fails rather than
        # dropping the message; a peer's reconnection takes its routing id over
        self.router.setsockopt(zmq.ROUTER_MANDATORY, 1)
        self.router.setsockopt(zmq.ROUTER_HANDOVER, 1)
        self._watcher = gate.watch(self.router, "this node's peer port")
        port = self.router.bind_to_random_port(f"tcp://{bind_host}")
        self.endpoint = f"tcp://{advertise}:{port}"
        keys = credentials.keys
        self.coordinator = self.ctx.socket(zmq.DEALER)
        connect_as(self.coordinator, credentials, keys.coordinator_public if keys else None)
        # Watched before it connects: a refused handshake is never tried again, so its one
        # event, raised by ZeroMQ's I/O thread as soon as the coordinator answers, would be
        # lost to a monitor attached later (a node on a busy machine then waited out its
        # timeout instead of saying "authentication failed").
        self._handshake_events = self.coordinator.get_monitor_socket(
            zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
            | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL,
            addr=f"inproc://vastray-handshake-{next(_HANDSHAKE_MONITORS)}")
        self.coordinator.connect(coordinator)
        self.coordinator_heard = time.monotonic()
        self.inbound: dict[int, zmq.asyncio.Socket] = {}  # connected to each peer, by rank
        self._send_locks: dict[int, asyncio.Lock] = {}  # one send at a time to each peer
        self.rank, self.size = -1, 0
        self.endpoints: list[str] = []  # every node's endpoint, by rank (from the job)
        self.peer_tokens: list[bytes] = []  # the token shared with each rank (from the job)
        self.peer_ranks: dict[bytes, int] = {}
        self.peer_keys: list[bytes] = []  # each rank's CURVE public key (with keys)
        self.n_domains = 0
        self.films_taken: set[tuple[int, int]] = set()  # (child rank, unit ordinal)
        self.n_units = 0  # the job's units (passes of frames): a film's ordinal is below it
        self._waits = 0  # waits for other processes under way (``wait_any``)
        self.waiting_since: float | None = None
        self.mailboxes: dict[str, _Mailbox] = {}
        self._tasks = [asyncio.ensure_future(self._route(self.router, self._take_on_port)),
                       asyncio.ensure_future(self._route(self.coordinator,
                                                         self._take_control))]

    def mailbox(self, kind: str) -> _Mailbox:
        return self.mailboxes.setdefault(kind, _Mailbox())

    async def _route(self, sock: zmq.asyncio.Socket, take) -> None:
        while True:
            frames = await sock.recv_multipart(copy=False)
            try:
                take(frames)
            except Exception as exc:  # noqa: BLE001 - the receive path must never die
                self.rejections.add("internal", f"{type(exc).__name__}: {exc}")
            # A receive that finds a message waiting completes without yielding to the event
            # loop: under a flood this loop would starve the heartbeat (the node then looked
            # stalled to its coordinator in one CI run of the flood test). Yield each time.
            await asyncio.sleep(0)

    def _take_control(self, frames: list) -> None:
        """Check one message from the coordinator and deliver it, or drop it."""
        if len(frames) < 2:
            self.rejections.add("malformed", "no token or header frame")
            return
        token = frames[0].bytes
        if self.token is not None and token != self.token:
            # once the job is known its control messages (a regroup above all) must carry
            # the job's token: none of an earlier connection's may act on this job
            self.rejections.add("stranger", "a control message without this job's token")
            return
        self.coordinator_heard = time.monotonic()
        try:
            message = decode(frames[1:])
            protocol.check(message, protocol.FROM_COORDINATOR)
        except (CodecError, protocol.ProtocolError) as exc:
            self.rejections.add("malformed", str(exc))
            return
        if message.kind == protocol.HEARTBEAT:
            return
        if message.kind == protocol.JOB and self.token is None:
            try:
                self.join(token, message.meta)
            except protocol.ProtocolError as exc:
                self.rejections.add("malformed", f"job: {exc}")
                return
        self._deliver(message)

    def join(self, token: bytes, job: dict) -> None:
        """Learn the job: the coordinator channel's token, this node's rank, its peers (their
        endpoints, the token shared with each, their keys), then check the peer messages held
        back.

        Raises
        ------
        ProtocolError
            For a job whose peer lists do not match its size.
        """
        size, rank = int(job["size"]), int(job["rank"])
        tokens = job.get("peer_tokens")
        keys = job.get("keys") or []
        if not (0 <= rank < size and len(job["endpoints"]) == size
                and isinstance(tokens, list) and len(tokens) == size
                and all(isinstance(t, bytes) and len(t) >= 16 for t in tokens)
                and len(set(tokens)) == size
                and (not self.credentials.curve or (
                    len(keys) == size and all(isinstance(k, bytes) for k in keys)))):
            raise protocol.ProtocolError("rank, endpoints, peer tokens or keys do not fit "
                                         "the job's size")
        self.token, self.rank, self.size = token, rank, size
        self.endpoints = list(job["endpoints"])
        self.peer_tokens = tokens
        self.peer_ranks = {t: r for r, t in enumerate(tokens)}
        self.peer_keys = list(keys)
        if self.credentials.curve:
            self.gate.open(frozenset(self.peer_keys).__contains__)
        self.n_domains = int(job.get("domains", 0))
        self.n_units = len(job["units"])
        for peer, endpoint in enumerate(self.endpoints):
            if peer != rank:
                self._connect_to_peer(peer, endpoint)

    def _connect_to_peer(self, peer: int, endpoint: str) -> None:
        """Connect the socket this node receives from ``peer`` on: large frames (only ``peer``
        speaks on it; with keys the handshake checks that its key is ``peer``'s), and the
        routing id ``peer`` sends to this node by (the pair's token)."""
        sock = self.ctx.socket(zmq.DEALER)
        connect_as(sock, self.credentials, self.peer_keys[peer] if self.peer_keys else None)
        sock.setsockopt(zmq.MAXMSGSIZE, PEER_FRAME_LIMIT + FRAME_OVERHEAD)
        sock.setsockopt(zmq.ROUTING_ID, routing_id(self.peer_tokens[peer]))
        sock.connect(endpoint)
        self.inbound[peer] = sock
        self._tasks.append(asyncio.ensure_future(self._route(
            sock, lambda frames: self._take_peer(frames, peer))))

    def _take_on_port(self, frames: list) -> None:
        """A message on the peer port: none is expected (peers send on the connections this
        node accepts, never on them), so it is dropped and counted."""
        self.rejections.add("malformed", "a message on the peer port, which only sends")

    def _take_peer(self, frames: list, peer: int) -> None:
        """Check one message (``[token, header, frame, ...]``) that came over the connection
        to ``peer`` and deliver it, or drop it."""
        if len(frames) < 2:
            self.rejections.add("malformed", "no token or header frame")
            return
        sender = self.peer_ranks.get(frames[0].bytes)
        if sender is None:
            self.rejections.add("stranger", "a peer message without a token of this job")
            return
        if sender != peer:
            self.rejections.add("impersonation", f"node {sender}'s token from node {peer}")
            return
        try:
            message = decode(frames[1:])
            protocol.check(message, protocol.FROM_PEER)
            if message.meta["rank"] != sender:
                raise protocol.ProtocolError(f"node {sender} spoke for rank "
                                             f"{message.meta['rank']}")
            protocol.check_peer_kind(message, sender, self.rank, self.size)
            if message.kind == protocol.RAYS:
                protocol.check_ray_ids(message, self.n_domains)
            if message.kind == protocol.FILM:
                once = (sender, int(message.meta.get("ordinal", 0)))
                if not 0 <= once[1] < self.n_units:
                    # a child may run ahead, so later units' films are kept until reduced:
                    # but only those of units the job has
                    raise protocol.ProtocolError(f"a film from node {sender} for unit "
                                                 f"{once[1]} of a job of {self.n_units}")
                if once in self.films_taken:
                    raise protocol.ProtocolError(f"a second film from node {sender} for "
                                                 f"unit {once[1]}")
                self.films_taken.add(once)
        except (CodecError, protocol.ProtocolError) as exc:
            self.rejections.add("malformed", str(exc))
            return
        self._deliver(message)

    def _deliver(self, message) -> None:
        held = sum(box.nbytes for box in self.mailboxes.values())
        if held + item_nbytes(message) > protocol.UNDELIVERED_BUDGET:
            self.rejections.add("budget", f"{held} bytes already undelivered")
            return
        self.mailbox(message.kind).put_nowait(message)

    async def watch_coordinator(self, silence: float) -> None:
        """Exit the process once the coordinator has been silent for ``silence`` seconds: it
        died or was cut off, and a node must not render on for nobody. (The render worker
        thread cannot be cancelled, so this ends the process rather than the task.)

        On a starved machine silence alone is no verdict: messages already waiting on the
        socket mean this node's own loop is behind, and a coordinator that started this node
        (its parent) and still uses CPU is slow, not lost (for up to ``BUSY_GRACE`` times
        ``silence``)."""
        parent_env = os.environ.get(protocol.PARENT_PID_ENV)
        parent = None if parent_env is None else int(parent_env)
        witness = CpuWitness(silence / 2)
        while True:
            await asyncio.sleep(0.25)
            now = time.monotonic()
            quiet = now - self.coordinator_heard
            if quiet <= silence:
                if parent is not None:
                    witness.forget(parent)
                continue
            if quiet < BUSY_GRACE * silence and (
                    self.coordinator.getsockopt(zmq.EVENTS) & zmq.POLLIN
                    or (parent is not None and witness.busy(parent, now))):
                # Its messages wait here unread (this node is the one behind), or the
                # coordinator that started this node still works: slow, not lost.
                continue
            log.error("lost the coordinator (silent for %.1f s); exiting", quiet)
            logging.shutdown()
            os._exit(4)

    async def watch_handshake(self, endpoint: str) -> None:
        """Raise ``AuthenticationFailed`` if the coordinator refuses this node's CURVE
        handshake (other keys); returns never otherwise."""
        monitor = self._handshake_events
        unclear = 0
        try:
            while True:
                event = parse_monitor_message(await monitor.recv_multipart())
                if event["event"] & (zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
                                     | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL):
                    # A refusal (other mechanism, other keys) repeats on every reconnect; a
                    # single one can also be a connection to a coordinator socket that is
                    # closing (the last job's, after a regroup): wait for the repeat.
                    unclear += 1
                    log.info("handshake with %s failed (event %d), %d time(s)", endpoint,
                             event["event"], unclear)
                if event["event"] & zmq.EVENT_HANDSHAKE_FAILED_AUTH or unclear >= 3:
                    raise AuthenticationFailed(
                        f"authentication with the coordinator at {endpoint} failed: this "
                        "node's key is not on its allow-list (KEYS/public), or its key is not "
                        "the one in this node's KEYS/coordinator.pub, or one side has no keys")
        finally:  # the socket may be closed already when the node stops on an error
            if not self.coordinator.closed:
                self.coordinator.disable_monitor()
            monitor.close(linger=0)

    async def receive(self, kind: str, what: str):
        """The next message of ``kind``. The wait lasts as long as the coordinator speaks (its
        heartbeats): a node done with its share, waiting for the stop, a grant or a slower
        peer's film or rays, is idle, not lost, and never gives up while its job goes on
        (issue 42: nodes done early quit after the node timeout, and the frame was rendered
        again). It fails once the coordinator has been silent for the node timeout (at least
        that long after the wait began)."""
        box = self.mailbox(kind)
        if not box.empty():
            # a message already here needs no waiting task (it cost as much as the message's
            # own checks); yield once all the same, so that a node fed faster than it reads
            # still lets its heartbeat and its sockets' tasks run
            await asyncio.sleep(0)
            if not box.empty():
                return box.get_nowait()
        getter = asyncio.ensure_future(box.get())
        try:
            await self.wait_any([getter], what)
            return getter.result()
        finally:
            getter.cancel()

    async def wait_any(self, futures: list, what: str) -> set:
        """Wait until one of ``futures`` is done (returns those done), as ``receive`` waits:
        while the coordinator speaks, however long. Meanwhile the node's heartbeats say how
        long it has been waiting (``waiting_s``), so that the coordinator can tell a job in
        which every node waits for another (peers cut off from each other) from one in which
        some node still works, and end the first."""
        start = time.monotonic()
        with self._waiting():
            while True:
                left = max(self.coordinator_heard, start) + self.timeout - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no {what} within {self.timeout:.0f} s, the coordinator "
                                       "silent that long")
                done, _ = await asyncio.wait(futures, timeout=left,
                                             return_when=asyncio.FIRST_COMPLETED)
                if done:
                    return done

    @contextlib.contextmanager
    def _waiting(self):
        """While inside, this node waits for another (``waiting_s`` counts)."""
        self._waits += 1
        if self._waits == 1:
            self.waiting_since = time.monotonic()
        try:
            yield
        finally:
            self._waits -= 1
            if self._waits == 0:
                self.waiting_since = None

    def waiting_s(self) -> float:
        """Seconds this node has been waiting for others without a break (0: working)."""
        since = self.waiting_since
        return 0.0 if since is None else round(time.monotonic() - since, 2)

    async def to_coordinator(self, frames: list) -> None:
        """Send a message to the coordinator, behind the job token frame."""
        await asyncio.wait_for(self.coordinator.send_multipart(
            [self.token or b"", *frames], copy=False), self.timeout)

    async def repeat_to_coordinator(self, frames: list) -> None:
        """Send a message to the coordinator again every heartbeat, never waiting: a repeat
        that finds the queue full (no coordinator yet) is skipped."""
        while True:
            await asyncio.sleep(protocol.HEARTBEAT_S)
            try:
                await self.coordinator.send_multipart([self.token or b"", *frames],
                                                      flags=zmq.NOBLOCK, copy=False)
            except zmq.Again:
                pass

    async def to_peer(self, rank: int, frames: list) -> None:
        """Send a message to node ``rank``, behind the token this node shares with it, on the
        connection ``rank`` made to this node. Until it has connected, or while its queue is
        full, the send is tried again (every 1 to 50 ms) for up to the node timeout.

        Raises
        ------
        TimeoutError
            If ``rank`` took no message for the node timeout.
        """
        token = self.peer_tokens[rank]
        message = [routing_id(token), token, *frames]
        # one send to a peer at a time: a message retried while the peer's queue is full must
        # not be overtaken by a later one to the same peer (each pair's messages stay in
        # order, as on the one socket a pair had before)
        async with self._send_locks.setdefault(rank, asyncio.Lock()):
            if await self._send_now(message):
                return
            deadline = time.monotonic() + self.timeout
            pause = 0.001
            with self._waiting():  # on another node: a job whose nodes all wait is ended
                while not await self._send_now(message):
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise TimeoutError(f"node {rank} took no message within "
                                           f"{self.timeout:.0f} s (not connected to this "
                                           "node, or not reading)")
                    await asyncio.sleep(min(pause, left))
                    pause = min(2 * pause, 0.05)

    async def _send_now(self, message: list) -> bool:
        """Send on the peer port if the peer can take it now (False: not connected yet, or
        its queue is full)."""
        try:
            await self.router.send_multipart(message, flags=zmq.NOBLOCK, copy=False)
            return True
        except zmq.Again:
            return False
        except zmq.ZMQError as exc:
            if exc.errno != zmq.EHOSTUNREACH:
                raise
            return False

    def close(self) -> None:
        for task in [*self._tasks, self._watcher]:
            task.cancel()
        if not self.coordinator.closed:
            self.coordinator.disable_monitor()
        for sock in [self.router, self.coordinator, self._handshake_events,
                     *self.inbound.values()]:
            sock.close(linger=0)


def routing_id(token: bytes) -> bytes:
    """The routing id of a pair's connection (ZeroMQ reserves ids that begin with a zero
    byte, which a random token may)."""
    return b"p" + token
