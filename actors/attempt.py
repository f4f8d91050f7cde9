"""One attempt at a distributed job: listen (loopback, or ``listen`` for nodes started
elsewhere), start the nodes here or wait for them to join, send each its job, heartbeat to
them while gathering what they send, and stop them; on a node loss, tell the survivors to
regroup. The attempts themselves (one per node loss) are ``actors.coordinator``'s."""

from __future__ import annotations

import asyncio
import os
import secrets
import socket
import subprocess
import sys
from pathlib import Path

import zmq
import zmq.asyncio
from tqdm import tqdm

from vastray.actors import protocol
from vastray.actors.gather import Frames, Passes, gather, grant
from vastray.actors.node_failure import NodeFailure, NodeLost
from vastray.actors.node_logs import NodeLogs
from vastray.actors.rendezvous import write_address
from vastray.actors.watch import Watch
from vastray.render.integrators import RenderSettings
from vastray.scene.cpu_binding import node_cpu_blocks
from vastray.transport.codec import encode
from vastray.transport.join_secret import write_join_secret
from vastray.transport.keys import AllowList, CoordinatorKeys
from vastray.transport.security import Credentials, Gate, check_bind, serve


async def coordinate(job: dict, size: int, settings: RenderSettings, timeout: float,
                     listen: str | None, keys: CoordinatorKeys | None,
                     launched: dict[str, tuple[subprocess.Popen, Path]], bar: tqdm,
                     verbose: bool, rendezvous: str | os.PathLike | None = None,
                     heartbeat_timeout: float | None = None, frame_done=None,
                     regroup: bool = False, bound: dict | None = None, spare_exits: int = 0,
                     *, passes: Passes, secret: bytes, logs: NodeLogs, attempt: int = 0):
    """One attempt at the job on ``size`` nodes (``passes``: its units, see ``Passes``).
    With ``listen`` and ``regroup``, a node lost mid-frame makes the coordinator tell the
    others to regroup before ``NodeLost`` is raised; ``bound["listen"]`` gets the address
    bound, for the next attempt. Nodes authenticate with ``keys`` (only with ``listen``), or
    with the join ``secret``: handed to the nodes started here through a pipe, and left for
    nodes of this user on this machine in a file only the user can read."""
    host, _, port = (listen or "127.0.0.1:0").rpartition(":")
    credentials = (Credentials(keys=keys) if keys is not None and listen is not None
                   else Credentials(secret=secret))
    check_bind(host, credentials)
    ctx = zmq.asyncio.Context()
    allowed = AllowList(keys.allow_dir) if credentials.curve else None
    gate = Gate(ctx, secret=None if credentials.curve else secret,
                allow=None if allowed is None else lambda key: key in allowed.keys(),
                what="the coordinator")
    router = ctx.socket(zmq.ROUTER)
    serve(router, credentials)
    # watched before it binds, so that no connection escapes the doorkeeper's bound
    doorkeeper = gate.watch(router, f"tcp://{host}:{port or '(a random port)'}")
    try:
        if int(port or 0):
            router.bind(f"tcp://{host}:{port}")
        else:
            port = router.bind_to_random_port(f"tcp://{host}")
    except zmq.ZMQError as exc:
        router.close(linger=0)
        gate.close()
        ctx.destroy(linger=0)
        raise NodeFailure(f"cannot listen on tcp://{host}:{port}: {exc}") from None
    doorkeeper.where = f"tcp://{host}:{port}"
    if bound is not None:
        bound["listen"] = f"{host}:{port}"
    linger = 0
    procs = []
    beating = None
    secret_file = None
    token = secrets.token_bytes(16)  # this attempt's: every control message carries it
    try:
        if listen is None:
            # each node its own CPUs, where they suffice for its threads
            blocks = node_cpu_blocks(size, threads=job["options"].get("threads"))
            for rank in range(size):
                procs.append(_start_local_node(rank, port, timeout, secret,
                                               logs.path(rank, attempt),
                                               blocks[rank] if blocks else None))
        else:
            if not credentials.curve:
                secret_file = write_join_secret(int(port), secret)
            if rendezvous is not None:
                reachable = socket.getfqdn() if host in ("0.0.0.0", "*", "") else host
                write_address(rendezvous, f"tcp://{reachable}:{port}")
            # said even under --quiet: with port 0 this line is the only place the address is
            print(f"waiting for {size} node(s) on tcp://{host}:{port}"
                  + (f" (address in {rendezvous})" if rendezvous else ""), file=sys.stderr)
        address = f"tcp://{host}:{port}"
        watch = Watch(size, procs, [logs.path(r, attempt) for r in range(len(procs))], timeout,
                       launched, address, token=token,
                       heartbeat_timeout=heartbeat_timeout or timeout, spare_exits=spare_exits,
                       regrouping=bool(bound and bound.get("regrouping")))
        identities, endpoints, member_keys = {}, [None] * size, [b""] * size
        while len(identities) < size:
            identity, message = await watch.receive(router)
            if message.kind == protocol.HELLO and identity not in watch.members:
                rank = int(message.meta["rank"])
                if not 0 <= rank < size or rank in identities:  # let the coordinator choose
                    rank = min(set(range(size)) - set(identities))
                identities[rank] = identity
                endpoints[rank] = message.meta["endpoint"]
                member_keys[rank] = watch.user_ids.pop(identity, b"")
                watch.joined(rank, identity, message.meta)
                if listen is not None and verbose:
                    print(f"node {rank} joined from {message.meta.get('host', '?')} "
                          f"(pid {message.meta.get('pid', '?')}), {len(identities)} of {size}",
                          file=sys.stderr)
        peer_tokens = pair_tokens(size)
        for rank in range(size):
            frames = encode(protocol.JOB, {}, dict(
                job, endpoints=endpoints, rank=rank, size=size, peer_tokens=peer_tokens[rank],
                keys=member_keys if credentials.curve else []))
            await router.send_multipart([identities[rank], token, *frames])
        watch.job_out()
        beating = asyncio.ensure_future(_heartbeat(router, identities, token))
        frames = Frames(size, job.get("frames"), frame_done)
        passes.begin(lambda next_unit, clock: grant(router, identities, token, next_unit, clock))
        try:
            film, reports = await gather(router, watch, settings, bar, frames, size, passes)
        except NodeLost as lost:
            if regroup and listen is not None:
                await _call_regroup(router, identities, token, lost)
                linger = 2000  # let the regroup reach the survivors before the close
            raise
        finally:
            await frames.drain()  # the frames delivered are written, even when one is lost
        frames.check_complete()
        for rank in range(size):
            await router.send_multipart([identities[rank], token, *encode(protocol.STOP, {})])
        await watch.wait_exit()
        for report in reports.values():
            report["counters"]["coordinator_rejected_messages"] = watch.rejections.total
            report["counters"]["coordinator_refused_connections"] = (
                gate.refusals + gate.failed_handshakes)
            report["counters"]["coordinator_messages"] = dict(sorted(watch.kinds.items()))
        return film, [reports[r] for r in range(size)]
    finally:
        if beating is not None:
            beating.cancel()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        router.close(linger=linger)
        gate.close()
        ctx.destroy(linger=0)
        if secret_file is not None:
            secret_file.unlink(missing_ok=True)
        if rendezvous is not None and listen is not None:
            Path(rendezvous).unlink(missing_ok=True)


def _start_local_node(rank: int, port: int, timeout: float, secret: bytes,
                      log_path: Path, cpus: list[int] | None = None) -> subprocess.Popen:
    """Start node ``rank`` here, handing it the join secret through a pipe (never argv or
    the environment, which other processes may read); ``cpus``: the CPUs it binds itself to
    (``scene.cpu_binding``; None: unbound)."""
    read_end, write_end = os.pipe()
    os.write(write_end, secret)  # 32 bytes: far below the pipe's buffer
    os.close(write_end)
    try:
        with open(log_path, "wb") as log_file:
            return subprocess.Popen(
                [sys.executable, "-m", "vastray.actors.node", "--coordinator",
                 f"tcp://127.0.0.1:{port}", "--rank", str(rank), "--timeout", str(timeout),
                 "--secret-fd", str(read_end)]
                + (["--cpus", ",".join(map(str, cpus))] if cpus else []),
                stdout=subprocess.DEVNULL, stderr=log_file, stdin=subprocess.DEVNULL,
                pass_fds=(read_end,),
                env=dict(os.environ, **{protocol.PARENT_PID_ENV: str(os.getpid())}))
    finally:
        os.close(read_end)


def pair_tokens(size: int) -> list[list[bytes]]:
    """For each rank, the token it shares with each other rank (``[i][j] == [j][i]``, each
    pair's its own): a peer message's token names its sender to its receiver, and no third
    node knows it."""
    pairs = {(i, j): secrets.token_bytes(16) for i in range(size) for j in range(i, size)}
    return [[pairs[min(i, j), max(i, j)] for j in range(size)] for i in range(size)]


async def _call_regroup(router, identities: dict[int, bytes], token: bytes,
                        lost: NodeLost) -> None:
    """Tell every node but the lost one to drop the job and join again (a stalled node that
    wakes up later hears nothing, and exits on the coordinator's silence)."""
    frames = encode(protocol.REGROUP, {}, {"lost": str(lost)[:200]})
    for rank, identity in identities.items():
        if rank != lost.rank:
            await router.send_multipart([identity, token, *frames])


async def _heartbeat(router, identities: dict[int, bytes], token: bytes) -> None:
    """Tell every node, every ``protocol.HEARTBEAT_S``, that the coordinator is alive."""
    frames = encode(protocol.HEARTBEAT, {}, {})
    while True:
        for identity in identities.values():
            await router.send_multipart([identity, token, *frames])
        await asyncio.sleep(protocol.HEARTBEAT_S)
