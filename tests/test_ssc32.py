"""Lynxmotion SSC-32U: command encoding, the simulator, and the driver on it."""

from __future__ import annotations

import time

import pytest
import serial

from livebridge.drivers import ssc32
from livebridge.servo.bus import ServoSetup, open_bus
from livebridge.simulators.ssc32_bus import SSC32Sim


def test_encoding():
    assert ssc32.move({0: 1500, 5: 1999.6}, 100) == b"#0P1500#5P2000T100\r"
    assert ssc32.query_pulses([0, 1]) == b"QP0 QP1\r"
    assert ssc32.query_moving() == b"Q\r"
    assert ssc32.decode_pulses(bytes([150, 200])) == [1500, 2000]
    with pytest.raises(ValueError):
        ssc32.move({40: 1500})


def test_simulator_group_move_timed():
    sim = SSC32Sim()
    port = serial.Serial(sim.start(), timeout=0.2)
    try:
        port.write(b"#0P1000#1P2000\r")
        port.write(b"#0P2000#1P1000T400\r")
        time.sleep(0.2)
        port.write(b"Q\rQP0 QP1\r")
        reply = port.read(3)
        assert reply[:1] == b"+" and 140 <= reply[1] <= 160 and 140 <= reply[2] <= 160  # both halfway
        time.sleep(0.3)
        port.write(b"Q\rQP0\r")
        assert port.read(2) == b"." + bytes([200])
        port.write(ssc32.version())
        assert port.read_until(b"\r").startswith(b"SSC32")
    finally:
        port.close()
        sim.close()


def test_driver_on_simulator():
    bus = open_bus("simssc32://")
    try:
        sim = bus.simulator
        bus.configure([ServoSetup(c, 1000, 2000, 1500, name=f"c{c}") for c in (0, 3)], 0.02)
        bus.activate()
        bus.write({0: 1800.0, 3: 2600.0})
        time.sleep(0.05)
        assert sim.move_log[-2:] == [(0, 1800), (3, 2000)]
        assert bus.poll()[0].position == 1800
        bus.estop()
        time.sleep(0.05)
        assert sim.goal[0] == 0 and sim.goal[3] == 0
    finally:
        bus.close()
