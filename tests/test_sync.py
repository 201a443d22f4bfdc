"""The frame synchroniser: property tests with random jitter, drops, delivery delays and a dead camera."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from livebridge.capture.frame import Frame
from livebridge.capture.sync import SyncedCapture, Synchronizer

IMAGE = np.zeros((2, 2), np.uint8)


def _stream(seed, n_cams, n_frames, fps, domains, jitter, drop_p, dead_cam, dead_at, max_delay):
    """Frames of a simulated rig in arrival order, with the true instant of every frame.

    ``domains``: "hardware" (one domain, shared seq), "free" (own domain and counter each) or "mixed".
    Returns (frames in arrival order, {id(frame): instant}, dropped (n_cams, n_frames) bool).
    """
    rng = np.random.default_rng(seed)
    period = 1.0 / fps
    names = [f"c{k}" for k in range(n_cams)]
    if domains == "hardware":
        domain_of, seq_offset = ["hw"] * n_cams, np.zeros(n_cams, int)
    elif domains == "free":
        domain_of, seq_offset = names, rng.integers(0, 1000, n_cams)
    else:
        domain_of = ["A" if k % 2 == 0 else "B" for k in range(n_cams)]
        seq_offset = np.array([0 if k % 2 == 0 else 77 for k in range(n_cams)])
    offset = rng.uniform(-0.05, 0.05, n_cams) * period
    dropped = rng.random((n_cams, n_frames)) < drop_p
    instant_of, arrivals = {}, []
    for c in range(n_cams):
        arrival = -np.inf
        for k in range(n_frames):
            if dead_cam == c and k >= dead_at:
                break
            if dropped[c, k]:
                continue
            t = 10.0 + k * period + offset[c] + rng.uniform(-1, 1) * jitter * period
            frame = Frame(IMAGE, t, k + seq_offset[c], names[c], sync_domain=domain_of[c])
            instant_of[id(frame)] = k
            arrival = max(arrival, t + rng.uniform(0, max_delay) * period)  # in order per camera
            arrivals.append((arrival, c, frame))
    arrivals.sort(key=lambda a: (a[0], a[1]))
    return names, [a[2] for a in arrivals], instant_of, dropped, period


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), n_cams=st.integers(2, 5), n_frames=st.integers(5, 80),
       fps=st.sampled_from([30.0, 60.0, 90.0, 120.0]), domains=st.sampled_from(["hardware", "free", "mixed"]),
       jitter=st.floats(0.0, 0.15), drop_p=st.floats(0.0, 0.3), kill=st.booleans(),
       dead_frac=st.floats(0.0, 0.5), max_delay=st.floats(0.0, 1.5))
def test_synchroniser_properties(seed, n_cams, n_frames, fps, domains, jitter, drop_p, kill, dead_frac, max_delay):
    dead_cam = 0 if kill else None
    dead_at = int(dead_frac * n_frames)
    names, frames, instant_of, dropped, period = _stream(seed, n_cams, n_frames, fps, domains, jitter, drop_p,
                                                         dead_cam, dead_at, max_delay)
    sync = Synchronizer(names, period)
    out = []
    for frame in frames:
        out.extend(sync.push(frame))
    out.extend(sync.flush())
    stats = sync.stats

    placed = [f for fs in out for f in fs.frames if f is not None]
    assert len({id(f) for f in placed}) == len(placed)  # no frame in two sets
    assert sum(stats.late.values()) == 0  # delays below max_wait: nothing is late
    assert len(placed) == len(frames)  # every frame placed exactly once
    instants = []
    for k, fs in enumerate(out):
        assert fs.index == k and fs.source_ids == tuple(names)
        present = {instant_of[id(f)] for f in fs.frames if f is not None}
        assert len(present) == 1  # one instant per frame set
        instants.append(present.pop())
        assert fs.skew <= sync.tolerance_s + 1e-12
        for name, f in zip(fs.source_ids, fs.frames):
            assert f is None or f.source_id == name
    assert instants == sorted(instants) and len(set(instants)) == len(instants)  # in time order, no split sets
    delivered = {instant_of[id(f)] for f in frames}
    assert set(instants) == delivered
    assert stats.framesets == len(out) and stats.complete == sum(fs.complete for fs in out)
    # drops: exactly the frames a live camera did not deliver, over the emitted sets
    for c, name in enumerate(names):
        missing = sum(1 for fs, k in zip(out, instants) if fs.frames[c] is None)
        if c != dead_cam:
            assert stats.drops[name] == sum(dropped[c, k] for k in instants) == missing
        else:
            assert stats.drops[name] <= missing
    if dead_cam is not None and (n_frames - dead_at) * period > sync.dead_after_s + sync.max_wait_s + 2 * period:
        assert names[dead_cam] in stats.dead and any("dead" in e for e in sync.events)
        # the rest keep going: every later instant still produced a frame set
        assert max(instants) >= n_frames - 2 or drop_p > 0


def test_late_and_out_of_order_frames_are_counted_and_discarded():
    sync = Synchronizer(["a", "b"], 0.01)
    out = []
    for k in range(10):
        out += sync.push(Frame(IMAGE, 1 + k * 0.01, k, "a", sync_domain="a"))
    # b's frames 0..2 arrive after a has moved 10 frames on: beyond max_wait, their sets already left
    out += sync.push(Frame(IMAGE, 1.0005, 0, "b", sync_domain="b"))
    assert sync.stats.late["b"] == 1
    out += sync.push(Frame(IMAGE, 1.0905, 9, "b", sync_domain="b"))
    out += sync.push(Frame(IMAGE, 1.0805, 8, "b", sync_domain="b"))  # out of order for b: discarded
    assert sync.stats.late["b"] == 2
    out += sync.flush()
    assert [fs.index for fs in out] == list(range(len(out)))
    assert out[-1].complete and out[-1]["b"].seq == 9


def test_tolerance_is_at_most_half_a_period():
    with pytest.raises(ValueError, match="period/2"):
        Synchronizer(["a"], 1 / 60, tolerance_s=0.6 / 60)
    with pytest.raises(ValueError, match="repeat"):
        Synchronizer(["a", "a"], 1 / 60)


def test_hardware_domain_groups_by_seq_despite_timestamps():
    sync = Synchronizer(["l", "r"], 1 / 30)
    # same seq, timestamps 0.45 periods apart but ordered oppositely: grouped by seq, not time
    out = sync.push(Frame(IMAGE, 5.0, 7, "l", sync_domain="oak")) + sync.push(
        Frame(IMAGE, 5.0 + 0.45 / 30, 7, "r", sync_domain="oak"))
    out += sync.push(Frame(IMAGE, 5.0 + 1.0 / 30, 8, "r", sync_domain="oak"))
    out += sync.push(Frame(IMAGE, 5.0 + 0.6 / 30, 8, "l", sync_domain="oak"))
    out += sync.flush()
    assert [(fs["l"].seq, fs["r"].seq) for fs in out] == [(7, 7), (8, 8)]


def test_synced_capture_with_sim_rig_and_an_unplugged_camera(ict):
    from livebridge.simulators.rig import RigConfig, SimRig, generate_markers

    rig = SimRig(ict, generate_markers(ict, 20, 4), n_cameras=3,
                 config=RigConfig(size=(320, 200), fps=60, noise_sigma=0, drop_rate=0.05, sync="free"), seed=2)
    sources = rig.sources(realtime=True)
    sources[2].kill_after(20)
    got = []
    with SyncedCapture(sources, rig.period, queue_size=64) as capture:
        while len(got) < 60:
            fs = capture.read(timeout=1.0)
            assert fs is not None
            got.append(fs)
        events = capture.events
        stats = capture.sync.stats
    assert any("cam2" in e for e in events) and "cam2" in stats.dead
    assert all(fs["cam2"] is None for fs in got[40:])
    late_sets = got[40:]
    assert sum(fs["cam0"] is not None and fs["cam1"] is not None for fs in late_sets) >= 0.8 * len(late_sets)
    assert all(b.t > a.t for a, b in zip(got, got[1:]))
    assert max(fs.skew for fs in got) <= 0.5 * rig.period


class _DelayedCamera:
    """A paced 60 fps camera whose frames reach the host ``delay`` seconds after mid-exposure (or, unpaced,
    a camera that is simply slow: every read takes ``delay``)."""

    def __init__(self, name, delay, paced=True, period=1 / 60):
        self.source_id, self.delay, self.paced, self.period = name, delay, paced, period
        self.ended, self.error, self.k, self.t0 = False, None, 0, 0.0

    def start(self):
        import time

        self.t0 = time.monotonic() + 0.01

    def stop(self):
        self.ended = True

    def read(self, timeout=None):
        import time

        if self.ended:
            return None
        t = self.t0 + self.k * self.period
        wait = (t + self.delay - time.monotonic()) if self.paced else self.delay
        time.sleep(max(0.0, wait))
        self.k += 1
        return Frame(IMAGE, t, self.k - 1, self.source_id, sync_domain="hw")


def test_realtime_capture_tolerates_a_uniformly_slow_host():
    """Frames arriving together but 0.4 s after exposure (longer than dead_after_s) are not a dead rig."""
    cameras = [_DelayedCamera(f"c{k}", 0.4) for k in range(3)]
    got = []
    with SyncedCapture(cameras, 1 / 60, queue_size=256) as capture:
        assert capture.realtime and any(t.name == "sync ticker" for t in capture._threads)
        while len(got) < 40:
            fs = capture.read(timeout=2.0)
            assert fs is not None
            got.append(fs)
        stats = capture.sync.stats
        assert 0.35 < capture.delivery_delay < 0.6
    assert not stats.dead and stats.complete == stats.framesets, stats
    assert all(fs.complete for fs in got)


def test_unpaced_capture_follows_frame_time_only():
    """realtime=False: no ticker; sources slower than their frame period and slower
    than each other are read in step, not reported dead; a slower consumer still gets every frame set."""
    cameras = [_DelayedCamera(f"c{k}", 0.01 * (k + 1), paced=False, period=1 / 120) for k in range(3)]
    got = []
    with SyncedCapture(cameras, 1 / 120, queue_size=1, realtime=False,
                       dead_after_s=0.05) as capture:
        assert not capture.realtime and len(capture._threads) == 3  # reader threads only
        while len(got) < 15:
            fs = capture.read(timeout=2.0)
            assert fs is not None
            got.append(fs)
            time.sleep(0.06)  # slower than the sources
        stats = capture.sync.stats
        assert capture.dropped_framesets == 0
    assert not stats.dead and all(fs.complete for fs in got), stats
    assert [fs.frames[0].seq for fs in got] == list(range(15))


class _GappyCamera:
    """An unpaced camera of a recorded take: frames at ``seqs`` only (gaps where it dropped frames)."""

    def __init__(self, name, seqs, period=1 / 60):
        self.source_id, self.seqs, self.period = name, list(seqs), period
        self.ended, self.error, self.reads = False, None, 0

    def start(self):
        pass

    def stop(self):
        self.ended = True

    def read(self, timeout=None):
        if self.reads == len(self.seqs):
            self.ended = True
            return None
        seq = self.seqs[self.reads]
        self.reads += 1
        return Frame(IMAGE, seq * self.period, seq, self.source_id, sync_domain="hw")


def test_unpaced_in_flight_reads_only_as_far_as_the_consumer():
    """in_flight=1: a camera reads its next frame only once the consumer is done with the frame set of its
    last one, by frame time, so cameras with different gaps stay in step and no frame set is incomplete
    for want of waiting."""
    a = _GappyCamera("a", range(20))
    b = _GappyCamera("b", [k for k in range(20) if k not in (3, 4, 11)])
    with SyncedCapture([a, b], 1 / 60, queue_size=1, realtime=False, in_flight=1, stall_s=30.0) as capture:
        first = capture.read(timeout=2.0)
        time.sleep(0.1)
        assert first.frames[0].seq == 0 and (a.reads, b.reads) == (1, 1)  # nothing read ahead of the consumer
        got = [first]
        capture.done(first.t)
        while len(got) < 20 and (frameset := capture.read(timeout=2.0)) is not None:
            time.sleep(0.002)
            assert max(a.reads, b.reads) <= frameset.frames[0].seq + 2  # at most the next frame read ahead
            got.append(frameset)
            capture.done(frameset.t)
    assert [fs.frames[0].seq for fs in got] == list(range(20))
    assert [fs.frames[1] is None for fs in got] == [k in (3, 4, 11) for k in range(20)]


def test_unpaced_in_flight_stall_guard_never_deadlocks():
    a = _GappyCamera("a", range(5))
    with SyncedCapture([a], 1 / 60, queue_size=8, realtime=False, in_flight=1, stall_s=0.1) as capture:
        start = time.monotonic()
        got = [capture.read(timeout=2.0) for _ in range(3)]  # the consumer never reports done
        assert all(fs is not None for fs in got)
        assert 0.15 < time.monotonic() - start < 1.5  # two stalls of ~0.1 s


class _FakeClock:
    """A monotonic clock the test sets."""

    def __init__(self, now=100.0):
        self.now = now

    def __call__(self):
        return self.now


class _OneFrameCamera:
    """A live camera that delivers one frame, taken at the injected clock's time, then nothing."""

    def __init__(self, name, clock):
        self.source_id, self.clock = name, clock
        self.ended, self.error, self.delivered = False, None, False

    def start(self):
        pass

    def stop(self):
        self.ended = True

    def read(self, timeout=None):
        if self.delivered:
            time.sleep(min(timeout or 0.01, 0.01))
            return None
        self.delivered = True
        return Frame(IMAGE, self.clock(), 0, self.source_id, sync_domain="hw")


def test_realtime_capture_reads_the_host_clock_it_is_given():
    """Silent cameras are marked dead by the injected clock's time, not by the real time that passes."""
    clock = _FakeClock()
    cameras = [_OneFrameCamera(name, clock) for name in ("a", "b")]
    with SyncedCapture(cameras, 1 / 60, queue_size=4, clock=clock) as capture:
        assert capture.read(timeout=2.0).complete
        time.sleep(0.5)  # twice dead_after_s of real time, none of the clock's
        assert capture.sync.dead == ()
        clock.now += 1.0
        deadline = time.monotonic() + 2.0
        while capture.sync.dead != ("a", "b"):
            assert time.monotonic() < deadline, capture.sync.dead
            time.sleep(0.01)


def test_unpaced_in_flight_stall_guard_runs_on_the_clock_it_is_given():
    clock = _FakeClock()
    a = _GappyCamera("a", range(5))
    with SyncedCapture([a], 1 / 60, queue_size=8, realtime=False, in_flight=1, stall_s=0.1, clock=clock) as capture:
        assert capture.read(timeout=2.0) is not None  # the consumer never reports done
        assert capture.read(timeout=0.3) is None  # the clock stands still: no stall yet
        clock.now += 0.2
        assert capture.read(timeout=2.0) is not None


class _FailingCamera(_GappyCamera):
    """An unpaced camera whose ``read`` raises after ``fail_after`` frames (a driver bug, a USB error)."""

    def __init__(self, name, seqs, fail_after):
        super().__init__(name, seqs)
        self.fail_after = fail_after

    def read(self, timeout=None):
        if self.reads == self.fail_after:
            raise OSError(5, "Input/output error")
        return super().read(timeout)


def test_a_camera_whose_read_raises_is_reported_dead_and_the_rest_go_on():
    """The exception becomes the camera's fault (no reader thread dies with a traceback); frame sets go on
    without it; a camera that simply ends is no fault."""
    failures = []
    previous_hook, threading.excepthook = threading.excepthook, failures.append
    try:
        a, b = _GappyCamera("a", range(20)), _FailingCamera("b", range(20), fail_after=5)
        with SyncedCapture([a, b], 1 / 60, queue_size=1, realtime=False) as capture:
            got = []
            while (frameset := capture.read(timeout=2.0)) is not None:
                got.append(frameset)
            assert capture.ended and set(capture.gone) == {"a", "b"}
            faults = capture.faults
    finally:
        threading.excepthook = previous_hook
    assert not failures, failures
    assert faults == {"b": "OSError: [Errno 5] Input/output error"}
    assert [fs.frames[0].seq for fs in got] == list(range(20))
    assert all(fs.frames[1] is not None for fs in got[:5]) and all(fs.frames[1] is None for fs in got[6:])
    assert "b: dead (OSError: [Errno 5] Input/output error)" in capture.events
