"""Grouping frames from several cameras into frame sets of one instant.

Rules (:class:`Synchronizer`):

- Cameras in one hardware ``sync_domain`` are grouped by frame counter (``seq``): frames with the same
  ``seq`` in a domain belong together, whatever their timestamps say.
- Across domains frames are grouped by ``t_capture``: a frame joins the open frame set whose mean time
  is closest, if within ``tolerance_s`` (at most half a frame period) and that set has no frame of the
  same camera yet, nor of the same domain with another ``seq``.
- A frame set leaves as soon as every live camera has either delivered its frame or moved past it (each
  camera delivers in order), or when it is ``max_wait_s`` older than the newest time seen (a camera
  that lags). Missing frames count as *drops*; a frame that arrives after its set left is *late* and is
  discarded (frame sets leave in time order and are never revised).
- A camera with no frame for ``dead_after_s`` is marked *dead* and reported; the rest keep going (frame
  sets no longer wait for it). It comes back to life with its next frame.

The synchroniser keeps no clock of its own: time advances with the frames' ``t_capture`` and with
``poll(now)``, so it runs identically live and in tests. :class:`SyncedCapture` runs sources on
reader threads and hands out frame sets through a bounded queue that keeps the newest; with
``realtime=True`` (live cameras) a ticker also polls with the host clock, with ``realtime=False``
(unpaced simulators and replays) time follows the frames only.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from livebridge.capture.frame import Frame, FrameSet
from livebridge.capture.queue import NewestQueue

MAX_DELIVERY_DELAY_S = 1.0  # a live synchroniser's host clock lags by at most this much (see SyncedCapture)


@dataclass(frozen=True)
class SyncStats:
    """Counters of a synchroniser.

    Attributes
    ----------
    framesets : int
        Frame sets emitted.
    complete : int
        Frame sets emitted with a frame from every camera.
    drops : dict of str to int
        Per camera: frame sets emitted without its frame while it was alive.
    late : dict of str to int
        Per camera: frames that arrived after their frame set had left (discarded).
    dead : tuple of str
        Cameras currently considered dead.
    max_skew : float
        Largest frame-set skew seen, seconds.
    """

    framesets: int
    complete: int
    drops: dict[str, int]
    late: dict[str, int]
    dead: tuple[str, ...]
    max_skew: float


@dataclass
class _Slot:
    frames: dict[int, Frame] = field(default_factory=dict)
    seqs: dict[str, int] = field(default_factory=dict)
    t_sum: float = 0.0

    @property
    def t(self) -> float:
        return self.t_sum / len(self.frames)

    def add(self, index: int, frame: Frame) -> None:
        self.frames[index] = frame
        self.seqs[frame.sync_domain] = frame.seq
        self.t_sum += frame.t_capture


class Synchronizer:
    """Frames in, frame sets out (see the module docstring).

    Parameters
    ----------
    source_ids : sequence of str
        The cameras, in the order frame sets list them.
    period_s : float
        Nominal frame period.
    tolerance_s : float, optional
        Largest time difference of frames grouped across domains; default and maximum ``period_s / 2``.
    max_wait_s : float, optional
        How long (in frame time) a frame set waits for lagging cameras; default ``max(3 periods, 50 ms)``.
    dead_after_s : float, optional
        Silence after which a camera is reported dead; default ``max(10 periods, 0.25 s)``.
    """

    def __init__(self, source_ids, period_s: float, tolerance_s: float | None = None,
                 max_wait_s: float | None = None, dead_after_s: float | None = None):
        self.source_ids = tuple(source_ids)
        if len(set(self.source_ids)) != len(self.source_ids):
            raise ValueError(f"camera names repeat: {self.source_ids}")
        if not period_s > 0:
            raise ValueError(f"period_s must be positive, got {period_s}")
        self.period_s = float(period_s)
        half = 0.5 * self.period_s
        self.tolerance_s = half if tolerance_s is None else float(tolerance_s)
        if not 0 < self.tolerance_s <= half + 1e-12:
            raise ValueError(f"tolerance_s must be in (0, period/2 = {half:.6f}], got {tolerance_s}")
        self.max_wait_s = max(3 * self.period_s, 0.05) if max_wait_s is None else float(max_wait_s)
        self.dead_after_s = max(10 * self.period_s, 0.25) if dead_after_s is None else float(dead_after_s)
        self._index = {name: k for k, name in enumerate(self.source_ids)}
        self._slots: list[_Slot] = []  # open frame sets, sorted by time
        self._last_t = [-math.inf] * len(self.source_ids)  # newest t_capture per camera
        self._emitted_seq: dict[str, int] = {}  # per domain: highest seq emitted
        self._emitted_t = -math.inf
        self._now = -math.inf
        self._first_t: float | None = None
        self._dead = [False] * len(self.source_ids)
        self._count = 0
        self._complete = 0
        self._drops = [0] * len(self.source_ids)
        self._late = [0] * len(self.source_ids)
        self._max_skew = 0.0
        self.events: deque[str] = deque(maxlen=100)

    # ------------------------------------------------------------------------------------ API
    def push(self, frame: Frame) -> list[FrameSet]:
        """Add one frame; returns the frame sets that became ready (oldest first)."""
        index = self._index.get(frame.source_id)
        if index is None:
            raise ValueError(f"frame from unknown camera {frame.source_id!r}; cameras: {self.source_ids}")
        t = frame.t_capture
        if self._first_t is None:
            self._first_t = t
        if self._dead[index]:
            self._dead[index] = False
            self.events.append(f"{frame.source_id}: delivering again")
        self._now = max(self._now, t)
        if t <= self._last_t[index]:
            self._late[index] += 1  # not after its own previous frame: out of order, discard
            return self._ready()
        self._last_t[index] = t
        domain = frame.sync_domain
        emitted_seq = self._emitted_seq.get(domain)
        if emitted_seq is not None and (frame.seq <= emitted_seq or t <= self._emitted_t) or \
                emitted_seq is None and t < self._emitted_t + self.tolerance_s * 0.999:
            # its frame set has left (by seq in its domain, else by time), or it is older than a set
            # that has left: frame sets leave in time order
            self._late[index] += 1
            return self._ready()
        self._place(index, frame)
        return self._ready()

    def poll(self, now: float) -> list[FrameSet]:
        """Advance time to ``now`` (host monotonic seconds) without a frame; returns frame sets that became ready."""
        self._now = max(self._now, float(now))
        return self._ready()

    def flush(self) -> list[FrameSet]:
        """Emit every open frame set (end of stream)."""
        out = []
        while self._slots:
            out.append(self._emit(self._slots.pop(0)))
        return out

    def mark_dead(self, source_id: str, reason: str = "") -> None:
        """Report a camera as gone (e.g. its source ended); frame sets stop waiting for it."""
        index = self._index[source_id]
        if not self._dead[index]:
            self._dead[index] = True
            self.events.append(f"{source_id}: dead" + (f" ({reason})" if reason else ""))

    @property
    def dead(self) -> tuple[str, ...]:
        return tuple(name for name, dead in zip(self.source_ids, self._dead) if dead)

    @property
    def stats(self) -> SyncStats:
        return SyncStats(self._count, self._complete, dict(zip(self.source_ids, self._drops)),
                         dict(zip(self.source_ids, self._late)), self.dead, self._max_skew)

    # ------------------------------------------------------------------------------ internals
    def _place(self, index: int, frame: Frame) -> None:
        domain, t = frame.sync_domain, frame.t_capture
        best, best_gap = None, math.inf
        for slot in self._slots:
            seq = slot.seqs.get(domain)
            if seq == frame.seq:
                if index in slot.frames:
                    self._late[index] += 1  # duplicate seq from one camera
                    return
                slot.add(index, frame)
                return
            if seq is not None or index in slot.frames:
                continue
            gap = abs(slot.t - t)
            if gap <= self.tolerance_s and gap < best_gap:
                best, best_gap = slot, gap
        if best is None:
            best = _Slot()
            position = len(self._slots)
            while position > 0 and self._slots[position - 1].t > t:
                position -= 1
            self._slots.insert(position, best)
        best.add(index, frame)

    def _check_dead(self) -> None:
        for k, last in enumerate(self._last_t):
            if self._dead[k]:
                continue
            since = last if last > -math.inf else self._first_t
            if since is not None and self._now - since > self.dead_after_s:
                self._dead[k] = True
                self.events.append(f"{self.source_ids[k]}: no frame for {self._now - since:.3f} s, marked dead")

    def _decided(self, slot: _Slot) -> bool:
        if self._now - slot.t > self.max_wait_s:
            return True
        for k in range(len(self.source_ids)):
            if k in slot.frames or self._dead[k]:
                continue
            if self._last_t[k] <= slot.t + self.tolerance_s:
                return False
        return True

    def _ready(self) -> list[FrameSet]:
        self._check_dead()
        out = []
        while self._slots and self._decided(self._slots[0]):
            out.append(self._emit(self._slots.pop(0)))
        return out

    def _emit(self, slot: _Slot) -> FrameSet:
        frames = [slot.frames.get(k) for k in range(len(self.source_ids))]
        for k, frame in enumerate(frames):
            if frame is None and not self._dead[k]:
                self._drops[k] += 1
        for domain, seq in slot.seqs.items():
            self._emitted_seq[domain] = max(seq, self._emitted_seq.get(domain, -math.inf))
        frameset = FrameSet.from_frames(frames, self.source_ids, index=self._count)
        self._emitted_t = max(self._emitted_t, frameset.t)
        self._count += 1
        self._complete += frameset.complete
        self._max_skew = max(self._max_skew, frameset.skew)
        return frameset


class SyncedCapture:
    """Live sources on reader threads, synchronised into frame sets.

    ``read(timeout)`` returns the next ready frame set, or None. Live (``realtime``), the queue is bounded
    and keeps the newest (older ready frame sets are dropped and counted in ``dropped_framesets``);
    unpaced, the reader threads wait for room instead, so every frame set is handed out. A source that
    ends (unplugged) is marked dead and reported in ``events``; the others keep going. A source that fails
    (it ends with an ``error``, or its ``read`` raises) is also kept in :attr:`faults`, with why: an
    exception never ends a reader thread with a traceback.

    Parameters
    ----------
    sources : list of CameraSource
    period_s : float
    queue_size : int
    realtime : bool
        True (live cameras): besides the frames' own times, a ticker advances the synchroniser with the host
        clock, so frame sets leave and silent cameras are reported even when no frame arrives. The host
        clock is taken minus the recent delivery delay of the frames (arrival minus ``t_capture``, the
        largest of the last second, at most ``MAX_DELIVERY_DELAY_S``), so a uniformly slow host -- frames that
        arrive late but together -- does not make every camera look dead. False (unpaced sources:
        simulators or replays run as fast as possible): time follows the frames only, no ticker, no frame
        set is dropped (the sources wait for the consumer), and the sources are read in step, in frame-time
        order: a camera reads its next frame only when no live camera is behind it in frame time, as if
        one clock triggered them all (a camera with gaps in its recording waits for the others).
    in_flight : int, optional
        Unpaced only: the sources also wait for the consumer, which reports each frame set it finished
        with :meth:`done`. A camera reads its next frame only while fewer than ``in_flight`` frame sets up
        to its last frame are unfinished: 1, a frame set is read once the previous one is done (no frame
        set waits behind another: its latency is its processing time); 2, the next set is read while the
        previous one is processed. None (default): the sources run as far ahead as the queue allows.
    stall_s : float
        With ``in_flight``: if the consumer reports nothing for this long (a frame set lost on its way),
        the sources go on regardless, so nothing deadlocks.
    clock : callable
        Monotonic seconds, the host clock of ``realtime`` capture and of the ``stall_s`` timeout (tests pass
        one they drive).
    **sync_options
        Passed to :class:`Synchronizer`.
    """

    def __init__(self, sources, period_s: float, queue_size: int = 2, realtime: bool = True,
                 in_flight: int | None = None, stall_s: float = 0.5, clock: Callable[[], float] = time.monotonic,
                 **sync_options):
        self.clock = clock
        self.sources = list(sources)
        self.realtime = bool(realtime)
        if in_flight is not None and (self.realtime or int(in_flight) < 1):
            raise ValueError(f"in_flight is for unpaced capture, at least 1; got {in_flight} (realtime={realtime})")
        self.in_flight = None if in_flight is None else int(in_flight)
        self.stall_s = float(stall_s)
        self.sync = Synchronizer([s.source_id for s in self.sources], period_s, **sync_options)
        self._lock = threading.Lock()
        # held from taking ready frame sets out of the synchroniser until they are queued, so the frame sets
        # of two threads (a reader's push, another's camera ending) never overtake each other
        self._handing_out = threading.Lock()
        self._queue: NewestQueue[FrameSet] = NewestQueue(queue_size)
        self._threads: list[threading.Thread] = []
        self._running = threading.Event()
        self._delays: deque[tuple[float, float]] = deque(maxlen=1024)  # (arrival, arrival - t_capture)
        self._first_arrival: float | None = None
        self._step = threading.Condition()  # unpaced: readers in frame-time order (see _may_read)
        self._read_t = [-math.inf] * len(self.sources)
        self._live = [True] * len(self.sources)
        self._done_t = -math.inf  # unpaced with in_flight: time of the newest frame set the consumer finished
        self._done_at = self.clock()
        self._faults: dict[str, str] = {}

    @property
    def faults(self) -> dict[str, str]:
        """The cameras that failed (ended with an error, or their ``read`` raised): name -> why."""
        with self._lock:
            return dict(self._faults)

    @property
    def ended(self) -> bool:
        """Every source has ended or failed (none is read any more)."""
        with self._step:
            return not any(self._live)

    @property
    def gone(self) -> tuple[str, ...]:
        """The sources that ended or failed (not those stopped by :meth:`stop`)."""
        with self._step:
            return tuple(s.source_id for s, live in zip(self.sources, self._live) if not live)

    @property
    def events(self) -> list[str]:
        with self._lock:
            return list(self.sync.events)

    @property
    def delivery_delay(self) -> float:
        """Recent largest delay from mid-exposure to a frame reaching the synchroniser, seconds (0 unknown)."""
        with self._lock:
            return self._delivery_delay(self.clock())

    def start(self) -> None:
        self._running.set()
        for source in self.sources:
            source.start()
        for source in self.sources:
            thread = threading.Thread(target=self._reader, args=(source,), name=f"read {source.source_id}",
                                      daemon=True)
            thread.start()
            self._threads.append(thread)
        if self.realtime:
            ticker = threading.Thread(target=self._ticker, name="sync ticker", daemon=True)
            ticker.start()
            self._threads.append(ticker)

    def stop(self) -> None:
        self._running.clear()
        with self._step:
            self._step.notify_all()
        for source in self.sources:
            source.stop()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads.clear()

    def __enter__(self) -> SyncedCapture:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def read(self, timeout: float | None = None) -> FrameSet | None:
        return self._queue.get(timeout)

    @property
    def dropped_framesets(self) -> int:
        """Ready frame sets dropped because the consumer had not taken the older ones (live only)."""
        return self._queue.dropped

    def done(self, t: float) -> None:
        """The consumer finished (or gave up on) the frame set of time ``t`` (see ``in_flight``)."""
        with self._step:
            self._done_t = max(self._done_t, float(t))
            self._done_at = self.clock()
            self._step.notify_all()

    def _offer(self, framesets: list[FrameSet]) -> None:
        for frameset in framesets:
            if self.realtime:
                self._queue.put(frameset)
            else:  # unpaced sources can wait: hand out every frame set
                self._queue.put_waiting(frameset, self._running.is_set)

    def _delivery_delay(self, now: float) -> float:
        """Largest delivery delay of the frames that arrived in the last second (call with the lock held)."""
        while self._delays and now - self._delays[0][0] > 1.0:
            self._delays.popleft()
        if not self._delays:
            return 0.0
        return min(max(0.0, max(delay for _, delay in self._delays)), MAX_DELIVERY_DELAY_S)

    def _host_poll(self) -> list[FrameSet]:
        """Advance the synchroniser to host time (minus the delivery delay); frame time only when unpaced."""
        if not self.realtime or self._first_arrival is None:  # host time means nothing before the first frame
            return self.sync.poll(-math.inf)
        now = self.clock()
        return self.sync.poll(now - self._delivery_delay(now))

    def _may_read(self, k: int) -> bool:
        """Unpaced: camera ``k`` may read its next frame when no live camera is behind it in frame time and,
        with ``in_flight``, when the consumer is far enough along (call with ``_step`` held)."""
        tolerance = self.sync.tolerance_s
        behind = min((t for t, live in zip(self._read_t, self._live) if live), default=math.inf)
        if self._read_t[k] > behind + tolerance:
            return False
        if self.in_flight is None:
            return True
        ahead = (self.in_flight - 1) * self.sync.period_s + tolerance
        if self._read_t[k] <= self._done_t + ahead:
            return True
        if self.clock() - self._done_at > self.stall_s:  # nothing came back: do not deadlock
            self._done_t, self._done_at = self._read_t[k] - ahead, self.clock()
            return True
        return False

    def _reader(self, source) -> None:
        k = self.sources.index(source)
        stepped = not self.realtime
        while self._running.is_set():
            if stepped:  # unpaced: merge the streams in frame-time order (and wait for the consumer)
                with self._step:
                    if not self._step.wait_for(lambda: not self._running.is_set() or self._may_read(k), 0.05):
                        continue
            try:
                frame = source.read(timeout=0.1)
            except Exception as error:  # noqa: BLE001 - a failing camera is reported dead, the rest go on
                self._gone(k, f"{type(error).__name__}: {error}")
                return
            if frame is None:
                if not self._running.is_set():
                    return  # stopped by us, not gone: not reported dead
                if source.ended:
                    self._gone(k, source.error)
                    return
                continue
            if stepped:
                with self._step:
                    self._read_t[k] = frame.t_capture
                    self._step.notify_all()
            arrival = self.clock()
            with self._handing_out:
                with self._lock:
                    if self._first_arrival is None:
                        self._first_arrival = arrival
                    if self.realtime:
                        self._delays.append((arrival, arrival - frame.t_capture))
                    ready = self.sync.push(frame)
                self._offer(ready)

    def _gone(self, k: int, error: str | None) -> None:
        """Camera ``k`` ended (``error`` None: it finished, like a replayed take) or failed (``error`` says why):
        frame sets stop waiting for it; a failure is kept in :attr:`faults`."""
        source_id = self.sources[k].source_id
        with self._step:
            self._live[k] = False
            self._step.notify_all()
        with self._handing_out:
            with self._lock:
                if error:
                    self._faults[source_id] = error
                self.sync.mark_dead(source_id, error or "source ended")
                ready = self._host_poll()
            self._offer(ready)

    def _ticker(self) -> None:
        while self._running.is_set():
            time.sleep(self.sync.period_s / 2)
            with self._handing_out:
                with self._lock:
                    ready = self._host_poll()
                self._offer(ready)
