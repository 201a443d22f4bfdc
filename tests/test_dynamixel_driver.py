"""Our DYNAMIXEL driver (on dynamixel_sdk) against the simulated bus, faults included."""

from __future__ import annotations

import time

import numpy as np
import pytest

from livebridge.devices.registry import open_bus
from livebridge.drivers import dynamixel_protocol as dxl
from livebridge.errors import InputError
from livebridge.servo.bus import ServoBus, ServoSetup

pytest.importorskip("dynamixel_sdk")


# The simulator is a thread of this process: on a loaded machine it can be descheduled for longer than the
# SDK's 34 ms. A reply that comes after the driver stopped waiting is then taken as the reply to the next
# request, so the tests give replies a generous timeout (ms beyond the wire time); it only costs time where a
# reply never comes (a missing servo).
REPLY_MS = 1000.0


def _setups(ids, low=1500, high=2600):
    return [ServoSetup(i, low, high, 2048, "XL330-M288", f"s{i}") for i in ids]


@pytest.fixture
def bus():
    bus = open_bus("simdynamixel://?ids=1-4&model=XL330-M288&delay=0", timeout_margin_ms=REPLY_MS)
    yield bus
    bus.close()


def test_scan_configure_activate(bus):
    assert isinstance(bus, ServoBus)
    infos = bus.scan()
    assert [i.address for i in infos] == [1, 2, 3, 4] and infos[0].model == "XL330-M288"
    bus.configure(_setups([1, 2, 3, 4]), frame_period=0.025)
    servo = bus.companion.servo(1)
    assert servo.get("drive_mode") & dxl.DRIVE_MODE_TIME_BASED
    assert servo.get("profile_velocity") == 25 and servo.get("operating_mode") == 3
    assert (servo.get("min_position_limit"), servo.get("max_position_limit")) == (1500, 2600)
    positions = bus.activate()
    assert positions == {i: 2048.0 for i in (1, 2, 3, 4)}
    assert servo.torque_on and servo.get("goal_position") == 2048


def test_model_check_and_missing_servo_name_the_servo(bus):
    with pytest.raises(InputError, match="XM430-W350"):
        bus.configure([ServoSetup(1, 1500, 2600, 2048, "XM430-W350", "jaw")], 0.02)
    bus.port.timeout_margin_ms = 200.0  # id 9 never answers: no need to wait long for it
    with pytest.raises(InputError, match=r"brow \(id 9\)"):
        bus.configure([ServoSetup(9, 1500, 2600, 2048, None, "brow")], 0.02)


def test_write_is_one_sync_write_and_clamps(bus):
    bus.configure(_setups([1, 2, 3, 4]), 0.02)
    bus.activate()
    sim = bus.companion
    sim.log_goals = True
    before = sim.stats["packets"]
    bus.write({1: 1000.0, 2: 2300.0, 3: float("nan"), 4: 9999.0})
    assert sim.wait_until(lambda: sim.stats["packets"] >= before + 1)  # the write needs no reply: wait for it
    time.sleep(0.05)  # nothing else arrives
    assert sim.stats["packets"] == before + 1
    goals = {i: g for _, i, g in sim.goal_log}
    assert goals == {1: 1500, 2: 2300, 4: 2600}  # NaN skipped, others clamped to the servo's limits
    assert sim.wait_until(lambda: sim.servo(2).motion is None)
    status = bus.poll()
    assert status[2].position == 2300 and status[2].temperature == 30.0 and status[2].fault is None


def test_fast_sync_read_used_when_firmware_has_it(bus):
    bus.configure(_setups([1, 2]), 0.02)
    assert bus._use_fast
    bus.activate()
    got = bus.sync_read(132, 4, [1, 2])
    assert {i: dxl.to_int(d) for i, (d, _) in got.items()} == {1: 2048, 2: 2048}
    assert bus.stats["fast_failures"] == 0


def test_estop_turns_torque_off(bus):
    bus.configure(_setups([1, 2, 3, 4]), 0.02)
    bus.activate()
    sim = bus.companion
    assert all(s.torque_on for s in sim.servos.values())
    bus.estop()
    assert sim.wait_until(lambda: not any(s.torque_on for s in sim.servos.values()))


def test_corrupted_replies_and_overheating_servo_mid_run():
    """5% corrupted replies, servo 3 overheats mid-run: the others keep moving, the fault is reported,
    recovery works once it cooled, and no goal outside the limits ever reaches the bus."""
    low, high = 1700, 2400
    bus = open_bus("simdynamixel://?ids=1-6&model=XL330-M288&delay=0&corrupt=0.05&seed=3",
                   timeout_margin_ms=REPLY_MS)
    try:
        sim = bus.companion
        bus.configure(_setups(range(1, 7), low, high), 0.02)
        bus.activate()
        sim.log_goals = True
        rng = np.random.default_rng(0)
        reached = []
        for k in range(60):
            wanted = 2050 + 600 * np.sin(k / 6) + rng.normal(0, 300)  # often beyond the limits
            bus.write({i: float(wanted) for i in range(1, 7)})
            bus.poll()
            if k == 20:
                sim.overheat(3)
            if k >= 40:
                reached.append({i: sim.servo(i).position for i in range(1, 7)})
            time.sleep(0.005)
        assert sim.stats["corrupted_out"] > 0
        assert "overheating" in bus.faults.get(3, "")
        assert set(bus.faults) == {3}
        assert any(event[1] == 3 and "overheating" in event[2] for event in bus.events)
        assert not sim.servo(3).torque_on
        # the others kept following: they moved during the last 20 frames; servo 3 did not
        spread = {i: np.ptp([r[i] for r in reached]) for i in range(1, 7)}
        assert all(spread[i] > 50 for i in (1, 2, 4, 5, 6)) and spread[3] == 0
        goals = np.array([g for _, _, g in sim.goal_log])
        assert len(goals) > 0 and goals.min() >= low and goals.max() <= high
        # after cooling down, a reboot brings it back
        sim.servo(3).temperature = 35.0
        for _ in range(3):
            if bus.recover(3):
                break
        assert 3 not in bus.faults and sim.servo(3).torque_on
    finally:
        bus.close()


def test_disappearing_servo_is_reported_and_others_continue():
    # each poll waits the whole timeout for the missing servo (twice: FAST SYNC READ, then SYNC READ)
    bus = open_bus("simdynamixel://?ids=1-3&model=XL330-M288&delay=0", timeout_margin_ms=250.0, missing_after=3)
    try:
        sim = bus.companion
        bus.configure(_setups([1, 2, 3]), 0.02)
        bus.activate()
        sim.disconnect(2)
        for k in range(5):
            bus.write({1: 2000.0 + 50 * k, 2: 2000.0, 3: 2000.0 + 50 * k})
            bus.poll()
        assert bus.faults == {2: "not answering"}
        assert sim.wait_until(lambda: sim.servo(1).motion is None and sim.servo(3).motion is None)
        status = bus.poll()
        assert status[1].position == 2200 and status[3].position == 2200
        sim.reconnect(2)
        bus.poll()
        assert "reappeared" in bus.faults[2]
    finally:
        bus.close()


def test_bad_url():
    with pytest.raises(InputError, match="cannot open"):
        open_bus("dynamixel:///dev/does-not-exist?baud=1000000")
    with pytest.raises(InputError, match="scheme"):
        open_bus("canbus:///dev/x")


def _count_reads(port) -> list[int]:
    """Record the length of every ``port.readPort`` call the SDK makes from now on."""
    calls: list[int] = []
    read = port.readPort

    def counted(length):
        calls.append(length)
        return read(length)

    port.readPort = counted
    return calls


@pytest.fixture
def slow_bus():
    # the servos' factory return delay (500 us per status packet): the SDK's own readPort spins through it
    bus = open_bus("simdynamixel://?ids=1-4&model=XL330-M288", timeout_margin_ms=REPLY_MS, fast_read=False)
    bus.configure(_setups([1, 2, 3, 4]), 0.02)
    bus.activate()
    yield bus
    bus.close()


# Each status packet takes the SDK two reads (header, rest) plus one that sleeps until bytes come; spinning
# the SDK way costs hundreds of reads per sync read here (thousands while a reply never comes).
READS_PER_PACKET = 4


def test_sync_read_waits_for_replies_without_spinning(slow_bus):
    calls = _count_reads(slow_bus.port)
    for _ in range(10):
        got = slow_bus.sync_read(132, 4, [1, 2, 3, 4])
        assert {i: dxl.to_int(d) for i, (d, _) in got.items()} == {i: 2048 for i in (1, 2, 3, 4)}
    assert len(calls) <= 10 * 4 * READS_PER_PACKET


def test_reply_timeout_is_slept_through_not_spun(slow_bus):
    slow_bus.port.timeout_margin_ms = 100.0  # id 2 never answers: every sync read waits out the timeout
    slow_bus.companion.disconnect(2)
    calls = _count_reads(slow_bus.port)
    for _ in range(3):
        assert set(slow_bus.sync_read(132, 4, [1, 2, 3])) == {1, 3}
    assert len(calls) <= 3 * 3 * READS_PER_PACKET


class _NoFileno:
    """A pyserial port seen without a file descriptor (as on Windows): reads fall back to the SDK's loop."""

    def __init__(self, ser):
        self._ser = ser

    def __getattr__(self, name):
        if name == "fileno":
            raise AttributeError(name)
        return getattr(self._ser, name)


def test_port_without_fileno_reads_as_the_sdk(slow_bus):
    ser = slow_bus.port.ser
    slow_bus.port.ser = _NoFileno(ser)
    try:
        got = slow_bus.sync_read(132, 4, [1, 2, 3, 4])
    finally:
        slow_bus.port.ser = ser
    assert {i: dxl.to_int(d) for i, (d, _) in got.items()} == {i: 2048 for i in (1, 2, 3, 4)}


def test_simulated_bus_in_its_own_process():
    """``process=1``: the simulator runs in a child process (as hardware, it takes no GIL from the driver's
    process); the real driver scans, configures and moves its servos over the pseudo-terminal, and closing
    the bus ends the child."""
    import threading

    bus = open_bus("simdynamixel://?ids=1-3&model=XL330-M288&delay=0&process=1", timeout_margin_ms=REPLY_MS)
    try:
        process = bus.companion._process
        assert process.poll() is None and not any(t.name.startswith("pty-bus") for t in threading.enumerate())
        assert [i.address for i in bus.scan()] == [1, 2, 3]
        bus.configure(_setups([1, 2, 3]), frame_period=0.02)
        assert bus.activate() == {i: 2048.0 for i in (1, 2, 3)}
        bus.write({1: 2300, 2: 1800, 3: 2048})
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            bus.poll()
            if abs(bus.status[1].position - 2300) < 2 and abs(bus.status[2].position - 1800) < 2:
                break
            time.sleep(0.02)
        assert abs(bus.status[1].position - 2300) < 2 and abs(bus.status[2].position - 1800) < 2
    finally:
        bus.close()
    assert process.poll() is not None


def test_bad_simulator_options_are_reported_before_a_process_starts():
    with pytest.raises(InputError, match="simdynamixel"):
        open_bus("simdynamixel://?ids=1-3&model=NOPE-1&process=1")
