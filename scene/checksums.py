"""Checksums of a store's array files: written with each file, checked on every load.

A manifest records two per file (format version 4; the SHA-256 alone since version 2):

* ``"crc32"``, checked each time a domain is loaded for rendering. zlib's CRC-32 runs at about
  7 GB/s, 3.4 times SHA-256 with the CPU's SHA instructions and 10 times without them: under
  3 % of the domain's BVH build, where SHA-256 costs 8 to 22 % (``python bench/checksums.py``;
  the figures are in docs/DESIGN.md). Every change of up to 32 consecutive bits is caught, any
  other with probability 1 - 2**-32: enough to notice a file changed since it was written.
* ``"sha256"``, checked by ``vastray verify`` (:mod:`vastray.scene.verify`), and by loads of
  stores written before version 4, which have no CRC-32.
"""

from __future__ import annotations

import hashlib
import re
import zlib

CRC32 = "crc32"
SHA256 = "sha256"
#: How a digest of each kind is written in a manifest: this many lowercase hex digits.
DIGITS = {CRC32: 8, SHA256: 64}
PATTERNS = {kind: re.compile(f"[0-9a-f]{{{n}}}") for kind, n in DIGITS.items()}
#: How messages name each kind.
NAMES = {CRC32: "CRC-32", SHA256: "SHA-256"}


def digest(kind: str, data) -> str:
    """The ``kind`` checksum (:data:`CRC32` or :data:`SHA256`) of ``data`` (any buffer: bytes,
    a bytearray, an ``mmap``), as the manifest writes it."""
    running = RunningDigest(kind)
    running.update(data)
    return running.hexdigest()


class HashingWriter:
    """A write-only file object that also feeds everything written to both checksums.

    Parameters
    ----------
    fh : the binary file written to.
    """

    def __init__(self, fh):
        self._fh = fh
        self._sha = hashlib.sha256()
        self._crc = 0

    def write(self, data) -> int:
        self._sha.update(data)
        self._crc = zlib.crc32(data, self._crc)
        return self._fh.write(data)

    def digests(self) -> dict[str, str]:
        """``{"sha256": hex, "crc32": hex}`` of everything written so far."""
        return {SHA256: self._sha.hexdigest(), CRC32: f"{self._crc:08x}"}


def load_check(crc32: dict, sha256: dict, kind: str) -> tuple[str, str] | None:
    """The checksum a load checks the ``kind`` file against: ``(algorithm, expected digest)``,
    the CRC-32 where the manifest has one, else its SHA-256 (stores of version 2 and 3), else
    None (version 1 stores have no checksums)."""
    if kind in crc32:
        return CRC32, crc32[kind]
    if kind in sha256:
        return SHA256, sha256[kind]
    return None


def checksum_mismatch(data, check: tuple[str, str] | None) -> str | None:
    """What differs when ``data`` (a file's bytes as read; any buffer) does not have the checksum
    ``check`` (``(algorithm, expected)``, from :func:`load_check`), e.g. ``"CRC-32 0badf00d,
    manifest 1234abcd"``; None when it has, or when there is nothing to check."""
    if check is None:
        return None
    return digest_mismatch(digest(check[0], data), check)


def digest_mismatch(got: str, check: tuple[str, str]) -> str | None:
    """``checksum_mismatch`` of a digest already computed (``got``, of ``check``'s kind)."""
    algorithm, expected = check
    if got == expected:
        return None
    return f"{NAMES[algorithm]} {got}, manifest {expected}"


class RunningDigest:
    """The ``kind`` checksum of bytes fed piece by piece (``update``), as :func:`digest`
    writes it of them all: a load checks each piece of a file just read, while it is still
    in the CPU's cache, instead of reading the whole buffer from memory again."""

    def __init__(self, kind: str):
        self.kind = kind
        self._crc = 0
        self._sha = None if kind == CRC32 else hashlib.sha256()

    def update(self, data) -> None:
        if self._sha is not None:
            self._sha.update(data)
        else:
            self._crc = zlib.crc32(data, self._crc)

    def hexdigest(self) -> str:
        return self._sha.hexdigest() if self._sha is not None else f"{self._crc:08x}"
