"""Structure-of-arrays ray sets and per-domain ray queues."""

from __future__ import annotations

from collections.abc import Iterator

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

    @classmethod
    def _trusted(cls, fields: dict[str, np.ndarray]) -> SoA:
        """An SoA over ``fields`` known to be of equal length (no check: hot paths)."""
        soa = cls.__new__(cls)
        soa.fields = fields
        return soa

    def take(self, rows: np.ndarray) -> SoA:
        """The rows ``rows`` of every field, copied: ``rows`` a (len(self),) bool mask, or
        indices.

        A mask is turned into indices once, and each field gathered by ``ndarray.take``:
        indexing every field by the mask scans the mask again per field, and numpy's fancy
        indexing costs about twice ``take`` (12 fields of 4,000 rays, half of them kept:
        210 us by mask, 56 us here), on the schedules' every step.
        """
        rows = np.asarray(rows)
        if rows.dtype == np.bool_:
            if len(rows) != len(self):
                raise IndexError(f"a mask of {len(rows)} rows for {len(self)} rays")
            rows = np.flatnonzero(rows)
        return SoA._trusted({k: a.take(rows, axis=0) for k, a in self.fields.items()})

    def rows(self, start: int, stop: int) -> SoA:
        """Rows ``start:stop`` as views (no copy)."""
        return SoA._trusted({k: a[start:stop] for k, a in self.fields.items()})

    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.fields.values())

    def without(self, *names: str) -> SoA:
        """The same rays without the fields ``names``."""
        return SoA._trusted({k: a for k, a in self.fields.items() if k not in names})

    @staticmethod
    def concat(parts: list[SoA]) -> SoA:
        if len(parts) == 1:
            return parts[0]
        return SoA._trusted({k: np.concatenate([p.fields[k] for p in parts])
                             for k in parts[0].fields})


class GrowingArray:
    """A 1-D array appended to in blocks, in amortised constant time per element (its buffer
    doubles when full): ``np.concatenate`` on every append copies all that came before, which
    over a render's millions of rows and thousands of appends is quadratic.

    ``values`` is the live part, (n,), a view: index and assign through it; take it afresh
    after an ``append`` (the buffer may have moved).
    """

    def __init__(self, dtype, capacity: int = 1024):
        self._buffer = np.zeros(max(int(capacity), 1), dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def values(self) -> np.ndarray:
        return self._buffer[:self._n]

    def append(self, block: np.ndarray) -> None:
        """Add ``block`` (k,) at the end."""
        need = self._n + len(block)
        if need > len(self._buffer):
            grown = np.zeros(max(need, 2 * len(self._buffer)), self._buffer.dtype)
            grown[:self._n] = self._buffer[:self._n]
            self._buffer = grown
        self._buffer[self._n:need] = block
        self._n = need


def index_of(keys: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(m,) int64 position in ``keys`` ((n,) distinct ints, e.g. path ids) of each of
    ``values`` ((m,), every one among ``keys``): a sort and a search, O((n + m) log n)."""
    order = np.argsort(keys, kind="stable")
    return order[np.searchsorted(keys[order], values)]


def join_bound(parts: list[tuple[np.ndarray, SoA]]) -> tuple[np.ndarray, SoA] | None:
    """Parts of rays bound for domains, ``(domains (m_i,), rays (m_i rows))``, joined into one
    ``(domains (m,), rays (m rows))``; None for no parts."""
    if not parts:
        return None
    return np.concatenate([d for d, _ in parts]), SoA.concat([r for _, r in parts])


#: Bytes of popped rows ``DomainQueues`` may keep alive in partly popped blocks before it
#: copies the queued runs out of them, whatever the queued bytes: small queues never copy.
WASTE_FLOOR = 4 << 20


class DomainQueues:
    """One queue of rays per domain; a ray set is pushed split by destination domain.

    A push sorts its rays by destination once (one gather per field) and queues, per domain,
    the bounds of that domain's run in the sorted block: the per-domain rays are sliced out
    (views) only when the queue is popped or peeked, instead of one gather per field and
    domain on every push. A block stays in memory until its last run is popped (``nbytes``
    counts what is held), unless more than ``WASTE_FLOOR`` bytes and more than half the queued
    bytes are popped rows kept alive that way: then the runs left in blocks less than two
    thirds queued are copied out and those blocks freed (``_compact``). Without that, a
    speculative schedule's copies of one push, spread over dozens of domains, held the whole
    push until its last domain was served: 455 MB held for 17 MB queued (issue 37).

    Parameters
    ----------
    n_domains : number of domains.
    """

    def __init__(self, n_domains: int):
        # domain -> its (sorted block, start, stop) runs, oldest first; only domains with
        # rays have an entry (a list per domain made every queue O(D): 1.6 ms at 871 domains,
        # and a node makes queues for every tile it hears of)
        self._chunks: dict[int, list[tuple[SoA, int, int]]] = {}
        self._counts = np.zeros(n_domains, dtype=np.int64)
        # id(block) -> [block, rows of it still queued, bytes per row]; bytes of the blocks
        # held and of the rows queued, kept as running totals
        self._blocks: dict[int, list] = {}
        self._held = 0
        self._live = 0

    def push(self, domain: np.ndarray, rays: SoA) -> None:
        """Queue row i of ``rays`` into ``domain[i]`` ((n,) ints). The queue may keep
        ``rays``' arrays without copying them: do not modify them afterwards."""
        if len(rays) == 0:
            return
        counts = np.bincount(domain, minlength=len(self._counts))
        present = np.flatnonzero(counts)
        if len(present) == 1:
            block = SoA._trusted(dict(rays.fields))  # one destination: no sort, no copy
        else:
            block = rays.take(np.argsort(domain, kind="stable"))
        stops = np.cumsum(counts)[present]
        starts = stops - counts[present]
        self._hold(block)
        chunks = self._chunks
        for d, start, stop in zip(present.tolist(), starts.tolist(), stops.tolist(), strict=True):
            chunks.setdefault(d, []).append((block, start, stop))
        self._counts += counts

    def pop(self, domain: int) -> SoA | None:
        """All rays queued in ``domain`` (None when empty); the queue is emptied."""
        chunks = self._chunks.pop(domain, None)
        if not chunks:
            return None
        self._counts[domain] = 0
        for block, start, stop in chunks:
            self._release(block, stop - start)
        if len(chunks) == 1:
            block, start, stop = chunks[0]
            rays = block.rows(start, stop)
        else:
            rays = SoA._trusted({
                k: np.concatenate([block.fields[k][start:stop] for block, start, stop in chunks])
                for k in chunks[0][0].fields})
        self._compact()
        return rays

    def _hold(self, block: SoA) -> None:
        nbytes = block.nbytes()
        self._blocks[id(block)] = [block, len(block), nbytes // len(block)]
        self._held += nbytes
        self._live += nbytes

    def _release(self, block: SoA, rows: int) -> None:
        """``rows`` of ``block`` left the queues; the block is dropped with its last row."""
        entry = self._blocks[id(block)]
        entry[1] -= rows
        self._live -= rows * entry[2]
        if entry[1] == 0:
            del self._blocks[id(block)]
            self._held -= len(block) * entry[2]

    def _compact(self) -> None:
        """Copy the runs out of blocks less than two thirds queued once the popped rows they
        keep alive exceed ``WASTE_FLOOR`` and half the queued bytes: afterwards every block
        held is at least two thirds queued (the queues hold at most 1.5x their rays). Each
        byte copied frees at least half a byte, so the copies cost at most twice the pushes.

        A domain's consecutive runs in such blocks are copied into one new block (their
        order kept: the rays of a queue pop in the order they were pushed), not run by run:
        a speculative schedule's queues hold tens of thousands of runs of a few rays, and
        copying them one at a time, a gather per field and run, took 0.9 s of a 35 s render
        for 142 MB (the README's 100 M-triangle store at 512x512)."""
        waste = self._held - self._live
        if waste <= max(WASTE_FLOOR, self._live // 2):
            return
        sparse = {key for key, (block, rows, _) in self._blocks.items()
                  if 3 * rows < 2 * len(block)}
        for domain, chunks in self._chunks.items():
            if not any(id(block) in sparse for block, _, _ in chunks):
                continue
            merged: list[tuple[SoA, int, int]] = []
            group: list[tuple[SoA, int, int]] = []
            for chunk in chunks:
                if id(chunk[0]) in sparse:
                    group.append(chunk)
                    continue
                if group:
                    merged.append(self._copied(group))
                    group = []
                merged.append(chunk)
            if group:
                merged.append(self._copied(group))
            self._chunks[domain] = merged
        for key in sparse:
            block, rows, row_bytes = self._blocks.pop(key)
            self._held -= len(block) * row_bytes
            self._live -= rows * row_bytes

    def _copied(self, runs: list[tuple[SoA, int, int]]) -> tuple[SoA, int, int]:
        """``runs`` (block, start, stop) copied, in order, into one new block held here."""
        copy = SoA._trusted({k: np.concatenate([b.fields[k][start:stop]
                                                for b, start, stop in runs])
                             for k in runs[0][0].fields})
        self._hold(copy)
        return copy, 0, len(copy)

    def counts(self) -> np.ndarray:
        """(D,) rays waiting per domain."""
        return self._counts.copy()

    def count(self, domain: int) -> int:
        """Rays waiting for ``domain``."""
        return int(self._counts[domain])

    def total(self) -> int:
        return int(self._counts.sum())

    def nbytes(self) -> int:
        """Bytes held: every block some queue still has a run in, counted once."""
        return self._held

    def peek_fields(self, domain: int, names: tuple[str, ...]) -> Iterator[tuple[np.ndarray, ...]]:
        """The chunks queued in ``domain``, oldest first, each as the views of the fields
        ``names`` only (left queued: do not modify them), made one at a time as they are
        asked for: a search for the first chunk with some property (``_would_trace``) makes
        the views of the chunks it reads, not of a queue's hundreds. Do not push or pop while
        iterating."""
        for block, start, stop in self._chunks.get(domain, ()):
            fields = block.fields
            yield tuple([fields[k][start:stop] for k in names])

    def peek(self, domain: int) -> list[SoA]:
        """The chunks queued in ``domain``, left queued (views: do not modify them)."""
        return [block.rows(start, stop) for block, start, stop in self._chunks.get(domain, ())]
