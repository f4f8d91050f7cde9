"""ZeroMQ CURVE for cluster traffic: one key pair per cluster, made by ``vastray keys``.

Every process of a cluster holds the same key pair. Listening sockets are CURVE servers with
the cluster's secret key; connecting sockets are CURVE clients that present the cluster's key
pair; a ZAP authenticator admits only clients presenting the cluster's public key. So traffic
is encrypted, and only holders of the key file can join. Without keys, vastray listens on
loopback only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq

from vastray.scene.errors import InputError

KEY_FILE = "cluster.key"
PUBLIC_DIR = "public"


@dataclass(frozen=True)
class ClusterKeys:
    """The cluster key pair (Z85 bytes) and the folder of public keys the authenticator trusts."""

    public: bytes
    secret: bytes
    public_dir: Path


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
    fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"public = {public.decode()}\nsecret = {secret.decode()}\n")
    # zmq.auth's certificate format, read by configure_curve(location=...).
    (folder / PUBLIC_DIR / "cluster.key").write_text(
        f'metadata\ncurve\n    public-key = "{public.decode()}"\n')
    return key_file


def load_keys(folder: str | os.PathLike) -> ClusterKeys:
    """Read the key pair written by ``generate_keys``."""
    folder = Path(folder)
    key_file = folder / KEY_FILE
    if not key_file.is_file():
        raise InputError(key_file, "no cluster key here; make one with `vastray keys -o DIR`")
    values = {}
    for line in key_file.read_text().splitlines():
        if "=" in line:
            name, value = (part.strip() for part in line.split("=", 1))
            values[name] = value.encode()
    if len(values.get("public", b"")) != 40 or len(values.get("secret", b"")) != 40:
        raise InputError(key_file, "malformed cluster key (expected Z85 public and secret keys)")
    return ClusterKeys(values["public"], values["secret"], folder / PUBLIC_DIR)


def secure_server(sock: zmq.Socket, keys: ClusterKeys | None) -> None:
    """Make a listening socket a CURVE server (no-op without keys)."""
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_server = True


def secure_client(sock: zmq.Socket, keys: ClusterKeys | None) -> None:
    """Make a connecting socket a CURVE client of the cluster (no-op without keys)."""
    if keys is not None:
        sock.curve_secretkey = keys.secret
        sock.curve_publickey = keys.public
        sock.curve_serverkey = keys.public


def start_authenticator(ctx: zmq.Context, keys: ClusterKeys | None):
    """Admit only clients presenting the cluster key (asyncio contexts); None without keys."""
    if keys is None:
        return None
    from zmq.auth.asyncio import AsyncioAuthenticator

    auth = AsyncioAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(keys.public_dir))
    return auth


def check_bind(host: str, keys: ClusterKeys | None) -> None:
    """Refuse to listen beyond loopback without encryption."""
    if keys is None and not (host.startswith("127.") or host in ("localhost", "::1")):
        raise InputError(None, f"listening on {host} needs cluster keys (--keys DIR from "
                               "`vastray keys -o DIR`); without them vastray binds loopback only")
