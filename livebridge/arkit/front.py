"""The Live Link Face front: packets from an iPhone become solved frames on the pipeline's front thread.

A :class:`~livebridge.runtime.front.Front` (FRONT.md): :meth:`LiveLinkFront.read` takes the newest valid
packet off the receiver (:mod:`livebridge.arkit.receiver`; older ones are superseded, never queued), solves
its 52 ARKit weights into contractions (:class:`~livebridge.arkit.solve.ArkitSolver`) and turns its head
rotation into the frame's head pose (rotation only, about the head's origin: the phone reports no
translation). Contractions leave finite and in [0, 1] whatever the packet held.

The frame's timing: ``capture`` and ``complete`` are the packet's arrival off the socket (the phone's own
clock is another device's), ``solved`` the end of the solve; the pipeline fills in ``servo`` and
``outputs``, and :meth:`done` keeps the arrival -> servo-bytes latency of recent frames for the status line.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from livebridge.arkit.head import head_pose_from_rotation
from livebridge.arkit.receiver import LiveLinkReceiver
from livebridge.arkit.solve import ArkitSolver
from livebridge.runtime.frame import FrameTiming, SolvedFrame

_WINDOW = 120  # frames of latency and rate kept for the status line (2 s at 60 Hz)


class LiveLinkFront:
    """Live Link Face packets -> solved frames.

    Parameters
    ----------
    receiver : LiveLinkReceiver
        Not yet started (:meth:`start` starts it).
    solver : ArkitSolver
    clock : callable
        Host monotonic seconds (the receiver's clock).
    """

    kind = "livelink"
    realtime = True

    def __init__(self, receiver: LiveLinkReceiver, solver: ArkitSolver, clock: Callable[[], float] = time.monotonic):
        self.receiver, self.solver, self.clock = receiver, solver, clock
        self.state = solver.initial_state()
        self.seq = 0
        self._arrivals: deque[float] = deque(maxlen=_WINDOW)
        self._latency: deque[float] = deque(maxlen=_WINDOW)
        self._stopped = False

    def start(self) -> None:
        self.receiver.start()

    def read(self, timeout: float) -> SolvedFrame | None:
        """The next solved frame from the newest packet, or None when none came within ``timeout`` s."""
        arrival = self.receiver.get(timeout)
        if arrival is None:
            return None
        dequeued = self.clock()
        self.state, result = self.solver.step(self.state, arrival.packet.weights)
        contractions = np.clip(np.nan_to_num(result.contractions, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
        solved = self.clock()
        t = arrival.t_arrival
        frame = SolvedFrame(seq=self.seq, index=arrival.packet.frame_number,
                            timing=FrameTiming(t, t, t, dequeued, dequeued, solved),
                            contractions=contractions, held=result.held,
                            quality=(("upper mm", float(result.rms_error_mm[0])),
                                     ("lower mm", float(result.rms_error_mm[1]))),
                            head_pose=head_pose_from_rotation(arrival.packet.head_rotation))
        self.seq += 1
        self._arrivals.append(t)
        return frame

    @property
    def ended(self) -> bool:
        """A network source does not end by itself; only :meth:`stop` ends it."""
        return self._stopped

    def done(self, frame: SolvedFrame) -> None:
        """Keep the frame's packet -> servo-bytes latency (when servos wrote it)."""
        if math.isfinite(frame.timing.servo):
            self._latency.append(frame.timing.servo - frame.timing.capture)

    def status(self) -> str:
        """``livelink 60.0 packets/s, packets N lost N ... , packet->servo p50 0.4 ms``."""
        arrivals = list(self._arrivals)
        span = arrivals[-1] - arrivals[0] if len(arrivals) > 1 else 0.0
        rate = (len(arrivals) - 1) / span if span > 0 else 0.0
        text = f"livelink {rate:.1f} packets/s, {self.receiver.status()}"
        if self._latency:
            text += f", packet->servo p50 {1000 * float(np.median(self._latency)):.2f} ms"
        return text

    def stop(self) -> None:
        self._stopped = True
        self.receiver.stop()
