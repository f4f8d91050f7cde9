"""What checking a domain on every load costs, against building its BVH (issue 37).

For every domain of a generated scene (reused from .bench_cache/, as bench/load.py makes it),
with its files in the page cache, the best of ``--repeat`` timings (the machine may be shared:
best = least disturbed) of:

* ``build``: ``DomainBVH`` of the domain's arrays, already in memory (Embree's own threads);
* ``sha256``, ``crc32``: the checksum of the domain's files, bytes already in memory;
* ``read``: reading the files into memory, as every load now does (``Store.load_domain``),
  and ``map``: mapping them instead (``mmap=True``; the build then touches the pages).

It prints each in ms per MB of domain files and as a fraction of the build, summed over the
domains. ``OPENSSL_ia32cap=:~0x20000000`` in the environment hides the CPU's SHA instructions
from OpenSSL, to see SHA-256 as it runs on CPUs without them.

    python bench/checksums.py [--resolution 256] [--repeat 5]
"""

from __future__ import annotations

import argparse
import hashlib
import time
import zlib

from bench_scenes import cached_rm

from vastray.scene.bvh import DomainBVH
from vastray.scene.store import Store


def best(fn, repeat: int) -> float:
    """The shortest of ``repeat`` timings of ``fn()``, in seconds."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def domain_times(store: Store, domain: int, repeat: int) -> dict[str, float]:
    """Seconds of each step for ``domain`` (see the module docstring)."""
    info = store.domains[domain]
    data = [store.domain_path(info, kind).read_bytes() for kind in info.files]
    arrays = store.load_domain(domain)
    return {
        "build": best(lambda: DomainBVH(domain, arrays), repeat),
        "sha256": best(lambda: [hashlib.sha256(d).digest() for d in data], repeat),
        "crc32": best(lambda: [zlib.crc32(d) for d in data], repeat),
        "read": best(lambda: store.load_domain(domain), repeat),
        "map": best(lambda: store.load_domain(domain, mmap=True), repeat),
        "mb": sum(map(len, data)) / 2**20,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    store = cached_rm(args.resolution)
    total: dict[str, float] = {}
    for domain in range(len(store.domains)):
        if store.domains[domain].n_triangles:
            for key, value in domain_times(store, domain, args.repeat).items():
                total[key] = total.get(key, 0.0) + value
    mb, build = total.pop("mb"), total["build"]
    print(f"{len(store.domains)} domains, {store.n_triangles:,} triangles, {mb:.1f} MB of files")
    for key, seconds in total.items():
        print(f"{key:>7}: {seconds * 1e3 / mb:6.3f} ms/MB  ({seconds / build:6.1%} of the build)")


if __name__ == "__main__":
    main()
