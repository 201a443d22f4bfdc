"""VMC/OSC output: contractions as blendshape values for existing renderers.

The Virtual Motion Capture protocol is OSC over UDP. Per frame, every
blendshape value goes out as ``/VMC/Ext/Blend/Val (string name, float
value)``, then one ``/VMC/Ext/Blend/Apply`` tells the receiver to apply them
all. The messages are packed into OSC bundles that each fit one UDP
datagram of at most ``max_datagram`` bytes (1472 by default, so the IP packet
stays within a 1500-byte Ethernet MTU); ``Apply`` closes the last bundle.

Muscles become blendshapes through a linear map: each muscle drives one or
more blendshapes with weights, and a blendshape's value is the weighted sum,
clipped to [0, 1]. The default map sends the 16 Choe-Ko muscles to Apple
ARKit blendshape names (the names Perfect-Sync avatars and VSeeFace use);
receivers differ in case, so the names can be written ``camel``
(``browInnerUp``, ARKit's own spelling), ``pascal`` (``BrowInnerUp``),
``lower`` (``browinnerup``) or ``snake`` (``brow_inner_up``).
"""

from __future__ import annotations

import ipaddress
import re
import socket
import struct
from collections.abc import Mapping, Sequence

import numpy as np

from livebridge.errors import InputError

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 39539
VAL_ADDRESS = "/VMC/Ext/Blend/Val"
APPLY_ADDRESS = "/VMC/Ext/Blend/Apply"
MAX_DATAGRAM = 1472  # 1500-byte MTU minus IPv4 and UDP headers
CASES = ("camel", "pascal", "lower", "snake")
_BUNDLE_HEADER = b"#bundle\x00" + struct.pack(">Q", 1)  # time tag 1 = "immediately"

# Choe-Ko muscle -> ARKit blendshapes (from the ICT-FaceKit shapes the reference basis is built from).
ARKIT_MAPPING: dict[str, dict[str, float]] = {
    "frontalis_L": {"browInnerUp": 0.5, "browOuterUpLeft": 1.0},
    "frontalis_R": {"browInnerUp": 0.5, "browOuterUpRight": 1.0},
    "corrugator_L": {"browDownLeft": 1.0},
    "corrugator_R": {"browDownRight": 1.0},
    "orbicularis_oculi_L": {"eyeBlinkLeft": 1.0},
    "orbicularis_oculi_R": {"eyeBlinkRight": 1.0},
    "levator_labii_L": {"noseSneerLeft": 1.0},
    "levator_labii_R": {"noseSneerRight": 1.0},
    "zygomatic_major_L": {"mouthSmileLeft": 1.0},
    "zygomatic_major_R": {"mouthSmileRight": 1.0},
    "risorius_L": {"mouthStretchLeft": 1.0},
    "risorius_R": {"mouthStretchRight": 1.0},
    "depressor_anguli_oris": {"mouthFrownLeft": 1.0, "mouthFrownRight": 1.0},
    "orbicularis_oris": {"mouthPucker": 1.0},
    "lips_pressor": {"mouthPressLeft": 1.0, "mouthPressRight": 1.0},
    "jaw": {"jawOpen": 1.0},
}


def convert_case(name: str, case: str) -> str:
    """Spell a camelCase blendshape name in ``case`` (one of :data:`CASES`)."""
    if case == "camel":
        return name[:1].lower() + name[1:]
    if case == "pascal":
        return name[:1].upper() + name[1:]
    if case == "lower":
        return name.lower()
    if case == "snake":
        return re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", name).lower()
    raise InputError(f"case must be one of {CASES}, got {case!r}", field="case")


class BlendshapeMap:
    """Linear map from contractions to blendshape values.

    Parameters
    ----------
    muscle_names : sequence of str, length n_muscles
        The basis's muscles, in order.
    mapping : mapping of str to mapping of str to float, optional
        ``{muscle: {blendshape: weight}}``; default :data:`ARKIT_MAPPING`.
        ``"identity"`` sends each muscle under its own name. Muscles the
        mapping does not name drive nothing; a mapping entry for a muscle the
        basis lacks is an error.
    case : str
        Spelling of the blendshape names, one of :data:`CASES`.

    Attributes
    ----------
    names : tuple of str, length n_blendshapes
    matrix : ndarray, shape (n_blendshapes, n_muscles)
    """

    def __init__(self, muscle_names: Sequence[str], mapping: Mapping | str | None = None, case: str = "camel"):
        muscle_names = tuple(muscle_names)
        if mapping is None:
            mapping = ARKIT_MAPPING
        if mapping == "identity":
            mapping = {name: {name: 1.0} for name in muscle_names}
            case_of = {name: name for name in muscle_names}
        else:
            case_of = None
        if not isinstance(mapping, Mapping):
            raise InputError("mapping must be a table of {muscle = {blendshape = weight}} or 'identity'",
                             field="mapping")
        columns: dict[str, dict[int, float]] = {}
        for muscle, targets in mapping.items():
            if muscle not in muscle_names:
                if mapping is ARKIT_MAPPING:
                    continue  # the default map covers the Choe-Ko muscles a basis may not have
                raise InputError(f"unknown muscle {muscle!r}; the basis has {', '.join(muscle_names)}",
                                 field=f"mapping.{muscle}")
            if not isinstance(targets, Mapping):
                raise InputError("expected a table {blendshape = weight}", field=f"mapping.{muscle}")
            for shape, weight in targets.items():
                if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not np.isfinite(weight):
                    raise InputError(f"weight must be a finite number, got {weight!r}",
                                     field=f"mapping.{muscle}.{shape}")
                name = case_of[shape] if case_of else convert_case(shape, case)
                columns.setdefault(name, {})[muscle_names.index(muscle)] = float(weight)
        self.names = tuple(columns)
        self.matrix = np.zeros((len(self.names), len(muscle_names)))
        for row, weights in enumerate(columns.values()):
            for column, weight in weights.items():
                self.matrix[row, column] += weight

    def __call__(self, contractions: np.ndarray) -> np.ndarray:
        """Blendshape values in [0, 1], shape (n_blendshapes,), from contractions (n_muscles,); NaN -> 0."""
        values = self.matrix @ np.nan_to_num(np.asarray(contractions, dtype=np.float64), nan=0.0)
        return np.clip(values, 0.0, 1.0)


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
