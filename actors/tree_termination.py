"""Termination detection of an asynchronous frame (``async``, ``temporal``) over the binary tree
of ranks: Mattern's four-counter method, with its waves carried by the tree instead of one
process. No message goes to the coordinator; a wave costs each node at most one message
from its parent, one to each of its (up to two) children and their replies, and takes
ceil(log2 P) steps down and as many up.

The protocol (``TreeTermination``, a pure object: it says what to send, the frame sends it)
-----------------------------------------------------------------------------------------
A node is *passive* when it has injected every tile of the frame, no ray waits in it, its
outboxes are empty and no ray batch waits in its inbox; it counts the frame's ray batches it
has sent (``sent``, at the send) and received (``received``, at the delivery). Only a
delivered batch makes a passive node active again.

1. The root, when passive and no wave is open, opens wave ``w`` (1, 2, ...) and sends
   ``WAVE(w)`` to its children; a node that hears ``WAVE(w)`` from its parent passes it on
   to its children at once.
2. A node answers ``WAVE_REPLY(w, S, R)`` to its parent once it is passive and has every
   child's reply to ``w``: ``S`` and ``R`` are its own counts *read then* plus its children's
   sums. A node busy when the wave comes answers when it is next passive (it never answers a
   wave twice). At the root the same moment (passive, every child's reply in) closes the wave
   with totals ``(S_w, R_w)``.
3. If ``(S_w, R_w) == (S_{w-1}, R_{w-1})`` and ``S_w == R_w``, the frame has ended: the root
   sends ``WAVE(finished)`` down the tree, each node passes it on and ends its frame.
   Otherwise the root opens wave ``w + 1`` (it is passive).

Every message carries the frame's label (``status_label``), so waves of two frames never
mix; a wave goes only from parent to child and a reply only from child to parent
(``protocol.check_peer_kind``).

Why no frame can end while a batch is in flight (safety)
--------------------------------------------------------
Let wave ``w - 1`` close at the root at time ``t``. Every count read in wave ``w - 1`` was
read at or before ``t`` (a node reads its own before it replies, its children theirs before
them, the root its own at ``t``), and every count of wave ``w`` after ``t`` (no node hears
``WAVE(w)`` before the root opens it, after ``t``). Counts only grow, so summed over nodes

    S_{w-1} <= S(t) <= S_w  and  R_{w-1} <= R(t) <= R_w.

With ``S_w = S_{w-1} = R_{w-1} = R_w`` this gives ``S(t) <= S_w = R_{w-1} <= R(t)``, and
``R(t) <= S(t)`` always (no batch is delivered before it is sent), so ``S(t) = R(t)``: at
``t`` every batch sent had been delivered. Moreover ``R(t) = R_{w-1}`` and each node's count
is monotone, so no node had a batch delivered between its read in wave ``w - 1`` (when it
was passive) and ``t``: every node was passive at ``t``. Passive nodes with no batch in
flight stay so forever; the frame had ended at ``t``, before the root declares it. (A batch
of the *next* frame, sent by a node that finished first, is neither counted in this frame's
``received`` nor able to make a node of this frame active: it is held for its frame.)

Why every frame ends (liveness)
-------------------------------
Once the frame has ended (every node passive, nothing in flight) no count changes. The wave
open then closes (every node is passive, so it answers once its children have), the next
wave reads the final counts, ``S = R``, and the one after reads them again: the root ends
the frame at most three waves after the frame has ended. A wave opened earlier can only wait
for nodes that are still active, which they are only while there is work.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from vastray.actors import protocol
from vastray.transport.tree import children, parent

#: What to send: (destination rank, kind, meta).
Send = tuple[int, str, dict]


@dataclass
class TreeTermination:
    """One node's part in one frame's termination detection (see the module docstring).

    Parameters
    ----------
    rank, size : this node and the number of nodes.
    label : the frame's label, carried by every message (``status_label``).

    Attributes
    ----------
    finished : the frame has ended (the root declared it, or the word came down the tree).
    waves : waves this node answered (at the root: waves closed).
    """

    rank: int
    size: int
    label: int
    finished: bool = False
    waves: int = 0
    wave: int = 0  # the open wave's number (0: none yet)
    open: bool = False  # a wave reached this node and it has not answered yet
    replies: dict = field(default_factory=dict)  # child -> (sent, received) for ``wave``
    previous: tuple | None = None  # the root's totals of the last closed wave

    @property
    def kids(self) -> list[int]:
        return children(self.rank, self.size)

    def _down(self, finished: bool) -> list[Send]:
        meta = {"rank": self.rank, "label": self.label, "wave": self.wave, "finished": finished}
        return [(child, protocol.WAVE, dict(meta)) for child in self.kids]

    def on_wave(self, meta: dict) -> list[Send]:
        """Hear ``WAVE`` from the parent: pass it on to the children (and end the frame if it
        says finished)."""
        if self.finished or self.rank == 0:
            return []
        self.wave = int(meta["wave"])
        if meta["finished"]:
            self.finished = True
        else:
            self.open, self.replies = True, {}
        return self._down(self.finished)

    def on_reply(self, meta: dict) -> None:
        """Hear a child's ``WAVE_REPLY`` (one of another wave than the open one is ignored)."""
        if self.open and int(meta["wave"]) == self.wave:
            self.replies[int(meta["rank"])] = (int(meta["sent"]), int(meta["received"]))

    def passive(self, sent: int, received: int) -> list[Send]:
        """This node is passive with these counts: answer the open wave if every child has;
        at the root, close it and end the frame or open the next."""
        out: list[Send] = []
        while not self.finished:
            if self.rank == 0 and not self.open:
                self.wave += 1
                self.open, self.replies = True, {}
                out += self._down(False)
            if not self.open or len(self.replies) < len(self.kids):
                return out
            total = (sent + sum(s for s, _ in self.replies.values()),
                     received + sum(r for _, r in self.replies.values()))
            self.open = False
            self.waves += 1
            if self.rank != 0:
                out.append((parent(self.rank), protocol.WAVE_REPLY, {
                    "rank": self.rank, "label": self.label, "wave": self.wave,
                    "sent": total[0], "received": total[1]}))
                return out
            if total == self.previous and total[0] == total[1]:
                self.finished = True
                out += self._down(True)
            self.previous = total
            if not self.kids and total[0] != total[1]:
                return out  # alone, and a batch to itself in flight: wait for it
        return out
