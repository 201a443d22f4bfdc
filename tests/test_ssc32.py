"""Lynxmotion SSC-32U: the simulator, and the driver on it (encoding: test_ssc32_protocol.py)."""

from __future__ import annotations

import serial

from livebridge.devices.registry import open_bus
from livebridge.drivers import ssc32_protocol as ssc32
from livebridge.servo.bus import ServoSetup
from livebridge.simulators.ssc32_bus import SSC32Sim


class _Clock:
    """A simulator clock the test advances by hand: timed moves do not depend on the machine's load."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_simulator_group_move_timed():
    clock = _Clock()
    sim = SSC32Sim(clock=clock)
    port = serial.Serial(sim.start(), timeout=2.0)  # replies come at once, unless the machine is loaded
    try:
        port.write(b"#0P1000#1P2000\r")
        port.write(b"#0P2000#1P1000T400\r")
        assert sim.wait_until(lambda: sim.goal[:2] == [2000, 1000])
        clock.now += 0.2
        port.write(b"Q\rQP0 QP1\r")
        assert port.read(3) == b"+" + bytes([150, 150])  # both halfway
        clock.now += 0.2
        port.write(b"Q\rQP0\r")
        assert port.read(2) == b"." + bytes([200])
        port.write(ssc32.version())
        assert port.read_until(b"\r").startswith(b"SSC32")
    finally:
        port.close()
        sim.close()


def test_driver_on_simulator():
    bus = open_bus("simssc32://", timeout=2.0)  # reply timeout: generous, the simulator may be descheduled
    try:
        sim = bus.companion
        bus.configure([ServoSetup(c, 1000, 2000, 1500, name=f"c{c}") for c in (0, 3)], 0.02)
        bus.activate()
        logged = len(sim.move_log)
        bus.write({0: 1800.0, 3: 2600.0})
        assert sim.wait_until(lambda: len(sim.move_log) >= logged + 2)  # the move gets no reply: wait for it
        assert sim.move_log[logged:] == [(0, 1800), (3, 2000)]
        assert sim.wait_until(lambda: not sim.moving(sim.clock()))
        assert bus.poll()[0].position == 1800
        bus.estop()
        assert sim.wait_until(lambda: sim.goal[0] == 0 and sim.goal[3] == 0)
    finally:
        bus.close()
