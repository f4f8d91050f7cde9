"""Key folders made by ``vastray keys``: the coordinator's key pair, one key pair per node,
the allow-list of node public keys, and one bundle per node (what that node's host is given).

Layout::

    coordinator.key    the coordinator's pair (owner-only); it never leaves the coordinator
    coordinator.pub    its public half: what a node needs to check the coordinator
    nodes/NAME.key     node NAME's pair (owner-only): all a node needs besides coordinator.pub
    public/NAME.key    node NAME's public key on the allow-list; delete it to shut NAME out
    bundles/NAME/      what host NAME is given, and nothing more: coordinator.pub and
                       nodes/NAME.key (the same layout, so a bundle is a key folder too)

The full folder stays with the coordinator. A host given only its bundle holds no other
node's secret, so once its public key is off the allow-list no key it has lets it in.
"""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass
from pathlib import Path

import zmq

from vastray.scene.errors import InputError

COORDINATOR_KEY = "coordinator.key"
COORDINATOR_PUBLIC = "coordinator.pub"
PUBLIC_DIR = "public"
NODES_DIR = "nodes"
BUNDLES_DIR = "bundles"
#: The key file of vastray before per-node membership: a pair every node held.
LEGACY_KEY_FILE = "cluster.key"
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}"


@dataclass(frozen=True)
class CoordinatorKeys:
    """The coordinator's key pair (Z85) and the allow-list folder of node public keys."""

    public: bytes
    secret: bytes
    allow_dir: Path


@dataclass(frozen=True)
class NodeKeys:
    """A node's own key pair (Z85), its name, and the coordinator's public key."""

    name: str
    public: bytes
    secret: bytes
    coordinator_public: bytes


def generate_keys(folder: str | os.PathLike, force: bool = False) -> Path:
    """Write the coordinator's key pair into ``folder`` (secret readable by the owner only)
    and make the (empty) allow-list.

    Raises
    ------
    InputError
        When ``folder`` is a file, or holds a coordinator key and ``force`` is not given
        (replacing it would lock every node out until each has the new public key).
    """
    folder = _key_folder(folder)
    key_file = folder / COORDINATOR_KEY
    if key_file.exists() and not force:
        raise InputError(key_file, "a coordinator key exists already; nodes that know it "
                                   "would be locked out (pass --force to replace it)")
    (folder / PUBLIC_DIR).mkdir(parents=True, exist_ok=True)
    public, secret = zmq.curve_keypair()
    _write_pair(key_file, public, secret)
    (folder / COORDINATOR_PUBLIC).write_text(f"public = {public.decode()}\n")
    return key_file


def check_node_name(name: str) -> None:
    """Refuse a node key name that is not a plain word (it names files and folders).

    Raises
    ------
    InputError
        Saying which characters a name may hold.
    """
    if not re.fullmatch(NAME_PATTERN, name) or name == "coordinator":
        raise InputError(None, f"node key name {name!r}: use letters, digits, '_', '.', '-'")


def add_node_key(folder: str | os.PathLike, name: str, force: bool = False) -> Path:
    """Give node ``name`` its own key pair (``nodes/NAME.key``) and put its public key on the
    allow-list (``public/NAME.key``).

    Raises
    ------
    InputError
        For a name that is not a plain word, or an existing node key without ``force``.
    """
    check_node_name(name)
    folder = _key_folder(folder)
    key_file = folder / NODES_DIR / f"{name}.key"
    if key_file.exists() and not force:
        raise InputError(key_file, "this node has a key already (pass --force to replace it)")
    key_file.parent.mkdir(parents=True, exist_ok=True)
    (folder / PUBLIC_DIR).mkdir(parents=True, exist_ok=True)
    public, secret = zmq.curve_keypair()
    _write_pair(key_file, public, secret)
    (folder / PUBLIC_DIR / f"{name}.key").write_text(
        f'metadata\ncurve\n    public-key = "{public.decode()}"\n')
    return key_file


def write_bundle(folder: str | os.PathLike, name: str) -> Path:
    """Write node ``name``'s bundle, ``bundles/NAME``: the coordinator's public key and the
    node's own key pair (owner-only), nothing else. Written again on every call, so it follows
    a replaced coordinator or node key.

    Raises
    ------
    InputError
        When the folder lacks the coordinator's public key or the node's key.
    """
    folder = _existing_folder(folder)
    node = load_node_keys(folder, name)
    bundle = folder / BUNDLES_DIR / name
    (bundle / NODES_DIR).mkdir(mode=0o700, parents=True, exist_ok=True)
    for part in (folder / BUNDLES_DIR, bundle, bundle / NODES_DIR):
        part.chmod(0o700)  # the folders of secrets, as the files: owner-only
    _write_pair(bundle / NODES_DIR / f"{name}.key", node.public, node.secret)
    (bundle / COORDINATOR_PUBLIC).write_text(f"public = {node.coordinator_public.decode()}\n")
    return bundle


def node_bundle(folder: str | os.PathLike, name: str) -> Path:
    """The bundle of node ``name`` in the key folder ``folder``, checked to hold its key.

    Raises
    ------
    InputError
        When there is none (a folder made before bundles existed, or a node never named).
    """
    bundle = Path(folder) / BUNDLES_DIR / name
    if not (bundle / NODES_DIR / f"{name}.key").is_file():
        raise InputError(bundle, f"no bundle for node {name!r}; make it with `vastray keys "
                                 f"-o {folder} --keep-existing --node {name}`")
    load_node_keys(bundle, name)  # refuses a malformed one
    return bundle


def _key_folder(folder: str | os.PathLike) -> Path:
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "is a file; -o names the folder to write the keys into")
    return folder


def _write_pair(path: Path, public: bytes, secret: bytes) -> None:
    path.unlink(missing_ok=True)  # a new file gets the owner-only mode
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"public = {public.decode()}\nsecret = {secret.decode()}\n")


def load_coordinator_keys(folder: str | os.PathLike) -> CoordinatorKeys:
    """The coordinator's key pair and allow-list folder."""
    folder = _existing_folder(folder)
    public, secret = _read_key(folder / COORDINATOR_KEY, "no coordinator key here; make one "
                                                         "with `vastray keys -o DIR`", True)
    return CoordinatorKeys(public, secret, folder / PUBLIC_DIR)


def load_node_keys(folder: str | os.PathLike, name: str | None = None) -> NodeKeys:
    """Node ``name``'s key pair and the coordinator's public key, from a node's bundle or the
    full key folder. Without ``name``: the one node key of a bundle, or else this host's short
    name's."""
    folder = _existing_folder(folder)
    found = sorted(p.stem for p in (folder / NODES_DIR).glob("*.key"))
    if name is None:
        name = found[0] if len(found) == 1 else default_key_name()
    if (folder / COORDINATOR_KEY).exists():
        missing = (f"no key for node {name!r}; make one with `vastray keys -o {folder} --node "
                   f"{name}` (or name this node's key with --key-name)")
    else:  # a bundle: its host has its own key and no other
        missing = (f"no key for node {name!r}; this host holds the key of "
                   f"{' and '.join(map(repr, found)) or 'no node'} only (its bundle, "
                   "`vastray keys` writes KEYS/bundles/NAME)")
    public, secret = _read_key(folder / NODES_DIR / f"{name}.key", missing, True)
    coordinator, _ = _read_key(folder / COORDINATOR_PUBLIC, "no coordinator public key "
                               "here; copy coordinator.pub from the coordinator's key folder",
                               False)
    return NodeKeys(name, public, secret, coordinator)


def default_key_name() -> str:
    """A node's key name when none is given: this host's short name."""
    return socket.gethostname().split(".")[0]


def _existing_folder(folder: str | os.PathLike) -> Path:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "no such key folder; make one with `vastray keys -o DIR`")
    if (folder / LEGACY_KEY_FILE).exists() and not (folder / COORDINATOR_PUBLIC).exists():
        raise InputError(folder, "holds a cluster key of an older vastray, which every node "
                                 "shared; make a new folder: `vastray keys -o DIR --node NAME "
                                 "...` (one key per node)")
    return folder


def _read_key(key_file: Path, missing: str, with_secret: bool) -> tuple[bytes, bytes | None]:
    if not key_file.is_file():
        raise InputError(key_file, missing)
    values = {}
    for line in key_file.read_text(errors="replace").splitlines():
        if "=" in line:
            name, value = (part.strip() for part in line.split("=", 1))
            values[name] = value.encode()
    if len(values.get("public", b"")) != 40 or (
            with_secret and len(values.get("secret", b"")) != 40):
        raise InputError(key_file, "malformed key (expected Z85 public"
                                   + (" and secret keys)" if with_secret else " key)"))
    return values["public"], values.get("secret")


class AllowList:
    """The node public keys in an allow-list folder, read again whenever the folder changes
    (a key added or deleted), so a revocation holds from the next handshake on."""

    def __init__(self, folder: Path):
        self.folder = folder
        self._stamp: tuple | None = None
        self._keys: frozenset[bytes] = frozenset()

    def keys(self) -> frozenset[bytes]:
        try:
            stamp = (self.folder.stat().st_mtime_ns,
                     tuple(sorted((p.name, p.stat().st_mtime_ns)
                                  for p in self.folder.glob("*.key"))))
        except OSError:
            return frozenset()
        if stamp != self._stamp:
            found = set()
            for path in self.folder.glob("*.key"):
                match = re.search(r'public-key\s*=\s*"([^"]{40})"', path.read_text(
                    errors="replace"))
                if match:
                    found.add(match.group(1).encode())
            self._stamp, self._keys = stamp, frozenset(found)
        return self._keys
