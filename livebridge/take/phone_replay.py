"""A phone take played back as the phone: ``[source] kind = "livelinkface"`` with ``url = "replay://TAKE_DIR"``.

``replay://TAKE_DIR?realtime=1&loop=0`` opens the Live Link Face packets a phone take recorded
(:mod:`livebridge.take.phone`) as a receiver the :class:`~livebridge.arkit.front.LiveLinkFront` reads in place
of :class:`~livebridge.arkit.receiver.LiveLinkReceiver`: the same packets in the same order, so the take is
solved again (with this session's basis, shapes and solver) and drives the servos, the render client and
every output as it did live, and a recording of the replay is a phone take again.

Timing: ``realtime=1`` (default) plays each packet at its recorded arrival time moved onto this host's clock
(the first when it is first read), so the servos move as they did live. ``realtime=0`` plays as fast as the
pipeline reads (it then runs in step with its outputs, nothing dropped), each packet arriving when it is read:
latencies stay honest, and the servos' safety stage (slew, filters) sees the replay's pace, not the
performer's. ``loop=1`` starts again at the end, the times running on.

Everything is read and checked when the replay is made (:class:`PhoneReplay`), so a damaged take is refused
before anything moves, with an error naming the file and the field.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from pathlib import Path

import numpy as np

from livebridge.arkit.packet import LiveLinkPacket
from livebridge.arkit.receiver import Arrival
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.take.directory import MANIFEST, load_manifest, read_arkit
from livebridge.take.replay import wait_until_due

SCHEME = "replay"


def parse_replay_url(url: str) -> tuple[Path, bool, bool]:
    """``replay://PATH?realtime=1&loop=0`` -> ``(path, realtime, loop)``; anything else is an InputError."""
    parsed = DeviceURL.parse(url)
    if parsed.scheme != SCHEME:
        raise InputError(f"a phone take is replayed with {SCHEME}://TAKE_DIR, got scheme {parsed.scheme!r}", url)
    parsed.check_known({"realtime", "loop"})
    path = parsed.netloc + parsed.path if parsed.netloc else parsed.path
    if not path:
        raise InputError("replay:// needs a take folder", url)
    return Path(path), parsed.take("realtime", bool, True), parsed.take("loop", bool, False)


class PhoneReplay:
    """A phone take's packets, read like a :class:`~livebridge.arkit.receiver.LiveLinkReceiver` (see the module
    docstring).

    Parameters
    ----------
    path : str or Path
        The take directory.
    realtime, loop : bool
    clock : callable
        Host monotonic seconds.

    Raises
    ------
    InputError
        The folder is no take, a take from cameras (no ``arkit``), or its ``arkit.csv`` is damaged or holds no
        packet.
    """

    def __init__(self, path, realtime: bool = True, loop: bool = False, clock: Callable[[], float] = time.monotonic):
        self.path = Path(path)
        manifest = load_manifest(self.path)
        if "arkit" not in manifest:
            raise InputError("this take holds no ARKit weights (it was recorded from cameras: replay it with "
                             "[cameras] urls = [\"replay://...\"] and raw frames)", self.path / MANIFEST, "arkit")
        self.track = read_arkit(self.path / manifest["arkit"])
        if not len(self.track.t):
            raise InputError("no packets recorded (the take ended before the phone sent any)",
                             self.path / manifest["arkit"])
        self.device = manifest.get("device_id", "")
        self.subject = manifest.get("subject", "")
        self.realtime, self.loop, self.clock = bool(realtime), bool(loop), clock
        self.received = self.accepted = self.lost = 0
        self.dropped: Counter[str] = Counter()
        self.superseded = 0
        self.recent: deque[float] = deque(maxlen=120)
        self._index = 0
        self._lap_s = 0.0
        self._offset: float | None = None  # host time - recorded time, fixed by the first packet
        self._open = self._ended = False

    @property
    def url(self) -> str:
        return f"{SCHEME}://{self.path}"

    @property
    def ended(self) -> bool:
        """Every packet played (never, looping) or stopped."""
        return self._ended

    def open(self) -> None:
        """Start playing; the first packet read arrives then."""
        self._open = True

    def stop(self) -> None:
        self._ended = True

    def _packet(self, k: int) -> LiveLinkPacket:
        track = self.track
        return LiveLinkPacket(self.device, self.subject, int(track.frame_number[k]), float(track.sub_frame[k]),
                              (int(track.rate[k, 0]), int(track.rate[k, 1])), track.values[k].copy())

    def _next_lap(self) -> bool:
        t = self.track.t
        if not self.loop:
            self._ended = True
            return False
        steps = np.diff(t)
        step = float(np.median(steps)) if len(steps) else 1.0 / 60.0  # the lap's last packet lasts a usual step
        self._lap_s += float(t[-1] - t[0]) + step
        self._index = 0
        return True

    def receive(self, timeout: float) -> Arrival | None:
        """The next packet at its (shifted) recorded arrival time; None when it is not due within ``timeout`` s
        (paced), at the end, or once stopped."""
        if not self._open or self._ended or (self._index >= len(self.track.t) and not self._next_lap()):
            return None
        now = self.clock()
        if self._offset is None:
            self._offset = now - float(self.track.t[0])
        t_arrival = now
        if self.realtime:
            t_arrival = float(self.track.t[self._index]) + self._lap_s + self._offset
            if not wait_until_due(t_arrival - now, timeout):
                return None
        packet = self._packet(self._index)
        self._index += 1
        self.received += 1
        self.accepted += 1
        self.recent.append(t_arrival)
        return Arrival(packet, t_arrival)


def open_phone_replay(url: str) -> PhoneReplay:
    """The :class:`PhoneReplay` of a ``replay://`` URL."""
    path, realtime, loop = parse_replay_url(url)
    return PhoneReplay(path, realtime, loop)
