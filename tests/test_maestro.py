"""Pololu Maestro: the simulator, and the driver on it (golden bytes: test_maestro_protocol.py)."""

from __future__ import annotations

import pytest
import serial

from livebridge.devices.registry import open_bus
from livebridge.drivers import maestro_protocol as mp
from livebridge.drivers.maestro_protocol import PROTOCOL_ERROR
from livebridge.servo.bus import ServoSetup
from livebridge.simulators.maestro_bus import MaestroSim


class _Clock:
    """A simulator clock the test advances by hand: motion does not depend on the machine's load."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture
def maestro():
    sim = MaestroSim(channels=6, device=12, clock=_Clock())
    port = serial.Serial(sim.start(), timeout=2.0)  # replies come at once, unless the machine is loaded
    yield sim, port
    port.close()
    sim.close()


def test_simulator_both_protocols(maestro):
    sim, port = maestro
    port.write(mp.set_target(0, 6000) + mp.set_target(1, 7000, device=12) + mp.set_target(2, 5000, device=7))
    port.write(mp.get_position(0) + mp.get_position(1, device=12) + mp.get_position(2))
    assert port.read(6) == bytes([0x70, 0x17, 0x58, 0x1B, 0, 0])  # device 7 is someone else
    port.write(bytes([0x84, 0x00, 0x90]))  # data byte with the high bit set: protocol error
    port.write(mp.get_errors())
    assert mp.decode_u16(port.read(2)) & PROTOCOL_ERROR
    port.write(mp.get_errors())
    assert mp.decode_u16(port.read(2)) == 0  # reading clears


def test_speed_limit_moves_gradually(maestro):
    sim, port = maestro
    port.write(mp.set_target(3, 4000))
    assert sim.wait_until(lambda: sim.position[3] == 4000)  # no pulses before: the first target is immediate
    port.write(mp.set_speed(3, 20) + mp.set_target(3, 8000))  # 20 * 0.25 µs / 10 ms = 500 µs/s
    assert sim.wait_until(lambda: sim.target[3] == 8000)
    sim.clock.now += 0.2
    port.write(mp.get_position(3))
    middle = mp.decode_u16(port.read(2)) / 4
    assert middle == 1000 + 500 * 0.2
    port.write(mp.get_moving_state())
    assert port.read(1) == b"\x01"


def test_driver_on_simulator():
    bus = open_bus("simmaestro://?channels=8&device=12", timeout=0.15)  # scan waits this long for each of 16
    try:
        sim = bus.companion
        assert [i.address for i in bus.scan()] == list(range(8))
        bus.serial.timeout = 2.0  # from now on every query is answered: wait generously (a loaded machine)
        bus.configure([ServoSetup(c, 1000, 2000, 1500, name=f"c{c}") for c in (0, 1, 2, 5)], 0.02)
        assert all(v != v for v in bus.activate().values())  # no pulses yet: position unknown (NaN)
        logged = len(sim.target_log)
        bus.write({0: 1200.0, 1: 900.0, 2: float("inf"), 5: 2500.0})
        assert sim.wait_until(lambda: len(sim.target_log) >= logged + 3)  # no reply to targets: wait for them
        assert sim.target[0] == 4800 and sim.target[1] == 4000 and sim.target[2] == 0 and sim.target[5] == 8000
        status = bus.poll()
        assert status[0].position == 1200
        bus.estop()
        assert sim.wait_until(lambda: sim.target[:6] == [0] * 6)
    finally:
        bus.close()


def test_limits_off_the_quarter_microsecond_grid_are_kept_after_rounding():
    """A limit of 64.625 us rounds to 258.5 quarters: the wire gets 259 (64.75 us), never 258 (64.5, past it)."""
    bus = open_bus("simmaestro://?channels=2")
    try:
        sim = bus.companion
        bus.serial.timeout = 2.0
        bus.configure([ServoSetup(c, 64.625, 2000.375, 1500, name=f"c{c}") for c in (0, 1)], 0.02)
        bus.activate()
        logged = len(sim.target_log)
        bus.write({0: 64.625, 1: 2000.375})
        assert sim.wait_until(lambda: len(sim.target_log) >= logged + 2)
        assert sim.target_log[logged:logged + 2] == [(0, 259), (1, 8001)]  # what went over the wire
    finally:
        bus.close()
