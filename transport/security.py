"""Who may connect: every listening socket admits a peer at the ZeroMQ handshake or not at all.

Two ways to be a member of a job:

- **Keys** (``vastray keys``; needed beyond loopback). The coordinator has a key pair of its
  own (``coordinator.key``; its public half in ``coordinator.pub``), each node has its own
  (``nodes/NAME.key``), and ``public/`` is the allow-list of node public keys. Sockets speak
  CURVE: encrypted, and a client is admitted only with a key on the allow-list, read again at
  every handshake (deleting ``public/NAME.key`` shuts NAME out of every later connection).
  No node holds a secret that lets another node, or anyone else, in.
- **No keys** (loopback only). Sockets speak PLAIN with a per-render *join secret*: the
  coordinator hands it to the nodes it starts through an inherited pipe, and for nodes started
  by hand (``--listen`` on loopback) writes it to a file only its user can read
  (``join_secret_path``). Other users of the machine cannot join.

The handshake is also where memory is bounded: a peer that has not authenticated can make a
socket hold at most ``FRAME_LIMIT`` bytes per connection (``MAXMSGSIZE``), for at most
``HANDSHAKE_S`` (``HANDSHAKE_IVL``); larger messages are sent as several frames by the codec.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import secrets
import socket
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.asyncio
from zmq.utils import z85
from zmq.utils.monitor import parse_monitor_message

from vastray.processes import running
from vastray.scene.errors import InputError
from vastray.transport.codec import FRAME_LIMIT

COORDINATOR_KEY = "coordinator.key"
COORDINATOR_PUBLIC = "coordinator.pub"
PUBLIC_DIR = "public"
NODES_DIR = "nodes"
#: The key file of vastray before per-node membership: a pair every node held.
LEGACY_KEY_FILE = "cluster.key"
#: Seconds a connection may take to authenticate before ZeroMQ drops it.
HANDSHAKE_S = 10.0
#: PLAIN user name (the password is what matters).
PLAIN_USER = b"vastray"
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}"

log = logging.getLogger(__name__)


# -- key folders ----------------------------------------------------------------------------

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


def add_node_key(folder: str | os.PathLike, name: str, force: bool = False) -> Path:
    """Give node ``name`` its own key pair (``nodes/NAME.key``) and put its public key on the
    allow-list (``public/NAME.key``).

    Raises
    ------
    InputError
        For a name that is not a plain word, or an existing node key without ``force``.
    """
    folder = _key_folder(folder)
    if not re.fullmatch(NAME_PATTERN, name) or name == "coordinator":
        raise InputError(None, f"node key name {name!r}: use letters, digits, '_', '.', '-'")
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


def load_node_keys(folder: str | os.PathLike, name: str) -> NodeKeys:
    """Node ``name``'s key pair and the coordinator's public key."""
    folder = _existing_folder(folder)
    public, secret = _read_key(folder / NODES_DIR / f"{name}.key",
                               f"no key for node {name!r}; make one with `vastray keys -o "
                               f"{folder} --node {name}` (or name this node's key with "
                               "--key-name)", True)
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


# -- join secrets without keys --------------------------------------------------------------

def new_secret() -> bytes:
    """A fresh join secret (hex text: it travels in PLAIN's password field)."""
    return secrets.token_hex(16).encode()


def runtime_dir() -> Path:
    """Where a coordinator without keys leaves its join secret: ``$VASTRAY_RUNTIME_DIR``, else
    ``~/.vastray/run`` (created owner-only)."""
    return Path(os.environ.get("VASTRAY_RUNTIME_DIR") or Path.home() / ".vastray" / "run")


def join_secret_path(port: int) -> Path:
    return runtime_dir() / f"{socket.gethostname()}-{int(port)}.join"


def _private_dir() -> Path:
    """``runtime_dir()``, made owner-only; refused if another user could read or replace it."""
    folder = runtime_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        info = folder.stat()
    except OSError as exc:
        raise InputError(folder, f"cannot keep the join secret here ({exc.strerror}); set "
                                 "VASTRAY_RUNTIME_DIR to a folder only you can read") from None
    if info.st_uid != os.getuid() or stat.S_IMODE(info.st_mode) & 0o077:
        raise InputError(folder, "must be a folder only you can read (owner "
                                 f"{info.st_uid}, mode {stat.S_IMODE(info.st_mode):o}); fix it "
                                 "with chmod 700 or set VASTRAY_RUNTIME_DIR")
    return folder


def write_join_secret(port: int, secret: bytes) -> Path:
    """Leave ``secret`` for nodes of this user on this machine (mode 0600, beside any left by
    coordinators that are gone, which are removed)."""
    folder = _private_dir()
    for old in folder.glob("*.join"):
        if not _holder_alive(old):
            old.unlink(missing_ok=True)
    path = join_secret_path(port)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"{os.getpid()} {secret.decode()}\n")
    os.replace(tmp, path)
    return path


def _holder_alive(path: Path) -> bool:
    try:
        return running(int(path.read_text().split()[0]))
    except (OSError, ValueError, IndexError):
        return False


def read_join_secret(port: int, timeout: float) -> bytes:
    """The join secret of this user's coordinator listening on ``port`` on this machine,
    waiting up to ``timeout`` seconds for it to start.

    Raises
    ------
    InputError
        When none appears: no coordinator of this user listens there (without keys, only the
        coordinator's own user on its own machine may join).
    """
    path = join_secret_path(port)
    deadline = time.monotonic() + timeout
    while True:
        try:
            pid, secret = path.read_text().split()
            if running(int(pid)) and path.stat().st_uid == os.getuid():
                return secret.encode()
        except (OSError, ValueError):
            pass
        if time.monotonic() > deadline:
            raise InputError(path, f"no join secret of a running coordinator appeared within "
                                   f"{timeout:.0f} s: without --keys, a node joins only a "
                                   "coordinator of its own user on its own machine (give both "
                                   "--keys to join from elsewhere)")
        time.sleep(0.1)


def read_secret_fd(fd: int) -> bytes:
    """The join secret a coordinator wrote into the pipe it handed this node (then closed)."""
    with os.fdopen(fd, "rb") as pipe:
        secret = pipe.read(256).strip()
    if not re.fullmatch(rb"[0-9a-f]{32}", secret):
        raise InputError(None, f"--secret-fd {fd} gave no join secret")
    return secret


# -- sockets ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Credentials:
    """How this process authenticates: by ``keys`` (CURVE) or by a join ``secret`` (PLAIN)."""

    secret: bytes | None = None
    keys: CoordinatorKeys | NodeKeys | None = None

    @property
    def curve(self) -> bool:
        return self.keys is not None


def bound(sock: zmq.Socket, hwm: int = 64) -> None:
    """Bounds every vastray socket keeps: frames of at most ``FRAME_LIMIT`` bytes (a larger
    one ends the connection before it is held), a handshake of at most ``HANDSHAKE_S``, and
    ``hwm`` messages queued each way per connection."""
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, FRAME_LIMIT)
    sock.setsockopt(zmq.HANDSHAKE_IVL, int(HANDSHAKE_S * 1000))
    sock.setsockopt(zmq.RCVHWM, hwm)
    sock.setsockopt(zmq.SNDHWM, hwm)


def serve(sock: zmq.Socket, credentials: Credentials) -> None:
    """Make a listening socket authenticate every connection (call before bind)."""
    bound(sock)
    keys = credentials.keys
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_server = True
    else:
        sock.plain_server = True


def connect_as(sock: zmq.Socket, credentials: Credentials, server_key: bytes | None = None
               ) -> None:
    """Make a connecting socket present this process's credentials (call before connect);
    ``server_key``: the listener's public key (with keys)."""
    bound(sock)
    keys = credentials.keys
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_serverkey = server_key
    else:
        sock.plain_username = PLAIN_USER
        sock.plain_password = credentials.secret


def check_bind(host: str, credentials: Credentials | None) -> None:
    """Refuse to listen beyond loopback without keys."""
    if (credentials is None or credentials.keys is None) and not (
            host.startswith("127.") or host in ("localhost", "::1")):
        raise InputError(None, f"listening on {host} needs keys (--keys DIR from `vastray keys "
                               "-o DIR --node NAME`); without them only nodes of your user on "
                               "this machine may join, and vastray binds loopback only")


class Gate:
    """The ZAP handler of one ZeroMQ context: admits a connection or refuses it at the
    handshake, and counts and logs refusals at a bounded rate (the first few, then every
    hundredth).

    Parameters
    ----------
    ctx : the asyncio context whose listening sockets it guards.
    secret : without keys, the PLAIN password that admits.
    allow : with keys, ``allow(z85_public_key) -> bool``. None until it is known (a node's
        peers before its job comes): a handshake then waits for ``open(allow)`` for up to
        half of ``HANDSHAKE_S``, since refusing it would end the connection for good.
    """

    def __init__(self, ctx: zmq.asyncio.Context, secret: bytes | None = None,
                 allow: Callable[[bytes], bool] | None = None, what: str = "this process"):
        self.secret, self.allow, self.what = secret, allow, what
        self.refusals = 0
        self.failed_handshakes = 0
        self._known = asyncio.Event()
        if allow is not None or secret is not None:
            self._known.set()
        self._pending = 0
        # A ROUTER, not the usual REP: a reply that waits for ``open`` holds back no other.
        self._sock = ctx.socket(zmq.ROUTER)
        self._sock.linger = 0
        self._sock.bind("inproc://zeromq.zap.01")
        self._tasks = [asyncio.ensure_future(self._serve())]

    def close_until_known(self) -> None:
        """Admit no key until the next ``open`` (a node's next job)."""
        self.allow = None
        self._known.clear()

    def open(self, allow: Callable[[bytes], bool]) -> None:
        """Set who is admitted (with keys) and answer the handshakes waiting for it."""
        self.allow = allow
        self._known.set()

    def admit(self, mechanism: bytes, credentials: list[bytes]) -> tuple[bool, bytes, str]:
        """(admitted, user id, reason) for one handshake."""
        if mechanism == b"PLAIN" and self.secret is not None and len(credentials) == 2:
            if secrets.compare_digest(credentials[1], self.secret):
                return True, b"member", "OK"
            return False, b"", "wrong join secret"
        if mechanism == b"CURVE" and self.allow is not None and len(credentials) == 1:
            key = z85.encode(credentials[0])
            if self.allow(key):
                return True, key, "OK"
            return False, b"", f"key {key[:8].decode()}... is not on the allow-list"
        return False, b"", f"{mechanism.decode('ascii', 'replace')[:20]} is not accepted here"

    async def _serve(self) -> None:
        while True:
            request = await self._sock.recv_multipart()
            if len(request) < 8 or request[1] != b"":
                continue  # not from libzmq's ZAP client
            if not self._known.is_set() and self._pending < 64:
                self._pending += 1
                self._tasks.append(asyncio.ensure_future(self._later(request)))
            else:
                await self._answer(request)

    async def _later(self, request: list[bytes]) -> None:
        try:
            await asyncio.wait_for(self._known.wait(), HANDSHAKE_S / 2)
        except TimeoutError:
            pass
        finally:
            self._pending -= 1
        await self._answer(request)

    async def _answer(self, request: list[bytes]) -> None:
        routing, _, version, request_id, _domain, address, _identity, mechanism = request[:8]
        try:
            ok, user, reason = self.admit(mechanism, request[8:])
        except Exception as exc:  # noqa: BLE001 - the gate never dies; refuse
            ok, user, reason = False, b"", f"bad request ({type(exc).__name__}: {exc})"
        if not ok:
            self.refusals += 1
            if self.refusals <= 5 or self.refusals % 100 == 0:
                log.warning("%s refused a connection from %s: %s (%d refused so far)",
                            self.what, address.decode("utf-8", "replace"), reason,
                            self.refusals)
        await self._sock.send_multipart([routing, b"", version, request_id,
                                         b"200" if ok else b"400",
                                         b"OK" if ok else reason.encode()[:200], user, b""])

    def watch(self, sock: zmq.asyncio.Socket, where: str) -> None:
        """Also count and log handshakes on ``sock`` that fail before any ZAP request (a
        CURVE client with no key or the wrong server key; a stranger's protocol)."""
        monitor = sock.get_monitor_socket(zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
                                          | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL)

        async def read() -> None:
            try:
                while True:
                    event = parse_monitor_message(await monitor.recv_multipart())
                    self.failed_handshakes += 1
                    n = self.failed_handshakes
                    if n <= 5 or n % 100 == 0:
                        log.warning("a handshake on %s failed before authentication (%s; %d "
                                    "so far): a client without keys, with another coordinator "
                                    "key, or not speaking ZeroMQ", where,
                                    "protocol error" if event["event"]
                                    & zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL else "no detail", n)
            finally:
                monitor.close(linger=0)

        self._tasks.append(asyncio.ensure_future(read()))

    def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        self._sock.close(linger=0)
