"""ZeroMQ CURVE for cluster traffic, with keys made by ``vastray keys``.

A key folder holds the cluster key pair (``cluster.key``), optionally one key pair per node
(``nodes/NAME.key``), and the allow-list (``public/``: one certificate per public key that
may connect). Listening sockets are CURVE servers with the cluster's secret key; connecting
sockets are CURVE clients presenting their node's own key pair (or the cluster's, for nodes
without one); a ZAP authenticator admits only clients whose public key is on the allow-list,
and logs each refusal with the peer's address. Traffic is encrypted; removing a node's
certificate from ``public/`` shuts that node out without re-keying the others. Without keys,
vastray listens on loopback only.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

import zmq

from vastray.scene.errors import InputError

KEY_FILE = "cluster.key"
PUBLIC_DIR = "public"
NODES_DIR = "nodes"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClusterKeys:
    """The cluster key pair (Z85 bytes) and the folder of public keys the authenticator trusts."""

    public: bytes
    secret: bytes
    public_dir: Path
    client_public: bytes | None = None  # this node's own key pair (default: the cluster's)
    client_secret: bytes | None = None


def generate_keys(folder: str | os.PathLike, force: bool = False) -> Path:
    """Write a new cluster key pair into ``folder`` (secret file readable by the owner only).

    Raises
    ------
    InputError
        When ``folder`` already holds a key and ``force`` is not given: replacing it would
        lock every node that has the old one out of the cluster.
    """
    folder = Path(folder)
    if (folder / KEY_FILE).exists() and not force:
        raise InputError(folder / KEY_FILE, "a cluster key exists already; nodes holding it "
                                           "would be locked out (pass --force to replace it)")
    (folder / PUBLIC_DIR).mkdir(parents=True, exist_ok=True)
    public, secret = zmq.curve_keypair()
    key_file = folder / KEY_FILE
    _write_pair(key_file, public, secret)
    _allow(folder, "cluster", public)
    return key_file


def add_node_key(folder: str | os.PathLike, name: str, force: bool = False) -> Path:
    """Give node ``name`` its own key pair (``nodes/NAME.key``) and put its public key on the
    allow-list; the cluster key pair must exist.

    Raises
    ------
    InputError
        For a name that is not a plain word, a missing cluster key, or an existing node key
        without ``force``.
    """
    folder = Path(folder)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", name) or name == "cluster":
        raise InputError(None, f"node key name {name!r}: use letters, digits, '_', '.', '-'")
    if not (folder / KEY_FILE).is_file():
        raise InputError(folder / KEY_FILE, "no cluster key here; make one first "
                                           "(`vastray keys -o DIR`)")
    key_file = folder / NODES_DIR / f"{name}.key"
    if key_file.exists() and not force:
        raise InputError(key_file, "this node has a key already (pass --force to replace it)")
    key_file.parent.mkdir(parents=True, exist_ok=True)
    public, secret = zmq.curve_keypair()
    _write_pair(key_file, public, secret)
    _allow(folder, name, public)
    return key_file


def _write_pair(path: Path, public: bytes, secret: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"public = {public.decode()}\nsecret = {secret.decode()}\n")


def _allow(folder: Path, name: str, public: bytes) -> None:
    """Put ``public`` on the allow-list (zmq.auth's certificate format, read by
    ``configure_curve(location=...)``)."""
    (folder / PUBLIC_DIR / f"{name}.key").write_text(
        f'metadata\ncurve\n    public-key = "{public.decode()}"\n')


def load_keys(folder: str | os.PathLike, node: str | None = None) -> ClusterKeys:
    """Read the cluster key pair, and node ``node``'s own pair when named."""
    folder = Path(folder)
    public, secret = _read_pair(folder / KEY_FILE, "no cluster key here; make one with "
                                                   "`vastray keys -o DIR`")
    if node is None:
        return ClusterKeys(public, secret, folder / PUBLIC_DIR)
    client = _read_pair(folder / NODES_DIR / f"{node}.key",
                        f"no key for node {node!r}; make one with `vastray keys -o DIR "
                        f"--node {node}`")
    return ClusterKeys(public, secret, folder / PUBLIC_DIR, *client)


def _read_pair(key_file: Path, missing: str) -> tuple[bytes, bytes]:
    if not key_file.is_file():
        raise InputError(key_file, missing)
    values = {}
    for line in key_file.read_text().splitlines():
        if "=" in line:
            name, value = (part.strip() for part in line.split("=", 1))
            values[name] = value.encode()
    if len(values.get("public", b"")) != 40 or len(values.get("secret", b"")) != 40:
        raise InputError(key_file, "malformed key (expected Z85 public and secret keys)")
    return values["public"], values["secret"]


def secure_server(sock: zmq.Socket, keys: ClusterKeys | None) -> None:
    """Make a listening socket a CURVE server (no-op without keys)."""
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_server = True


def secure_client(sock: zmq.Socket, keys: ClusterKeys | None) -> None:
    """Make a connecting socket a CURVE client of the cluster (no-op without keys)."""
    if keys is not None:
        sock.curve_secretkey = keys.client_secret or keys.secret
        sock.curve_publickey = keys.client_public or keys.public
        sock.curve_serverkey = keys.public


def start_authenticator(ctx: zmq.Context, keys: ClusterKeys | None):
    """Admit only clients presenting the cluster key (asyncio contexts); None without keys."""
    if keys is None:
        return None
    auth = _make_authenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(keys.public_dir))
    return auth


def check_bind(host: str, keys: ClusterKeys | None) -> None:
    """Refuse to listen beyond loopback without encryption."""
    if keys is None and not (host.startswith("127.") or host in ("localhost", "::1")):
        raise InputError(None, f"listening on {host} needs cluster keys (--keys DIR from "
                               "`vastray keys -o DIR`); without them vastray binds loopback only")


def _make_authenticator(ctx: zmq.Context):
    """A ZAP authenticator that logs every refusal with the peer's address (the first few,
    then every hundredth: a refused client retries its handshake ten times a second)."""
    from zmq.auth.asyncio import AsyncioAuthenticator

    class LoggingAuthenticator(AsyncioAuthenticator):
        refusals = 0
        _peer = "?"

        async def handle_zap_message(self, msg: list[bytes]) -> None:
            if len(msg) > 3:
                self._peer = msg[3].decode("utf-8", "replace")
            await super().handle_zap_message(msg)

        def _send_zap_reply(self, request_id, status_code, status_text, user_id="anonymous"):
            if status_code != b"200":
                self.refusals += 1
                if self.refusals <= 5 or self.refusals % 100 == 0:
                    log.warning("refused a CURVE connection from %s (%s; %d refused so far): "
                                "its key is not on the allow-list", self._peer,
                                status_text.decode("utf-8", "replace") or "unknown key",
                                self.refusals)
            super()._send_zap_reply(request_id, status_code, status_text, user_id)

    return LoggingAuthenticator(ctx)
