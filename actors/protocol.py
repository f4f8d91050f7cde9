"""Message kinds between the coordinator and nodes (each a codec message; payload in meta),
who may send each, and what each must hold.

Only members of the job connect at all (``transport.security``: the handshake admits them).
On the wire every message is ``[token, header, frame, ...]``: between the coordinator and a
node, the job's token (made by the coordinator for each attempt, sent in the job); between
two nodes, the token those two alone share (``peer_tokens`` in the job), which names the
sender. A message whose token does not fit is dropped before it is decoded.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

HELLO = "hello"          # node -> coordinator: rank, endpoint
JOB = "job"              # coordinator -> node: store, scene, settings, job options, peers,
                         # units (frame, first sample, stop sample) and whether they are paced
PROGRESS = "progress"    # node -> coordinator: paths done
HEARTBEAT = "heartbeat"  # node -> coordinator: still alive
FILM = "film"            # node -> parent node / root -> coordinator: partial film (node 0's
                         # to the coordinator may add the time rule's ahead_seconds and
                         # traced_ahead, ``gather.time_rule_of``)
DONE = "done"            # node -> coordinator: per-node timings and counters
FRAME = "frame"          # node -> coordinator: one animation frame's timings and counters
FAILED = "failed"        # node -> coordinator: this node's job failed (the error), it exits
STOP = "stop"            # coordinator -> node: shut down
REGROUP = "regroup"      # coordinator -> node: a node was lost; drop this job, join again
RAYS = "rays"            # node -> node: a ray batch for the receiver's domains
EXCHANGE = "exchange"    # node -> butterfly partner: its partial at one all-reduce step
GRANT = "grant"          # coordinator -> node (paced passes): the next unit to render, or -1
                         # (and the time rule's budget_s and per_sample_s of it, or None)
WAVE = "wave"            # node -> child node (async, temporal): a termination wave, or finished
WAVE_REPLY = "wave_reply"  # node -> parent node: its subtree's batches sent and received

#: Who may send what. A node takes control kinds only from its coordinator connection and
#: data kinds only from peers of its job; the coordinator takes only node kinds.
FROM_COORDINATOR = frozenset({JOB, STOP, REGROUP, HEARTBEAT, GRANT})
FROM_PEER = frozenset({RAYS, FILM, EXCHANGE, WAVE, WAVE_REPLY})
FROM_NODE = frozenset({HELLO, PROGRESS, HEARTBEAT, FILM, DONE, FRAME, FAILED})

_NUMBER = (int, float)

#: Required meta keys and their types, per kind (extra keys are allowed).
META = {
    HELLO: {"rank": int, "endpoint": str},
    JOB: {"store": str, "settings": dict, "options": dict, "rank": int, "size": int,
          "endpoints": list, "units": list, "paced": bool},
    PROGRESS: {"rank": int, "paths": int},
    HEARTBEAT: {},
    FILM: {"rank": int},
    DONE: {"rank": int, "busy_s": _NUMBER, "reduce_s": _NUMBER, "counters": dict},
    FRAME: {"rank": int, "frame": int, "busy_s": _NUMBER, "reduce_s": _NUMBER, "counters": dict},
    FAILED: {"rank": int, "error": str},
    STOP: {},
    REGROUP: {"lost": str},
    RAYS: {"rank": int, "tile": int, "queue": str},
    EXCHANGE: {"rank": int, "call": int, "step": int},
    GRANT: {"next": int},
    WAVE: {"rank": int, "label": int, "wave": int, "finished": bool},
    WAVE_REPLY: {"rank": int, "label": int, "wave": int, "sent": int, "received": int},
}

#: Arrays a film carries, all with one row per pixel.
FILM_FIELDS = ("sum", "batch", "count", "depth", "normal")


class ProtocolError(ValueError):
    """A message that decodes but breaks the protocol: unknown kind, wrong sender, missing or
    mistyped fields, inconsistent shapes."""


def check(message, allowed: frozenset[str]) -> None:
    """Check a decoded message against its kind's schema and the kinds ``allowed`` from its
    sender.

    Raises
    ------
    ProtocolError
        Saying what is wrong.
    """
    kind = message.kind
    if kind not in allowed:
        raise ProtocolError(f"kind {kind[:40]!r} not accepted from this sender")
    for key, types in META[kind].items():
        value = message.meta.get(key)
        ok = (type(value) is bool) if types is bool else (
            isinstance(value, types) and not isinstance(value, bool))
        if not ok:
            raise ProtocolError(f"{kind}: meta {key!r} missing or not {types}")
    if kind == RAYS:
        _check_rays(message)
    elif kind == FILM:
        _check_film(message)
    elif message.arrays and kind != EXCHANGE:
        raise ProtocolError(f"{kind} carries no arrays")


def check_peer_kind(message, sender: int, rank: int, size: int) -> None:
    """Whether node ``sender`` may send ``message`` to node ``rank`` of ``size``: films and
    termination replies go up the tree (only from a child), termination waves down it (only
    from the parent), an all-reduce partial only from the butterfly partner of its step; ray
    batches between any two nodes.

    Raises
    ------
    ProtocolError
        Naming the rule broken.
    """
    from vastray.transport.tree import children, exchange_partner, parent

    kind = message.kind
    if kind in (FILM, WAVE_REPLY) and sender not in children(rank, size):
        raise ProtocolError(f"{kind} from node {sender}, which is not a child of node {rank}")
    if kind == WAVE and sender != parent(rank):
        raise ProtocolError(f"{kind} from node {sender}, which is not node {rank}'s parent")
    if kind == EXCHANGE and sender != exchange_partner(rank, size, message.meta["step"]):
        raise ProtocolError(f"all-reduce step {message.meta['step']} from node {sender}, "
                            f"which is not node {rank}'s partner at that step")
    if kind == RAYS and sender == rank:
        raise ProtocolError("ray batch from this node's own rank")


#: Ray fields that hold domain ids, and the id each may hold for "none" besides the job's.
DOMAIN_FIELDS = {"domain": None, "hit_domain": np.iinfo(np.int32).max,
                 "cand_d": np.iinfo(np.int32).max, "at_d": -1}


def check_ray_ids(message, n_domains: int) -> None:
    """Every domain id in a ray batch names one of the job's ``n_domains`` domains (or is
    its field's "none").

    Raises
    ------
    ProtocolError
        For an id out of range.
    """
    for name, none in DOMAIN_FIELDS.items():
        ids = message.arrays.get(name)
        if ids is None or not len(ids):
            continue
        if ids.dtype.kind not in "iu" or ids.ndim != 1:
            raise ProtocolError(f"rays: {name} must be 1-D integers")
        # negative ids read as unsigned are beyond any domain count: one comparison
        bad = ids.view(ids.dtype.str.replace("i", "u")) >= n_domains
        if none is not None:
            bad &= ids != none
        if bad.any():
            raise ProtocolError(f"rays: {name} {int(ids[bad][0])} is no domain of the job's "
                                f"{n_domains}")


def check_ray_index(message, name: str, count: int) -> None:
    """Every entry of index field ``name`` of a ray batch (``path``: the tile's paths;
    ``slot``: a path's shadow slots) lies in ``0..count-1``; a batch without it passes.

    Raises
    ------
    ProtocolError
        For an index out of range.
    """
    index = message.arrays.get(name)
    if index is None or not len(index):
        return
    if index.dtype.kind not in "iu" or index.ndim != 1:
        raise ProtocolError(f"rays: {name} must be 1-D integers")
    if int(index.min()) < 0 or int(index.max()) >= count:
        raise ProtocolError(f"rays: {name} outside 0..{count - 1}")


def _check_rays(message) -> None:
    from vastray.schedule.paths import RADIANCE_FIELDS, SHADOW_FIELDS

    queue = message.meta["queue"]
    if queue not in ("radiance", "shadow"):
        raise ProtocolError(f"rays: unknown queue {queue[:40]!r}")
    arrays = message.arrays
    if not arrays:
        return  # an empty batch: counted, carries nothing
    domain = arrays.get("domain")
    if domain is None or domain.ndim != 1 or domain.dtype.kind not in "iu":
        raise ProtocolError("rays: needs a 1-D integer 'domain' field")
    missing = set(RADIANCE_FIELDS if queue == "radiance" else SHADOW_FIELDS) - set(arrays)
    if missing:
        raise ProtocolError(f"rays: missing fields {sorted(missing)}")
    n = len(domain)
    if any(a.ndim == 0 or a.shape[0] != n for a in arrays.values()):
        raise ProtocolError(f"rays: every field needs {n} rows")
    if n and (int(domain.min()) < 0):
        raise ProtocolError("rays: negative domain id")


def _check_film(message) -> None:
    arrays = message.arrays
    missing = set(FILM_FIELDS) - set(arrays)
    if missing:
        raise ProtocolError(f"film: missing fields {sorted(missing)}")
    n = len(arrays["count"])
    if any(arrays[f].ndim == 0 or arrays[f].shape[0] != n for f in FILM_FIELDS):
        raise ProtocolError("film: fields differ in pixel count")
    if not all(np.issubdtype(arrays[f].dtype, np.number) for f in FILM_FIELDS):
        raise ProtocolError("film: fields must be numeric")

#: Seconds between heartbeats (coordinator to nodes, and nodes to coordinator); a node that
#: hears nothing from the coordinator for five heartbeats exits (the coordinator died or was
#: cut off). Nothing on the coordinator's event loop blocks that long while nodes work (frames
#: are written on a thread); five, not two, so that a coordinator starved of the CPU for a
#: moment on a loaded machine is not taken for dead.
HEARTBEAT_S = 1.0
COORDINATOR_SILENCE_S = 5 * HEARTBEAT_S

#: Environment variable naming the coordinator's pid to the nodes it starts on its own machine:
#: they ask the kernel to kill them the moment it exits (Linux's parent-death signal).
PARENT_PID_ENV = "VASTRAY_PARENT_PID"


#: Bytes of received messages a node holds undelivered at most; beyond, messages are dropped
#: (the protocol bounds honest traffic far below: rays in flight are bounded by the tiles).
UNDELIVERED_BUDGET = 4 << 30


class Rejections:
    """Messages dropped on receipt, counted by reason and logged at a bounded rate (the first
    few of each reason, then every thousandth), so a flood cannot flood the log too."""

    def __init__(self):
        self.counts: dict[str, int] = {}

    def add(self, reason: str, detail: str) -> None:
        n = self.counts[reason] = self.counts.get(reason, 0) + 1
        if n <= 5 or n % 1000 == 0:
            log.warning("dropped a message (%s, %d so far): %s", reason, n, detail[:200])

    @property
    def total(self) -> int:
        return sum(self.counts.values())
