"""The coordinator's watch over its nodes: which joined (and with what hello), whether each is
alive (exits, silence past the heartbeat timeout, a node's own report of failure), and which
messages are admitted at all; the error that names the node lost."""

from __future__ import annotations

import asyncio
import logging
import subprocess
import time
from pathlib import Path

from vastray.actors import protocol
from vastray.actors.liveness import BUSY_GRACE, HUNG_CPU_SHARE, CpuWitness
from vastray.actors.node_failure import NodeFailure, NodeLost, exit_cause
from vastray.scene.errors import InputError
from vastray.transport.codec import CodecError, decode

log = logging.getLogger(__name__)


def _hello(body: list):
    """The message, where an undecoded one is a hello (a member repeats its hello, with
    whatever token it had, until its job comes); else None."""
    try:
        message = decode(body)
    except CodecError:
        return None
    return message if message.kind == protocol.HELLO else None


def _number(value) -> bool:
    """Whether a message's meta value is a finite number (not a bool)."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and value == value and abs(value) != float("inf"))


class Watch:
    """Receives from the coordinator socket while watching the nodes: child processes that
    exit, and any node silent for longer than the timeout (heartbeats come every second)."""

    def __init__(self, size: int, procs: list[subprocess.Popen], log_paths: list[Path],
                 timeout: float,
                 launched: dict[str, tuple[subprocess.Popen, Path]], address: str = "",
                 token: bytes = b"",
                 heartbeat_timeout: float | None = None, spare_exits: int = 0,
                 regrouping: bool = False):
        self.size, self.procs, self.log_paths, self.timeout = size, procs, log_paths, timeout
        self.regrouping = regrouping  # the survivors of a node loss are to join again
        self.heartbeat_timeout = heartbeat_timeout or timeout
        self.launched, self.address = dict(launched), address
        self.token = token
        self.user_ids: dict[bytes, bytes] = {}  # socket identity -> CURVE key, of hellos
        self.started = time.monotonic()
        self.last_heard = [self.started] * size
        self.ranks_joined: set[int] = set()
        self.last_join = self.started
        self.job_sent = False
        #: rank -> (seconds it had been waiting for others, when it said so), from its
        #: heartbeats: nodes wait for one another as long as the coordinator speaks, so a job
        #: in which every node waits (peers cut off from each other) ends here
        self.waiting: dict[int, tuple[float, float]] = {}
        self.members: dict[bytes, int] = {}  # socket identity -> rank
        self.once: set[tuple[str, int]] = set()
        self.rejections = protocol.Rejections()
        #: members' messages taken, by kind: what the coordinator still does per round shows
        #: here (the report's ``coordinator_messages``)
        self.kinds: dict[str, int] = {}
        self.spare_exits = spare_exits  # launched sessions of earlier lost nodes may exit
        self.hellos: dict[int, dict] = {}
        self.last_check = self.started
        #: whether a silent node started here still uses CPU (windows of half a timeout)
        self._cpu = CpuWitness(self.heartbeat_timeout / 2)
        #: rank -> (when, its CPU seconds then) since which a node that heartbeats, and is not
        #: waiting for others, has used under HUNG_CPU_SHARE of a core: a hung render thread
        self._idle_since: dict[int, tuple[float, float]] = {}

    def joined(self, rank: int, identity: bytes, hello: dict | None = None) -> None:
        self.ranks_joined.add(rank)
        self.members[identity] = rank
        self.hellos[rank] = hello or {}
        self.last_join = time.monotonic()
        self.heard(rank)

    def job_out(self) -> None:
        """Every node has its job: from now on each must heartbeat."""
        self.job_sent = True
        self.last_heard = [time.monotonic()] * self.size
        self._idle_since.clear()

    def beat(self, rank: int, waiting: float, cpu: float | None) -> None:
        """A heartbeat of node ``rank``: how long it has waited for others (``waiting_s``)
        and its process's CPU seconds (``cpu_s``; None from a node that does not say). The
        node counts as working while it waits, or while its CPU time grows by at least
        ``HUNG_CPU_SHARE`` of the time since it last did."""
        now = time.monotonic()
        self.waiting[rank] = (waiting, now)
        since = self._idle_since.get(rank)
        if (cpu is None or waiting > 0 or since is None
                or cpu - since[1] >= HUNG_CPU_SHARE * (now - since[0])):
            self._idle_since[rank] = (now, cpu if cpu is not None else 0.0)

    def _hung(self, rank: int, now: float) -> bool:
        """Whether node ``rank`` heartbeats but has used almost no CPU, without waiting for
        others, for longer than the node timeout."""
        since = self._idle_since.get(rank)
        return since is not None and now - since[0] > self.timeout

    def heard(self, rank: int) -> None:
        self.last_heard[rank] = time.monotonic()
        if rank < len(self.procs):
            self._cpu.forget(self.procs[rank].pid)

    def _working(self, rank: int, since: float, limit: float, now: float) -> bool:
        """Whether node ``rank``, a process started here, is still using the CPU, waited on
        since ``since`` for at most ``BUSY_GRACE`` times ``limit`` (so it is slow, not stuck).

        A node's start (imports, kernel warm-up) or its event loop (numba compiling on a cold
        cache) can be held up past a limit on a machine kept busy by other jobs; a stopped or
        hung node uses no CPU. Only for processes started here (their CPU time is in /proc)."""
        return (rank < len(self.procs) and now - since <= BUSY_GRACE * limit
                and self._cpu.busy(self.procs[rank].pid, now))

    def _starting(self, rank: int, now: float) -> bool:
        """Whether node ``rank``, started here and not yet joined, is still starting (for at
        most ``BUSY_GRACE`` node timeouts)."""
        return self._working(rank, self.started, self.timeout, now)

    def _busy_here(self, rank: int, now: float) -> bool:
        """Whether node ``rank``, started here and silent, is still working (for at most
        ``BUSY_GRACE`` heartbeat timeouts of silence)."""
        return self._working(rank, self.last_heard[rank], self.heartbeat_timeout, now)

    def _failure(self, rank: int, why: str, kind: type = NodeFailure,
                 cause: str = "lost", log_tail: bool = True) -> NodeFailure:
        """The error for node ``rank``; ``log_tail``: a local node's last log line is appended
        (its own words on why it exited), not where ``why`` already says it."""
        if rank < len(self.procs):
            last = ""
            if log_tail:
                text = self.log_paths[rank].read_text(errors="replace").strip()
                last = f": {text.splitlines()[-1] if text else 'no output'}"
            failure = kind(f"node {rank} (pid {self.procs[rank].pid}) {why}{last}")
        else:
            hello = self.hellos.get(rank, {})
            where = (f" (pid {hello['pid']} on {hello.get('host', '?')})" if "pid" in hello
                     else "")
            failure = kind(f"node {rank}{where} {why}")
        if isinstance(failure, NodeLost):
            failure.rank = rank
            failure.cause = cause
        return failure

    def failed(self, rank: int, error: str, bad_input: bool = False) -> Exception:
        """A node's report that its job failed: lost, like a node that exits mid-frame; but
        where a node started here failed on the input (``bad_input``: the store or a file
        this machine's other nodes read too, such as a damaged domain), the render fails at
        once with that error (``InputError``) rather than rendering the frame again on nodes
        that would meet it in turn."""
        if bad_input and rank < len(self.procs):
            return InputError(None, f"node {rank} (pid {self.procs[rank].pid}): "
                                    f"{error.removeprefix('InputError: ')}")
        return self._failure(rank, f"failed: {error}", NodeLost, cause="failed", log_tail=False)

    def check(self, judge_silence: bool = True) -> None:
        """Raise for a node that exited, never joined, or (``judge_silence``) went silent."""
        now = self.last_check = time.monotonic()
        for rank, proc in enumerate(self.procs):
            code = proc.poll()
            if code is not None and code != 0:
                # A joined node, or one killed by a signal (kill -9, the OOM killer), is a
                # loss the others can make up for; a node failing its start is not.
                lost = rank in self.ranks_joined or code < 0
                how = f" ({exit_cause(code)})" if code < 0 else ""
                raise self._failure(rank, f"exited with code {code}{how}",
                                    NodeLost if lost else NodeFailure, cause=exit_cause(code))
        for name, (proc, log) in list(self.launched.items()):
            code = proc.poll()
            if code is not None and code != 0:
                if self.spare_exits > 0:  # the session of a node lost before: no news
                    self.spare_exits -= 1
                    del self.launched[name]
                    continue
                text = Path(log).read_text(errors="replace").strip() if Path(log).exists() else ""
                last = text.splitlines()[-1] if text else "no output"
                # mid-frame, a lost node the others can make up for; before, a failed start
                failure = (NodeLost if self.job_sent else NodeFailure)(
                    f"node on {name} exited with code {code}: {last}")
                failure.cause = exit_cause(code)
                raise failure
        waiting = set(range(len(self.procs))) - self.ranks_joined
        # a node started here that still uses CPU is starting (importing, warming its kernels
        # on a starved machine), not stuck: it is given up to BUSY_GRACE limits to join
        stuck = {r for r in waiting if not self._starting(r, now)}
        if self.ranks_joined and stuck and now - self.last_join > self.heartbeat_timeout:
            # the others joined long ago: a node started here that has not is stuck
            raise self._failure(min(stuck), f"did not join within "
                                            f"{self.heartbeat_timeout:.0f} s of the others "
                                            "(stalled)", NodeLost, cause="stalled")
        late = len(self.ranks_joined) < self.size and now - self.started > self.timeout
        if late and self.procs:  # nodes started here: name one that never said hello
            blamed = (set(range(self.size)) - self.ranks_joined - waiting) | stuck
            if blamed:  # (none while every one missing is still starting)
                raise self._failure(min(blamed), f"did not join within "
                                                 f"{now - self.started:.0f} s")
        elif late:
            joined = len(self.ranks_joined)
            if self.regrouping:
                raise NodeFailure(
                    f"after the node loss, "
                    f"{'no' if joined == 0 else f'only {joined} of the {self.size}'} surviving "
                    f"node(s) joined again within {self.timeout:.0f} s on {self.address}; the "
                    "others ended or lost this coordinator (see their logs)")
            raise NodeFailure(
                f"{'no node' if joined == 0 else f'only {joined} of {self.size} nodes'} joined "
                f"within {self.timeout:.0f} s on {self.address}; check that each node's "
                "--coordinator names this address and that its --keys match this run's "
                "(a node with other keys is refused and says 'authentication failed')")
        # Nodes heartbeat once they have the job; until then a joined node is rightly quiet.
        silent = [r for r in self.ranks_joined if judge_silence and self.job_sent
                  and now - self.last_heard[r] > self.heartbeat_timeout
                  and not self._busy_here(r, now)]
        if silent:  # blame the one silent longest: the others may only be waiting for it
            rank = min(silent, key=lambda r: self.last_heard[r])
            # a node started here that is silent but running is stalled; from elsewhere,
            # silence is all the coordinator sees of a stall or a death
            how = "stalled" if rank < len(self.procs) else "stalled or gone"
            raise self._failure(rank, f"sent nothing for {self.heartbeat_timeout:.0f} s "
                                      f"({how})", NodeLost, cause="stalled")
        hung = [r for r in self.ranks_joined if self.job_sent and self._hung(r, now)]
        if hung:
            rank = min(hung, key=lambda r: self._idle_since[r][0])
            raise self._failure(rank, f"used almost no CPU for {self.timeout:.0f} s with its "
                                      "share unfinished, though its heartbeats came (hung: "
                                      "its render thread stuck)", NodeLost, cause="stalled")
        if judge_silence and self.job_sent and self.ranks_joined and all(
                self._waited(r, now) > self.timeout for r in range(self.size)):
            raise NodeFailure(
                f"every node has waited for another for over {self.timeout:.0f} s, though "
                "all heartbeat: nodes that cannot reach each other's peer ports (a firewall "
                "between them, a wrong --advertise address); see the node logs")

    def _waited(self, rank: int, now: float) -> float:
        """How long node ``rank`` has been waiting for others without a break, by its
        last heartbeat (0 while it works)."""
        waiting, heard = self.waiting.get(rank, (0.0, now))
        return waiting + (now - heard) if waiting > 0 else 0.0

    async def receive(self, router):
        """The next message that passes ``_admit`` (as identity, message); others are dropped
        and counted in ``rejections``, and never end the wait."""
        while True:
            # Silence is judged only on an empty queue: a coordinator that was itself kept
            # off the CPU (a loaded machine) first reads the heartbeats waiting for it,
            # instead of taking their senders for stalled. Exits are checked at least once
            # a second even while messages keep coming.
            pending = await router.poll(0)
            if not pending or time.monotonic() - self.last_check > 1.0:
                self.check(judge_silence=not pending)
            if pending or await router.poll(500):
                frames = await router.recv_multipart(copy=False)
                try:
                    admitted = self._admit(frames)
                except (CodecError, protocol.ProtocolError) as exc:
                    self.rejections.add("malformed", str(exc))
                    continue
                if admitted is not None:
                    return admitted

    def _admit(self, frames: list):
        """Check one message (every connection is a member's: the handshake admitted it):
        the sender (a socket that has not joined may only say hello; a member speaks only
        for its own rank, with this attempt's token), the kind's schema, and once-only kinds
        (the film of each unit from rank 0, each rank's done). A node repeats its hello until
        its job comes; a member's repeat passes here, to be ignored."""
        if len(frames) < 3:
            raise protocol.ProtocolError("no identity, token or header frame")
        identity, token, body = frames[0].bytes, frames[1].bytes, frames[2:]
        rank = self.members.get(identity)
        if rank is not None and token != self.token:
            repeat = _hello(body)
            if repeat is None:
                self.rejections.add("stranger", f"node {rank} without this attempt's token")
                return None
            protocol.check(repeat, frozenset({protocol.HELLO}))
            return identity, repeat  # a member's repeat: the caller ignores it
        message = decode(body)
        protocol.check(message, protocol.FROM_NODE if rank is not None
                       else frozenset({protocol.HELLO}))
        if rank is None:
            self.user_ids[identity] = frames[1].get("User-Id").encode()
            return identity, message
        if message.kind == protocol.HELLO:
            return identity, message
        if message.meta.get("rank", rank) != rank:
            raise protocol.ProtocolError(f"node {rank} spoke for rank "
                                         f"{message.meta.get('rank')}")
        once = ((message.kind, rank, message.meta.get("frame"), message.meta.get("unit"))
                if message.kind in (protocol.DONE, protocol.FILM, protocol.FRAME) else None)
        if once is not None:
            if once in self.once or (message.kind == protocol.FILM and rank != 0):
                raise protocol.ProtocolError(f"a second or unexpected {message.kind} from "
                                             f"node {rank}")
            self.once.add(once)
        self.heard(rank)
        self.kinds[message.kind] = self.kinds.get(message.kind, 0) + 1
        if message.kind == protocol.HEARTBEAT:
            waiting, cpu = message.meta.get("waiting_s", 0.0), message.meta.get("cpu_s")
            if not _number(waiting):
                waiting = 0.0
            self.beat(rank, max(0.0, float(waiting)), float(cpu) if _number(cpu) else None)
        else:  # a node's film, progress or done: it works
            self._idle_since.pop(rank, None)
        return identity, message

    async def wait_exit(self, grace: float = 15.0) -> None:
        """Let the nodes started here exit after the stop. The frame is complete by now, so
        a node that hangs (stopped, say) is killed after ``grace`` seconds and one that fails
        on its way out is only logged: neither changes the result. (5 s was too short on a
        loaded machine: 4 node processes tearing down on 2 busy cores overran it in 6 of 68
        exits of a benchmark, each then reported as killed.)"""
        deadline = time.monotonic() + min(grace, self.timeout)
        while any(p.poll() is None for p in self.procs) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        for rank, proc in enumerate(self.procs):
            if proc.poll() is None:
                log.warning("node %d did not exit after the frame; killed", rank)
                proc.kill()
                proc.wait()
            elif proc.returncode != 0:
                log.warning("node %d exited with code %d after the frame", rank,
                            proc.returncode)
