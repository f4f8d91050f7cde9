"""Per-frame counters of the temporal-coherence scheduler (Xu et al., TVCG 2022, §4.1, §4.3):
ray transmissions, loads, processing and loading speeds, summed over nodes at a frame's end."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

__all__ = ["FrameStats"]

#: Below this, a ray processing speed (rays/s) is "zero" (``FrameStats.s_proc``'s floor).
_S_PROC_EPS = 1e-6


def _fallback_mean(value: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``value`` where ``known``, else the mean of the known values, else 1.0."""
    fill = float(value[known].mean()) if known.any() else 1.0
    return np.where(known, value, fill)


@dataclass
class FrameStats:
    """One frame's counters, summed over nodes (§4.1, §4.3; note S2).

    Attributes
    ----------
    sent : (D, D) int64, s(A, B): rays forwarded from domain A to domain B != A (on one node or
        between nodes). The diagonal is ignored by every derived quantity.
    received : (D,) int64, r(A): rays A processed (from other domains, from the camera or
        spawned in A; note S12.2).
    loads : (D,) int64, N(d): loads of domain d.
    proc_rays : (D,) int64 and proc_s : (D,) float64: rays processed in d and the seconds of
        d's activations that processed them, from the activation to the end of its tracing
        and shading: the wait for d's load (what preloading did not hide) is included (for
        S_PROC). Reading: S_PROC(d) is the speed at which the node processed d's rays, as the
        node spent its time. Timing the tracing alone made Eq. 1's load term swamp Q/S_PROC
        wherever a domain's queue takes less time to trace than to load, so every domain not
        cached ranked near -T_LOAD whatever its rays, and the node loaded cheap domains
        holding few rays (bench/README.md, temporal.py: 1,152 loads per frame against 546).
    load_bytes : (P,) float64 and load_s : (P,) float64: bytes loaded by node n and seconds
        spent loading them (for S_LOAD).
    held : (P, D) int64, 1 where node n held domain d in its cache at the frame's end (each
        node fills its own row), for the cache-affinity assignment (``assign_affinity``).

    Every field is a sum over nodes, so a SUM all-reduce of ``to_arrays()`` merges nodes.
    """

    sent: np.ndarray
    received: np.ndarray
    loads: np.ndarray
    proc_rays: np.ndarray
    proc_s: np.ndarray
    load_bytes: np.ndarray
    load_s: np.ndarray
    held: np.ndarray | None = None

    DTYPES: ClassVar[dict[str, type]] = {
        "sent": np.int64, "received": np.int64, "loads": np.int64, "proc_rays": np.int64,
        "proc_s": np.float64, "load_bytes": np.float64, "load_s": np.float64,
        "held": np.int64,
    }

    def __post_init__(self):
        if self.held is None:
            self.held = np.zeros((len(self.load_bytes), len(self.received)), np.int64)
        for name, dtype in self.DTYPES.items():
            setattr(self, name, np.asarray(getattr(self, name), dtype=dtype))
        d = len(self.received)
        p = len(self.load_bytes)
        shapes = {"sent": (d, d), "received": (d,), "loads": (d,), "proc_rays": (d,),
                  "proc_s": (d,), "load_bytes": (p,), "load_s": (p,), "held": (p, d)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"FrameStats.{name} has shape {getattr(self, name).shape}, "
                                 f"expected {shape}")

    @classmethod
    def zeros(cls, n_domains: int, n_nodes: int) -> FrameStats:
        """All counters 0 for D = ``n_domains`` domains and P = ``n_nodes`` nodes."""
        d, p = int(n_domains), int(n_nodes)
        return cls(np.zeros((d, d), np.int64), np.zeros(d, np.int64), np.zeros(d, np.int64),
                   np.zeros(d, np.int64), np.zeros(d), np.zeros(p), np.zeros(p),
                   np.zeros((p, d), np.int64))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fields by name (the arrays themselves, not copies), for a SUM all-reduce."""
        return {name: getattr(self, name) for name in self.DTYPES}

    @classmethod
    def from_arrays(cls, d: dict[str, np.ndarray]) -> FrameStats:
        """The inverse of ``to_arrays`` (copies, cast to the field dtypes, shapes checked)."""
        return cls(**{name: np.array(d[name], dtype=dtype) for name, dtype in cls.DTYPES.items()})

    def _sent_off_diagonal(self) -> np.ndarray:
        """(D, D) int64 s(A, B) with the diagonal zeroed."""
        sent = self.sent.copy()
        np.fill_diagonal(sent, 0)
        return sent

    def transmission_ratio(self) -> np.ndarray:
        """R(A) = s(A) / r(A), 0 where r(A) = 0.

        Returns
        -------
        (D,) float64
        """
        s = self._sent_off_diagonal().sum(axis=1).astype(np.float64)
        r = self.received.astype(np.float64)
        return np.divide(s, r, out=np.zeros_like(s), where=r > 0)

    def pair_ratio(self, literal: bool = False) -> np.ndarray:
        """R(A, B) = s(A, B) / s(A) (note S12.1), 0 where the denominator is 0.

        Parameters
        ----------
        literal : use the paper's literal s(A, B) / r(A) instead (ablation; with it
            Q_CUR(act) R(act) R(act, d) counts R(act) twice).

        Returns
        -------
        (D, D) float64, row A, column B; zero diagonal.
        """
        sent = self._sent_off_diagonal().astype(np.float64)
        denom = self.received.astype(np.float64) if literal else sent.sum(axis=1)
        return np.divide(sent, denom[:, None], out=np.zeros_like(sent), where=denom[:, None] > 0)

    def s_proc(self, eps: float = _S_PROC_EPS) -> np.ndarray:
        """S_PROC(d), rays per second processed in each domain.

        A domain with no rays or no time recorded gets the mean speed of the domains that have
        both (1.0 if none has); the result is floored at ``eps``.

        Returns
        -------
        (D,) float64, >= eps
        """
        known = (self.proc_rays > 0) & (self.proc_s > 0)
        speed = np.divide(self.proc_rays.astype(np.float64), self.proc_s,
                          out=np.zeros(len(self.proc_s)), where=known)
        return np.maximum(_fallback_mean(speed, known), eps)

    def s_load(self) -> np.ndarray:
        """S_LOAD(n), bytes per second loaded by each node (§4.3).

        A node with no bytes or no time recorded gets the mean of the nodes that have both
        (1.0 if none has).

        Returns
        -------
        (P,) float64
        """
        known = (self.load_bytes > 0) & (self.load_s > 0)
        speed = np.divide(self.load_bytes, self.load_s, out=np.zeros(len(self.load_s)),
                          where=known)
        return _fallback_mean(speed, known)
