"""The simulated DYNAMIXEL bus, driven by the vendor's own dynamixel_sdk, unchanged."""

from __future__ import annotations

import time

import pytest

from livebridge.drivers import dynamixel_protocol as dxl
from livebridge.drivers.dynamixel import sdk_port
from livebridge.simulators.dynamixel_bus import DynamixelSim, parse_ids

sdk = pytest.importorskip("dynamixel_sdk")
GOAL, PRESENT, TORQUE = 116, 132, 64
# The simulator is a thread of this process: on a loaded machine it can answer later than the SDK's 34 ms.
# Replies the test expects wait up to REPLY_MS; where no reply must come, SILENCE_MS is enough (the
# simulator handles requests in order, so a later request's reply still proves the earlier one was handled).
REPLY_MS, SILENCE_MS = 2000.0, 100.0


class _Clock:
    """A simulator clock the test advances by hand (motion then does not depend on the machine's load)."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def _open(sim):
    sim.start()
    port = sdk_port(sim.path, REPLY_MS)
    assert port.openPort() and port.setBaudRate(1_000_000)
    return port


def _silent(port, call, *args):
    """``call(port, *args)`` with the short reply timeout: for requests that must get no reply."""
    port.timeout_margin_ms = SILENCE_MS
    try:
        return call(port, *args)
    finally:
        port.timeout_margin_ms = REPLY_MS


@pytest.fixture
def bus():
    sim = DynamixelSim(ids=[1, 2, 3], model={1: "XL330-M288", 2: "XL330-M288", 3: "XM430-W350"},
                       return_delay_time=0)
    port = _open(sim)
    ph = sdk.PacketHandler(2.0)
    yield sim, port, ph
    port.closePort()
    sim.close()


def test_ping_and_broadcast_ping(bus):
    sim, port, ph = bus
    assert ph.ping(port, 1) == (1200, 0, 0)
    assert ph.ping(port, 3)[0] == 1020
    assert _silent(port, ph.ping, 9)[1] == sdk.COMM_RX_TIMEOUT
    found, result = ph.broadcastPing(port)
    assert result == 0 and sorted(found) == [1, 2, 3] and found[3][0] == 1020


def test_write_read_and_eeprom_locked_while_torque_on(bus):
    sim, port, ph = bus
    assert ph.write1ByteTxRx(port, 1, 11, 3) == (0, 0)  # operating mode, torque off: fine
    assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (0, 0)
    assert ph.write1ByteTxRx(port, 1, 11, 1) == (0, dxl.ERROR_ACCESS)
    assert ph.write2ByteTxRx(port, 1, 0, 5) == (0, dxl.ERROR_ACCESS)  # model number is read-only
    assert ph.write1ByteTxRx(port, 1, TORQUE, 2) == (0, dxl.ERROR_DATA_RANGE)
    assert ph.read2ByteTxRx(port, 1, 0) == (1200, 0, 0)
    assert ph.read1ByteTxRx(port, 3, 31)[0] == 80  # XM430 temperature limit


def test_goal_outside_position_limits_is_refused(bus):
    sim, port, ph = bus
    ph.write4ByteTxRx(port, 2, 48, 3000)
    ph.write1ByteTxRx(port, 2, TORQUE, 1)
    assert ph.write4ByteTxRx(port, 2, GOAL, 3500) == (0, dxl.ERROR_DATA_LIMIT)
    assert ph.write4ByteTxRx(port, 2, GOAL, 2500) == (0, 0)


def test_motion_follows_time_based_profile():
    clock = _Clock()
    sim = DynamixelSim(ids=[1], return_delay_time=0, clock=clock)
    port = _open(sim)
    ph = sdk.PacketHandler(2.0)
    try:
        assert ph.write1ByteTxRx(port, 1, 10, dxl.DRIVE_MODE_TIME_BASED) == (0, 0)
        assert ph.write4ByteTxRx(port, 1, 112, 200) == (0, 0)  # reach the goal in 200 ms
        assert ph.write4ByteTxRx(port, 1, 108, 50) == (0, 0)  # accelerate for 50 ms
        assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (0, 0)
        start = ph.read4ByteTxRx(port, 1, PRESENT)[0]
        assert ph.write4ByteTxRx(port, 1, GOAL, start + 400) == (0, 0)
        clock.now += 0.1  # half way in time: trapezoid symmetric, so half way in distance
        middle = ph.read4ByteTxRx(port, 1, PRESENT)[0]
        assert middle == start + 200
        assert ph.read1ByteTxRx(port, 1, 122)[0] == 1  # moving
        clock.now += 0.025  # 25 ms into the cruise at 400 / (0.2 - 0.05) units/s
        assert ph.read4ByteTxRx(port, 1, PRESENT)[0] == start + 200 + round(400 / 0.15 * 0.025)
        clock.now += 0.2
        assert ph.read4ByteTxRx(port, 1, PRESENT)[0] == start + 400
        assert ph.read1ByteTxRx(port, 1, 122)[0] == 0  # not moving
    finally:
        port.closePort()
        sim.close()


def test_sync_write_sync_read_fast_sync_read(bus):
    sim, port, ph = bus
    writer = sdk.GroupSyncWrite(port, ph, GOAL, 4)
    for i in (1, 2, 3):
        ph.write1ByteTxRx(port, i, TORQUE, 1)
        writer.addParam(i, list(dxl.u32(1000 + 10 * i)))
    assert writer.txPacket() == 0
    # the XM430-W350 needs ~0.35 s for this move at no-load speed
    assert sim.wait_until(lambda: all(sim.servo(i).motion is None and sim.servo(i).get("present_position")
                                      == 1000 + 10 * i for i in (1, 2, 3)))
    reader = sdk.GroupSyncRead(port, ph, PRESENT, 4)
    for i in (1, 2, 3):
        reader.addParam(i)
    assert reader.txRxPacket() == 0
    assert [reader.getData(i, PRESENT, 4) for i in (1, 2, 3)] == [1010, 1020, 1030]
    assert reader.fastSyncRead() == 0
    assert [reader.getData(i, PRESENT, 4) for i in (1, 2, 3)] == [1010, 1020, 1030]


def test_bulk_read_and_write(bus):
    sim, port, ph = bus
    writer = sdk.GroupBulkWrite(port, ph)
    writer.addParam(1, 65, 1, [1])  # LED
    writer.addParam(2, 112, 4, list(dxl.u32(77)))  # profile velocity
    assert writer.txPacket() == 0
    reader = sdk.GroupBulkRead(port, ph)
    reader.addParam(1, 65, 1)
    reader.addParam(2, 112, 4)
    assert reader.txRxPacket() == 0
    assert reader.getData(1, 65, 1) == 1 and reader.getData(2, 112, 4) == 77


def test_reg_write_then_action(bus):
    sim, port, ph = bus
    assert ph.regWriteTxRx(port, 1, 65, 1, [1]) == (0, 0)
    assert ph.read1ByteTxRx(port, 1, 65)[0] == 0
    assert ph.read1ByteTxRx(port, 1, 69)[0] == 1  # registered instruction
    assert ph.action(port, dxl.BROADCAST_ID) == 0
    time.sleep(0.02)
    assert ph.read1ByteTxRx(port, 1, 65)[0] == 1


def test_overheating_trips_shutdown_and_alert_until_reboot(bus):
    sim, port, ph = bus
    ph.write1ByteTxRx(port, 2, TORQUE, 1)
    sim.overheat(2)
    value, result, error = ph.read1ByteTxRx(port, 2, 70)
    assert result == 0 and error & dxl.ERROR_ALERT and value & dxl.HW_OVERHEATING
    assert ph.read1ByteTxRx(port, 2, TORQUE)[0] == 0  # shutdown turned torque off
    assert ph.write1ByteTxRx(port, 2, TORQUE, 1)[1] & 0x7F == dxl.ERROR_RESULT_FAIL
    sim.servo(2).temperature = 40.0
    assert ph.reboot(port, 2) == (0, dxl.ERROR_ALERT)  # the reply still carries the alert
    assert ph.read1ByteTxRx(port, 2, 70) == (0, 0, 0)
    assert ph.write1ByteTxRx(port, 2, TORQUE, 1) == (0, 0)


def test_overload_after_one_second(bus):
    sim, port, ph = bus
    ph.write1ByteTxRx(port, 1, TORQUE, 1)
    sim.set_load(1, 1.5)
    sim.tick()
    assert ph.read1ByteTxRx(port, 1, 70)[0] == 0
    time.sleep(1.1)
    value, _, error = ph.read1ByteTxRx(port, 1, 70)
    assert value & dxl.HW_OVERLOAD and error & dxl.ERROR_ALERT


def test_status_return_level_and_factory_reset(bus):
    sim, port, ph = bus
    assert ph.write1ByteTxRx(port, 3, 68, 1) == (0, 0)  # the reply is still sent at the old level
    assert _silent(port, ph.write1ByteTxRx, 3, 65, 1)[0] == sdk.COMM_RX_TIMEOUT  # writes now get no status
    assert ph.read1ByteTxRx(port, 3, 65)[:2] == (1, 0)  # reads still answer
    ph.write1ByteTxOnly(port, 3, 68, 2)
    ph.write1ByteTxRx(port, 3, 7, 9)  # change ID
    assert ph.ping(port, 9)[1] == 0
    assert ph.factoryReset(port, 9, 0x01) == (0, 0)  # keep the ID
    time.sleep(0.02)
    assert ph.read1ByteTxRx(port, 9, 65)[0] == 0


def test_bus_watchdog_stops_servo_and_refuses_goals(bus):
    sim, port, ph = bus
    ph.write1ByteTxRx(port, 1, TORQUE, 1)
    ph.write1ByteTxRx(port, 1, 98, 3)  # 60 ms
    time.sleep(0.15)
    assert ph.read1ByteTxRx(port, 1, 98)[0] == 255
    assert ph.write4ByteTxRx(port, 1, GOAL, 2100) == (0, dxl.ERROR_DATA_RANGE)
    ph.write1ByteTxRx(port, 1, 98, 0)
    assert ph.write4ByteTxRx(port, 1, GOAL, 2100) == (0, 0)


def test_fault_injection_disconnect_and_dropped_replies(bus):
    sim, port, ph = bus
    # The simulator applies its fault settings when it handles a request, on its own thread: before changing
    # them, wait until it has handled every request sent so far (its packet count), never a fixed time.
    packets = sim.stats["packets"]
    sim.disconnect(2)
    assert _silent(port, ph.ping, 2)[1] == sdk.COMM_RX_TIMEOUT
    reader = sdk.GroupSyncRead(port, ph, PRESENT, 4)
    for i in (1, 2, 3):
        reader.addParam(i)
    port.timeout_margin_ms = SILENCE_MS  # the header claims 3 servos' data; only servo 1's ever comes
    assert reader.fastSyncRead() != 0  # the chain of fast replies breaks at the missing servo
    port.timeout_margin_ms = REPLY_MS
    assert sim.wait_until(lambda: sim.stats["packets"] == packets + 2)
    sim.reconnect(2)
    sim.drop_rate = 1.0
    assert _silent(port, ph.ping, 1)[1] == sdk.COMM_RX_TIMEOUT
    assert sim.wait_until(lambda: sim.stats["packets"] == packets + 3)
    assert sim.stats["dropped_out"] == 1 and sim.stats["corrupted_out"] == 0
    sim.drop_rate, sim.corrupt_rate = 0.0, 1.0
    assert ph.ping(port, 1)[1] == sdk.COMM_RX_CORRUPT  # the reply came, with a bit flipped
    assert sim.stats["corrupted_out"] == 1 and sim.stats["dropped_out"] == 1


def test_corrupt_instruction_gets_crc_error_status(bus):
    sim, port, ph = bus
    packet = bytearray(dxl.read(1, 0, 2))
    packet[-1] ^= 0xFF
    import os

    port.ser.write(bytes(packet))
    deadline = time.monotonic() + 1
    got = []
    reader = dxl.PacketReader()
    while not got and time.monotonic() < deadline:
        got = reader.feed(port.ser.read(64))
    assert got and got[0].error == dxl.ERROR_CRC
    assert os.path.exists(sim.path)


def test_parse_ids():
    assert parse_ids("1-3,7") == [1, 2, 3, 7]
    with pytest.raises(ValueError):
        parse_ids("1-3,2")
