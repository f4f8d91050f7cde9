"""Structure-of-arrays ray sets and per-domain ray queues."""

from __future__ import annotations

import numpy as np


class SoA:
    """Named arrays of equal length: one row per ray, never one object per ray.

    Parameters
    ----------
    **arrays : equal-length numpy arrays (first axis = rays).
    """

    def __init__(self, **arrays: np.ndarray):
        lengths = {len(a) for a in arrays.values()}
        if len(lengths) > 1:
            raise ValueError(f"fields differ in length: { {k: len(a) for k, a in arrays.items()} }")
        self.fields = arrays

    def __len__(self) -> int:
        return len(next(iter(self.fields.values()))) if self.fields else 0

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]

    def __setitem__(self, name: str, value: np.ndarray) -> None:
        self.fields[name] = value

    def take(self, rows: np.ndarray) -> SoA:
        return SoA(**{k: a[rows] for k, a in self.fields.items()})

    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.fields.values())

    def without(self, *names: str) -> SoA:
        """The same rays without the fields ``names``."""
        return SoA(**{k: a for k, a in self.fields.items() if k not in names})

    @staticmethod
    def concat(parts: list[SoA]) -> SoA:
        if len(parts) == 1:
            return parts[0]
        return SoA(**{k: np.concatenate([p[k] for p in parts]) for k in parts[0].fields})


class DomainQueues:
    """One queue of rays per domain; a ray set is pushed split by destination domain.

    Parameters
    ----------
    n_domains : number of domains.
    """

    def __init__(self, n_domains: int):
        self._chunks: list[list[SoA]] = [[] for _ in range(n_domains)]
        self._counts = np.zeros(n_domains, dtype=np.int64)

    def push(self, domain: np.ndarray, rays: SoA) -> None:
        """Queue row i of ``rays`` into ``domain[i]`` ((n,) ints)."""
        if len(rays) == 0:
            return
        order = np.argsort(domain, kind="stable")
        counts = np.bincount(domain, minlength=len(self._counts))
        start = 0
        for d in np.nonzero(counts)[0]:
            stop = start + counts[d]
            self._chunks[d].append(rays.take(order[start:stop]))
            start = stop
        self._counts += counts

    def pop(self, domain: int) -> SoA | None:
        """All rays queued in ``domain`` (None when empty); the queue is emptied."""
        chunks = self._chunks[domain]
        if not chunks:
            return None
        self._chunks[domain] = []
        self._counts[domain] = 0
        return SoA.concat(chunks)

    def counts(self) -> np.ndarray:
        """(D,) rays waiting per domain."""
        return self._counts.copy()

    def count(self, domain: int) -> int:
        """Rays waiting for ``domain``."""
        return int(self._counts[domain])

    def total(self) -> int:
        return int(self._counts.sum())

    def nbytes(self) -> int:
        return sum(c.nbytes() for chunks in self._chunks for c in chunks)

    def peek(self, domain: int) -> list[SoA]:
        """The chunks queued in ``domain``, left queued (do not modify them)."""
        return list(self._chunks[domain])
