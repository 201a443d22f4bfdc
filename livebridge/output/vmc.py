"""VMC/OSC output: contractions as blendshape values for existing renderers.

The Virtual Motion Capture protocol is OSC over UDP. Per frame, every
blendshape value goes out as ``/VMC/Ext/Blend/Val (string name, float
value)``, then one ``/VMC/Ext/Blend/Apply`` tells the receiver to apply them
all. The messages are packed into OSC bundles that each fit one UDP
datagram of at most ``max_datagram`` bytes (1472 by default, so the IP packet
stays within a 1500-byte Ethernet MTU); ``Apply`` closes the last bundle.

Muscles become blendshapes through the map every blendshape output shares
(:class:`livebridge.output.blendshapes.BlendshapeMap`, also Live Link Face's).
"""

from __future__ import annotations

import ipaddress
import socket
import struct
from collections.abc import Mapping, Sequence

import numpy as np

from livebridge.errors import InputError
from livebridge.output.blendshapes import BlendshapeMap

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 39539
VAL_ADDRESS = "/VMC/Ext/Blend/Val"
APPLY_ADDRESS = "/VMC/Ext/Blend/Apply"
MAX_DATAGRAM = 1472  # 1500-byte MTU minus IPv4 and UDP headers
_BUNDLE_HEADER = b"#bundle\x00" + struct.pack(">Q", 1)  # time tag 1 = "immediately"

def _message_prefix(name: str) -> bytes:
    """``/VMC/Ext/Blend/Val (name, 0.0)`` encoded by python-osc, minus its 4 float bytes."""
    from pythonosc.osc_message_builder import OscMessageBuilder

    builder = OscMessageBuilder(VAL_ADDRESS)
    builder.add_arg(name, "s")
    builder.add_arg(0.0, "f")
    return builder.build().dgram[:-4]


def _apply_message() -> bytes:
    from pythonosc.osc_message_builder import OscMessageBuilder

    return OscMessageBuilder(APPLY_ADDRESS).build().dgram


class VMCEncoder:
    """Encodes blendshape values as VMC bundles that each fit one datagram.

    The OSC encoding of every message comes from python-osc once; per frame
    only the big-endian float32 values change.
    """

    def __init__(self, names: Sequence[str], max_datagram: int = MAX_DATAGRAM):
        self.names = tuple(names)
        self._prefixes = [_message_prefix(name) for name in self.names]
        self._apply = _apply_message()
        self.max_datagram = max_datagram
        smallest = len(_BUNDLE_HEADER) + 4 + max([len(p) + 4 for p in self._prefixes] + [0]) + 4 + len(self._apply)
        if max_datagram < smallest:
            raise InputError(f"max_datagram {max_datagram} is too small for one message (needs {smallest})",
                             field="max_datagram")

    def encode(self, values: np.ndarray) -> list[bytes]:
        """OSC bundles for one frame, in sending order; ``Apply`` is the last message of the last bundle.

        Parameters
        ----------
        values : ndarray, shape (n_blendshapes,)
        """
        packed = struct.pack(f">{len(self.names)}f", *np.asarray(values, dtype=np.float64))
        bundles, parts, size = [], [_BUNDLE_HEADER], len(_BUNDLE_HEADER)
        for k, prefix in enumerate(self._prefixes):
            message = prefix + packed[4 * k:4 * k + 4]
            if size + 4 + len(message) > self.max_datagram:
                bundles.append(b"".join(parts))
                parts, size = [_BUNDLE_HEADER], len(_BUNDLE_HEADER)
            parts += [struct.pack(">i", len(message)), message]
            size += 4 + len(message)
        if size + 4 + len(self._apply) > self.max_datagram:
            bundles.append(b"".join(parts))
            parts = [_BUNDLE_HEADER]
        parts += [struct.pack(">i", len(self._apply)), self._apply]
        bundles.append(b"".join(parts))
        return bundles


class VMCOutput:
    """Sends contractions to a VMC receiver over UDP.

    Parameters
    ----------
    muscle_names : sequence of str
    host, port : str, int
        The receiver (default ``127.0.0.1:39539``, the VMC performer port). Another machine is reached only
        when its host is given here; :meth:`describe` says so, for the start-up banner.
    mapping, case : see :class:`BlendshapeMap`
    max_datagram : int
        Largest datagram sent, bytes.

    Sending never blocks: a datagram the OS cannot take at once (or that it
    refuses, e.g. the network went down) is dropped and counted in
    :attr:`dropped`; the last such error is kept in :attr:`last_error`.
    """

    def __init__(self, muscle_names: Sequence[str], host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 mapping: Mapping | str | None = None, case: str = "camel", max_datagram: int = MAX_DATAGRAM):
        self.map = BlendshapeMap(muscle_names, mapping, case)
        self.encoder = VMCEncoder(self.map.names, max_datagram)
        family, self.address = resolve_destination(host, port)
        self.host = host
        self.is_local = ipaddress.ip_address(self.address[0].split("%")[0]).is_loopback
        self._socket = socket.socket(family, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.sent = 0
        self.dropped = 0
        self.bytes_sent = 0
        self.last_error: OSError | None = None

    def describe(self) -> str:
        """One line for the start-up banner: where the datagrams go, and whether they leave this machine."""
        ip, port = self.address[:2]
        where = f"[{ip}]:{port}" if ":" in ip else f"{ip}:{port}"
        named = "" if self.host == ip else f" ({self.host})"
        if self.is_local:
            return f"VMC/OSC: sending to {where}{named} on this machine"
        return f"VMC/OSC: sending to {where}{named}, ANOTHER MACHINE: the face's contractions leave this computer"

    def send(self, frame) -> None:
        """Send one solved frame (:class:`~livebridge.output.Output`)."""
        self.send_contractions(frame.contractions)

    def send_contractions(self, contractions: np.ndarray) -> int:
        """Send one frame's contractions; returns the number of datagrams sent."""
        count = 0
        for datagram in self.encoder.encode(self.map(contractions)):
            try:
                self.bytes_sent += self._socket.sendto(datagram, self.address)
                count += 1
            except OSError as error:  # full buffer, nobody listening, network down: drop, never stall
                self.dropped += 1
                self.last_error = error
        self.sent += count
        return count

    def close(self) -> None:
        self._socket.close()

    def __enter__(self) -> VMCOutput:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def resolve_destination(host: str, port: int) -> tuple[int, tuple]:
    """``(address family, socket address)`` of a UDP receiver; a bad host or port raises InputError naming it."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise InputError(f"must be a port number 1..65535, got {port!r}", field="port")
    if not isinstance(host, str) or not host.strip():
        raise InputError(f"must name the receiving machine, got {host!r}", field="host")
    try:
        family, _, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
    except (socket.gaierror, UnicodeError) as error:
        raise InputError(f"cannot resolve VMC host {host!r} ({error})", field="host") from None
    ip = ipaddress.ip_address(address[0].split("%")[0])
    if ip.is_unspecified or ip == ipaddress.ip_address("255.255.255.255"):
        raise InputError(f"{host!r} is not one receiver (unspecified or broadcast address)", field="host")
    return family, address
