"""The optional shared key of a rig's nodes and host: ZeroMQ CURVE encryption and authentication.

A key file holds any secret of at least 32 bytes (``head -c 32 /dev/urandom > rig.key``), copied to every
node and to the host. Both derive one CURVE key pair from it (SHA-256 of the file): the node is the CURVE
server with that pair and accepts only clients that present the same public key, the host is the client
with the same pair; so only holders of the file can connect, and the traffic is encrypted.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

from livebridge.errors import InputError
from livebridge.nodes import require

MIN_KEY_BYTES = 32


@dataclass(frozen=True)
class SharedKey:
    """A CURVE key pair (Z85) derived from a shared key file."""

    public: bytes
    secret: bytes

    @classmethod
    def load(cls, path: str | Path) -> SharedKey:
        """The key pair of key file ``path`` (:class:`InputError` when it is missing or shorter than 32 bytes)."""
        zmq, _ = require()
        try:
            data = Path(path).read_bytes()
        except OSError as error:
            raise InputError(f"cannot read the key file: {error.strerror or error}", str(path)) from None
        if len(data) < MIN_KEY_BYTES:
            raise InputError(f"a key file holds at least {MIN_KEY_BYTES} bytes of secret, this one {len(data)} "
                             "(make one with: head -c 32 /dev/urandom > rig.key)", str(path))
        if not zmq.has("curve"):
            raise InputError("this pyzmq's libzmq has no CURVE security: install a pyzmq wheel (it bundles one "
                             "with CURVE) to use a shared key", str(path))
        from zmq.utils import z85

        secret = z85.encode(hashlib.sha256(data).digest())
        return cls(zmq.curve_public(secret), secret)

    def serve(self, socket) -> None:
        """Make ``socket`` (a node's) a CURVE server with this pair."""
        socket.curve_secretkey, socket.curve_publickey, socket.curve_server = self.secret, self.public, True

    def connect(self, socket) -> None:
        """Make ``socket`` (the host's) a CURVE client of a node serving this pair."""
        socket.curve_secretkey, socket.curve_publickey, socket.curve_serverkey = self.secret, self.public, self.public

    def authenticator(self, context):
        """A started ZAP authenticator on ``context`` that admits only clients holding this key; stop it with
        ``.stop()``."""
        from zmq.auth.thread import ThreadAuthenticator

        auth = ThreadAuthenticator(context)
        auth.start()
        auth.configure_curve_callback("*", credentials_provider=_SameKey(self.public))
        return auth


class _SameKey:
    """ZAP credentials provider: the client's public key must be the shared one."""

    def __init__(self, public: bytes):
        self.public = public

    def callback(self, domain: str, key: bytes | str) -> bool:
        """``key``: the client's public key, Z85."""
        return (key.encode() if isinstance(key, str) else bytes(key)) == self.public
