"""A simulated iPhone running Live Link Face: the app's packets, at 60 Hz, from a performer script.

The phone "sees" a performer (:class:`~livebridge.simulators.performer.ContractionScript` contractions
``x(t)`` and :class:`~livebridge.simulators.performer.HeadMotion` head rotation) and reports what ARKit
would: the 52 blendshape weights the shared muscle -> blendshape map makes of ``x(t)`` (clipped to [0, 1],
plus Gaussian noise ``noise`` when asked), the head's yaw, pitch and roll, the eyes at rest, in version-6
packets (:mod:`livebridge.arkit.packet`) with the app's frame time (frame number and sub-frame at 60/1)
and a device id and subject name. Everything is a deterministic function of ``(seed, frame)``, and
:meth:`SimulatedIPhone.truth` gives the contractions behind any frame, so a receiver's result can be
scored against ground truth.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Sequence

import numpy as np

from livebridge.arkit.head import rotation_from_head_pose
from livebridge.arkit.names import ARKIT_NAMES, HEAD_ROTATION, N_BLENDSHAPES, N_VALUES
from livebridge.arkit.packet import LiveLinkPacket, encode_packet
from livebridge.output.blendshapes import BlendshapeMap
from livebridge.simulators.performer import ContractionScript, HeadMotion

DEVICE_ID = "5A1E0D2C-1F3B-4C6D-8E9F-0A1B2C3D4E5F"  # the app sends the phone's UUID
SUBJECT = "iPhoneSim"
SEND_TIMES_KEPT = 36_000  # packets whose send time is kept (10 min at 60 Hz): a demo runs for hours


class SimulatedIPhone:
    """Sends Live Link Face packets to ``host:port`` over UDP.

    Parameters
    ----------
    muscle_names : sequence of str
        The performer's muscles (the basis the receiving side solves with, or any other).
    host, port : str, int
        Where the packets go (tests and the demo: loopback).
    script, seed : performer script and seed (:class:`ContractionScript`)
    fps : float
        Packets per second (the app: 60).
    noise : float
        Standard deviation of Gaussian noise on the weights (ARKit's tracking noise), before clipping.
    head_motion : bool
        Turn the head (a few degrees, smoothly); False: the head faces the phone.
    frame0 : int
        Frame number of the first packet (the app counts frames of the day's timecode).
    """

    def __init__(self, muscle_names: Sequence[str], host: str = "127.0.0.1", port: int = 11111,
                 script: str = "mixed", seed: int = 0, fps: float = 60.0, noise: float = 0.0,
                 head_motion: bool = True, frame0: int = 3_600 * 60, device_id: str = DEVICE_ID,
                 subject: str = SUBJECT):
        self.script = ContractionScript(muscle_names, script, seed)
        self.rows = BlendshapeMap(muscle_names).rows_for(ARKIT_NAMES)  # (52, n_muscles)
        self.head = HeadMotion(np.zeros(3), seed) if head_motion else None
        self.fps, self.noise, self.seed, self.frame0 = float(fps), float(noise), int(seed), int(frame0)
        self.device_id, self.subject = device_id, subject
        self.address = (host, port)
        self.sent = 0
        self.send_times: dict[int, float] = {}  # frame number -> host monotonic time sent (the recent ones)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def truth(self, frame: int | np.ndarray) -> np.ndarray:
        """The performer's contractions behind frame number(s) ``frame``, shape (..., n_muscles)."""
        return self.script((np.asarray(frame) - self.frame0) / self.fps)

    def packet(self, frame: int) -> LiveLinkPacket:
        """The packet the phone sends for frame number ``frame``."""
        t = (frame - self.frame0) / self.fps
        values = np.zeros(N_VALUES)
        weights = self.rows @ self.script(np.array([t]))[0]
        if self.noise > 0:
            weights += np.random.default_rng([self.seed, frame, 5]).normal(0.0, self.noise, N_BLENDSHAPES)
        values[:N_BLENDSHAPES] = np.clip(weights, 0.0, 1.0)
        if self.head is not None:
            values[HEAD_ROTATION] = rotation_from_head_pose(self.head(np.array([t]))[0])
        return LiveLinkPacket(self.device_id, self.subject, frame, 0.0, (int(round(self.fps)), 1), values)

    def datagram(self, frame: int) -> bytes:
        return encode_packet(self.packet(frame))

    # ------------------------------------------------------------------ sending
    def run(self, n_frames: int | None, realtime: bool = True) -> int:
        """Send ``n_frames`` packets (None: until :meth:`stop`), paced at ``fps`` or as fast as possible; returns
        the number sent."""
        family = socket.AF_INET6 if ":" in self.address[0] else socket.AF_INET
        with socket.socket(family, socket.SOCK_DGRAM) as sock:
            t0 = time.monotonic()
            k = 0
            while (n_frames is None or k < n_frames) and not self._stop.is_set():
                if realtime:
                    delay = t0 + k / self.fps - time.monotonic()
                    if delay > 0:
                        self._stop.wait(delay)
                frame = self.frame0 + k
                data = self.datagram(frame)
                self.send_times[frame] = time.monotonic()
                self.send_times.pop(frame - SEND_TIMES_KEPT, None)
                sock.sendto(data, self.address)
                self.sent += 1
                k += 1
        return self.sent

    def start(self, n_frames: int | None = None, realtime: bool = True) -> None:
        """Send in a background thread (None: until :meth:`stop`)."""
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, args=(n_frames, realtime), name="iphone-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
