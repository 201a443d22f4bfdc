"""The Live Link Face front: packets from an iPhone become solved frames on the pipeline's front thread.

A :class:`~livebridge.runtime.front.Front`: :meth:`LiveLinkFront.read` takes the newest valid packet off the
receiver (:mod:`livebridge.arkit.receiver`; older ones are superseded, never queued), solves its 52 ARKit
weights into contractions (:class:`~livebridge.arkit.solve.ArkitSolver`) and turns its head rotation into
the frame's head pose (rotation only, about the face model's origin: the phone reports no translation).
Contractions leave finite and in [0, 1] whatever the packet held (a muscle the solver holds keeps its last
value).

The frame's timing: ``capture`` and ``complete`` are the packet's arrival at this machine (the kernel's
receive time where the system gives one, else when the front read it; the phone's own clock is another
device's), ``solved`` the end of the solve; the pipeline fills in ``servo`` (so its "latency servo" is
packet arrival -> servo bytes written) and ``outputs``. ``seq`` is the packet's frame number, ``index``
the front's own count.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from livebridge.arkit.head import head_pose_from_rotation
from livebridge.arkit.names import N_BLENDSHAPES
from livebridge.arkit.receiver import LiveLinkReceiver
from livebridge.arkit.solve import ArkitSolver
from livebridge.runtime.frame import FrameTiming, SolvedFrame
from livebridge.runtime.front import FrontStats

SILENT_S = 1.0  # no valid packet for this long: the phone is reported silent


class LiveLinkFront:
    """Live Link Face packets -> solved frames (see the module docstring).

    Parameters
    ----------
    receiver : LiveLinkReceiver
        Open or not; :meth:`start` starts it. Or a recorded phone take played back
        (:class:`~livebridge.take.phone_replay.PhoneReplay`): the front is then as paced as the replay, and ends
        with it.
    solver : ArkitSolver
    clock : callable
        Host monotonic seconds (the receiver's clock).
    """

    kind = "livelink"
    input_name = "phone"

    def __init__(self, receiver: LiveLinkReceiver, solver: ArkitSolver, clock: Callable[[], float] = time.monotonic):
        self.receiver, self.solver, self.clock = receiver, solver, clock
        self.realtime = bool(receiver.realtime)
        self.muscle_names = tuple(solver.solver.basis.names)
        self.state = solver.initial_state()
        self.frames = 0
        self.cpu_s = 0.0
        self._last = np.zeros(len(self.muscle_names))
        self._started = math.nan
        self._stopped = False

    @property
    def name(self) -> str:
        """The phone as log lines name it: its device id once heard, else the bound address."""
        return self.receiver.device or self.receiver.url

    def warm_up(self) -> None:
        """The solver once (its compiled kernels load on first use), from a throw-away state."""
        self.solver.step(self.solver.initial_state(), np.zeros(N_BLENDSHAPES))

    def start(self) -> None:
        self._started = self.clock()
        self.receiver.open()  # read on the front thread (receive)

    def read(self, timeout: float) -> SolvedFrame | None:
        """The next solved frame from the newest packet, or None when none came within ``timeout`` s."""
        arrival = self.receiver.receive(timeout)
        if arrival is None:
            return None
        t0 = time.thread_time()
        dequeued = self.clock()
        self.state, result = self.solver.step(self.state, arrival.packet.weights)
        x = np.where(np.isfinite(result.contractions), result.contractions, self._last)  # held: last value
        contractions = np.clip(x, 0.0, 1.0)
        self._last = contractions
        solved = self.clock()
        t = arrival.t_arrival
        frame = SolvedFrame(seq=arrival.packet.frame_number, index=self.frames,
                            timing=FrameTiming(t, t, t, dequeued, dequeued, solved),
                            contractions=contractions, held=result.held,
                            quality=(("residual upper mm", float(result.rms_error_mm[0])),
                                     ("residual lower mm", float(result.rms_error_mm[1]))),
                            head_pose=head_pose_from_rotation(arrival.packet.head_rotation), packet=arrival.packet)
        self.frames += 1
        self.cpu_s += time.thread_time() - t0
        return frame

    @property
    def ended(self) -> bool:
        """A network source does not end by itself (only :meth:`stop` ends it); a replayed take does."""
        return self._stopped or self.receiver.ended

    def done(self, frame: SolvedFrame) -> None:
        """Nothing: the phone sends at its own pace."""

    def faults(self) -> dict[str, str]:
        return {}

    def packets_per_s(self) -> float:
        """Valid packets the phone delivered per second over the last ~2 s (0 once it is silent)."""
        arrivals = list(self.receiver.recent)
        if len(arrivals) < 2 or self.clock() - arrivals[-1] > SILENT_S:
            return 0.0
        return (len(arrivals) - 1) / max(arrivals[-1] - arrivals[0], 1e-9)

    def waiting(self) -> str | None:
        if self.frames:
            return None
        heard = self.receiver.received
        refused = self.refused_text()
        return (f"waiting for Live Link Face packets on {self.receiver.url}"
                + (f" ({heard} datagrams, none valid: {refused})" if heard else
                   ": in the app, add this machine's address and port under Live Link targets"))

    def status(self, summary=None) -> str:
        """``phone 60.0 packets/s | lost N | refused N (reason n, ...) | superseded N | residual ...``.

        The pipeline's own "latency servo" figures in the same line are packet arrival -> servo bytes.
        """
        receiver = self.receiver
        line = (f"phone {self.packets_per_s():.1f} packets/s | lost {receiver.lost} | refused "
                f"{self.refused_text()} | superseded {receiver.superseded}")
        silent = self._silent_s()
        if silent > SILENT_S:
            line += f" | SILENT for {silent:.1f} s"
        quality = dict(summary.quality) if summary is not None else {}
        upper, lower = quality.get("residual upper mm", math.nan), quality.get("residual lower mm", math.nan)
        if math.isfinite(upper) or math.isfinite(lower):
            line += f" | residual upper {upper:.3f} lower {lower:.3f} mm"
        return line

    def refused_text(self) -> str:
        """Refused datagrams: ``N (reason n, ...)``."""
        dropped = self.receiver.dropped
        total = sum(dropped.values())
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(dropped.items()))
        return f"{total}" + (f" ({reasons})" if reasons else "")

    def _silent_s(self) -> float:
        """Seconds since the last valid packet (since the start before the first; 0 before the start)."""
        recent = self.receiver.recent
        since = recent[-1] if recent else self._started
        return self.clock() - since if math.isfinite(since) else 0.0

    def stats(self) -> FrontStats:
        receiver = self.receiver
        silent = self._silent_s() > SILENT_S
        refused = sum(receiver.dropped.values())
        return FrontStats(inputs=1, dead=(self.name,) if silent else (),
                          frames_skipped=((self.name, refused),) if refused else (),
                          dropped=receiver.superseded, input_frame_drops=receiver.lost, attempts=self.frames,
                          cpu_s=self.cpu_s)

    def stop(self) -> None:
        self._stopped = True
        self.receiver.stop()
