"""The Live Link Face receiver: ``livelinkface://HOST:PORT`` (UDP), newest packet kept, every refusal counted.

``livelinkface://`` or ``livelinkface://:11111`` binds 127.0.0.1 (this machine only); the phone on the
network is heard only when the bind address is named, e.g. ``livelinkface://0.0.0.0:11111``. Port 0 lets the
system pick a free port (tests). Parameters: ``device=ID`` follows only that phone (default: the first
device heard; packets from any other are counted and dropped).

The consumer reads on its own thread (:meth:`LiveLinkReceiver.receive`): every datagram waiting on the socket
is taken off and decoded (:func:`~livebridge.arkit.packet.decode_packet`) and the newest valid one is returned,
so a packet reaches the solver with no thread hand-over; under a flood the consumer sees the latest face and
the older packets are counted as superseded, never queued.
Refusals are counted by reason (:data:`livebridge.arkit.packet.REASONS`, plus ``other-device`` and
``stale``: a frame number at or behind the last one taken, i.e. reordered). Gaps in the frame numbers are
counted as ``lost`` (packets the network or the socket buffer dropped).

Arrival times are the kernel's receive time of each datagram (``SO_TIMESTAMPNS``, Linux) carried onto the
receiver's clock, so the time a datagram waited in the socket for its reader counts in every latency
measured from arrival; elsewhere, the moment it was read.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

from livebridge.arkit.packet import LiveLinkPacket, PacketError, decode_packet
from livebridge.capture.queue import NewestQueue
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError

SCHEME = "livelinkface"
DEFAULT_BIND = "127.0.0.1"
DEFAULT_PORT = 11111
RESTART_S = 2.0  # a frame number this far behind the last one is a restarted phone, not a reordered packet
_RECV_BYTES = 2048
_TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", None)
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size) if _SO_TIMESTAMPNS is not None else 0


@dataclass(frozen=True)
class Arrival:
    """A valid packet and the host monotonic time it came off the socket (s)."""

    packet: LiveLinkPacket
    t_arrival: float


@dataclass(frozen=True)
class ReceiverAddress:
    """Where a receiver listens: ``host`` (an IP address) and ``port``, and the device it follows."""

    host: str = DEFAULT_BIND
    port: int = DEFAULT_PORT
    device: str | None = None


def parse_receiver_url(url: str) -> ReceiverAddress:
    """``livelinkface://[HOST][:PORT][?device=ID]`` -> :class:`ReceiverAddress`; anything else is an InputError."""
    parsed = DeviceURL.parse(url)
    if parsed.scheme != SCHEME:
        raise InputError(f"a Live Link Face source is {SCHEME}://HOST:PORT, got scheme {parsed.scheme!r}", url)
    parsed.check_known({"device"})
    if parsed.path not in ("", "/"):
        raise InputError(f"{SCHEME}:// takes HOST:PORT only, not the path {parsed.path!r}", url)
    host, colon, port_text = parsed.netloc.rpartition(":") if ":" in parsed.netloc else (parsed.netloc, "", "")
    host = host.strip("[]") or DEFAULT_BIND
    try:
        port = int(port_text) if colon else DEFAULT_PORT
    except ValueError:
        raise InputError(f"port {port_text!r} is not a number", url) from None
    if not 0 <= port <= 65535:
        raise InputError(f"port must be in 0..65535, got {port}", url)
    try:
        socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_NUMERICHOST)
    except (socket.gaierror, UnicodeError):
        raise InputError(f"bind address {host!r} is not an IP address of this machine "
                         "(127.0.0.1, 0.0.0.0, ::1, ...)", url) from None
    device = parsed.query.get("device")
    if device is not None and not device:
        raise InputError("parameter 'device' is empty", url, "device")
    return ReceiverAddress(host, port, device)


class LiveLinkReceiver:
    """Receives Live Link Face packets on a UDP port.

    Parameters
    ----------
    address : ReceiverAddress or str
        Or a ``livelinkface://`` URL.
    clock : callable
        Host monotonic seconds (arrival times).

    Attributes
    ----------
    received : int
        Datagrams taken off the socket.
    accepted : int
        Valid packets handed on (each may still be superseded by a newer one before it is read).
    dropped : Counter
        Refused datagrams by reason.
    lost : int
        Frame numbers skipped between accepted packets.
    realtime : bool
        Always: a phone sends at its own pace (a replayed take may not, see
        :class:`~livebridge.take.phone_replay.PhoneReplay`).
    """

    realtime = True

    def __init__(self, address: ReceiverAddress | str = ReceiverAddress(), clock: Callable[[], float] = time.monotonic):
        self.address = parse_receiver_url(address) if isinstance(address, str) else address
        self.clock = clock
        self._queue: NewestQueue[Arrival] = NewestQueue(1)
        self.received = self.accepted = self.lost = 0
        self.dropped: Counter[str] = Counter()
        self.device = self.address.device
        self.recent: deque[float] = deque(maxlen=120)  # arrival times of the last valid packets (the rate)
        self._last: LiveLinkPacket | None = None
        self._socket: socket.socket | None = None

    @property
    def url(self) -> str:
        """The ``livelinkface://`` URL listened on (the bound port once open)."""
        host, port = self.bound if self._socket is not None else (self.address.host, self.address.port)
        return f"{SCHEME}://{f'[{host}]' if ':' in host else host}:{port}"

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> tuple[str, int]:
        """Bind the socket (the port is taken now; once); returns the bound ``(host, port)``."""
        if self._socket is not None:
            return self.bound
        family = socket.AF_INET6 if ":" in self.address.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind((self.address.host, self.address.port))
        except OSError as error:
            sock.close()
            raise InputError(f"cannot listen on {self.address.host}:{self.address.port} ({error.strerror})",
                             f"{SCHEME}://{self.address.host}:{self.address.port}") from None
        sock.setblocking(False)  # receive() waits in select, then takes what is there
        if _SO_TIMESTAMPNS is not None:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        self._socket = sock
        return sock.getsockname()[:2]

    def stop(self) -> None:
        """Close the socket (a :meth:`receive` waiting on another thread then returns None)."""
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    @property
    def ended(self) -> bool:
        """Never: a phone may always send again."""
        return False

    @property
    def bound(self) -> tuple[str, int]:
        """The bound ``(host, port)``."""
        if self._socket is None:
            raise RuntimeError("the receiver is not open")
        return self._socket.getsockname()[:2]

    def receive(self, timeout: float) -> Arrival | None:
        """After :meth:`open`, on the caller's thread: wait up to ``timeout`` s for the socket, take every
        datagram waiting there, and return the newest valid packet (None: none; also once :meth:`stop` closed
        the socket).

        Reading on the consumer's thread, a packet goes from the socket to the solver with no thread hand-over
        (a hand-over cost up to a switch interval of the interpreter's lock under load: p99 2.1 -> 1.2 ms).
        """
        sock = self._socket
        if sock is None:  # stopped
            return None
        try:
            if select.select([sock], [], [], max(timeout, 0.0))[0]:
                while True:
                    try:
                        data, cmsgs, _, _ = sock.recvmsg(_RECV_BYTES, _ANCILLARY)
                    except BlockingIOError:
                        break
                    self.ingest(data, self._arrival_time(cmsgs))
        except (OSError, ValueError):  # closed under us by stop() (select on a closed socket: ValueError)
            return None
        return self.newest()

    def newest(self) -> Arrival | None:
        """The newest valid packet ingested and not yet read (None: none); the ones before it are superseded."""
        return self._queue.get(0.0)

    def _arrival_time(self, cmsgs) -> float:
        """The datagram's kernel receive time on :attr:`clock` (now, less how long it waited in the socket)."""
        now = self.clock()
        for level, kind, payload in cmsgs:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
                seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
                waited = time.time() - (seconds + 1e-9 * nanoseconds)
                return now - min(max(waited, 0.0), 1.0)  # a wall clock stepped meanwhile: at most 1 s
        return now

    # ------------------------------------------------------------------ packets
    def ingest(self, data: bytes, t_arrival: float) -> Arrival | None:
        """Decode one datagram, count it, and keep it for :meth:`get` when valid; returns it (None: dropped)."""
        self.received += 1
        try:
            packet = decode_packet(data)
        except PacketError as error:
            self.dropped[error.reason] += 1
            return None
        if self.device is None:
            self.device = packet.device_id
        elif packet.device_id != self.device:
            self.dropped["other-device"] += 1
            return None
        last = self._last
        if last is not None:
            gap = packet.frame_number - last.frame_number
            numerator, denominator = packet.rate
            restart = numerator > 0 and denominator > 0 and -gap > RESTART_S * numerator / denominator
            if gap <= 0 and not restart:
                self.dropped["stale"] += 1
                return None
            if gap > 1 and not restart:
                self.lost += gap - 1
        self._last = packet
        self.accepted += 1
        self.recent.append(t_arrival)
        arrival = Arrival(packet, t_arrival)
        self._queue.put(arrival)
        return arrival

    @property
    def superseded(self) -> int:
        """Valid packets replaced by a newer one before they were read."""
        return self._queue.dropped

    def status(self) -> str:
        """Counts for the status line: received, lost, superseded, dropped by reason."""
        dropped = sum(self.dropped.values())
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.dropped.items()))
        return (f"packets {self.received} lost {self.lost} superseded {self.superseded} dropped {dropped}"
                + (f" ({reasons})" if reasons else ""))

    def __enter__(self) -> LiveLinkReceiver:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
