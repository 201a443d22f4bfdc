"""Pololu Maestro serial protocol: golden bytes from the Maestro User's Guide ("Serial Servo Commands")."""

from __future__ import annotations

import pytest

from livebridge.drivers import maestro_protocol as mp


def test_set_target_compact_and_pololu():
    # the guide's example: channel 2 to 1500 µs = 6000 quarter-µs = 0b01011101110000 -> low 7 bits, high 7 bits
    assert mp.set_target(2, 6000) == bytes.fromhex("84 02 70 2E")
    assert mp.set_target(2, 6000, device=12) == bytes.fromhex("AA 0C 04 02 70 2E")
    assert mp.set_target(0, 6000) == bytes.fromhex("84 00 70 2E")
    assert mp.set_target(0, 0) == bytes.fromhex("84 00 00 00")  # target 0: no pulses
    assert mp.us_to_quarters(1500) == 6000
    with pytest.raises(ValueError):
        mp.set_target(0, 1 << 14)
    with pytest.raises(ValueError):
        mp.set_target(0, 6000, device=128)


def test_other_commands():
    assert mp.set_multiple_targets(0, [6000, 7000]) == bytes.fromhex("9F 02 00 70 2E 58 36")
    assert mp.set_multiple_targets(3, [6000], device=12) == bytes.fromhex("AA 0C 1F 01 03 70 2E")
    # the guide: 0x87, 0x05, 0x0C, 0x01 sets the speed of channel 5 to 140 (3.5 µs/ms)
    assert mp.set_speed(5, 140) == bytes.fromhex("87 05 0C 01")
    assert mp.set_speed(1, 140, device=12) == bytes.fromhex("AA 0C 07 01 0C 01")
    assert mp.set_acceleration(0, 4) == bytes.fromhex("89 00 04 00")
    assert mp.set_acceleration(0, 255, device=12) == bytes.fromhex("AA 0C 09 00 7F 01")
    assert mp.get_position(5) == bytes.fromhex("90 05")
    assert mp.get_position(5, device=12) == bytes.fromhex("AA 0C 10 05")
    assert mp.get_moving_state() == bytes.fromhex("93")
    assert mp.get_errors() == bytes.fromhex("A1")
    assert mp.get_errors(device=12) == bytes.fromhex("AA 0C 21")
    assert mp.go_home() == bytes.fromhex("A2")
    assert mp.go_home(device=12) == bytes.fromhex("AA 0C 22")


def test_replies():
    # get position / get errors answer low byte first (position in quarter-µs)
    assert mp.decode_u16(bytes([0x70, 0x17])) == 6000
    assert mp.encode_u16(6000) == bytes([0x70, 0x17])
    assert mp.decode_u16(mp.encode_u16(mp.PROTOCOL_ERROR)) == 0x10
    assert mp.error_text(mp.PROTOCOL_ERROR) == "serial protocol error"
    assert mp.error_text(0) == "none"
    with pytest.raises(ValueError):
        mp.decode_u16(b"\x01")


def test_decode_commands():
    decoded = mp.decode_command(bytes.fromhex("84 02 70 2E 90"))
    assert decoded == mp.Decoded(4, mp.Command(mp.SET_TARGET, bytes.fromhex("02 70 2E")))
    assert mp.join14(0x70, 0x2E) == 6000
    # Pololu protocol: the command byte travels without its high bit; decoded, it has it again
    decoded = mp.decode_command(bytes.fromhex("AA 0C 04 02 70 2E"))
    assert decoded == mp.Decoded(6, mp.Command(mp.SET_TARGET, bytes.fromhex("02 70 2E"), device=12))
    decoded = mp.decode_command(bytes.fromhex("9F 02 00 70 2E 58 36"))
    assert decoded.command == mp.Command(mp.SET_MULTIPLE_TARGETS, bytes.fromhex("02 00 70 2E 58 36"))
    assert mp.decode_command(bytes.fromhex("A1")) == mp.Decoded(1, mp.Command(mp.GET_ERRORS, b""))


def test_decode_incomplete_and_malformed():
    assert mp.decode_command(b"") == mp.Decoded(0)
    assert mp.decode_command(bytes.fromhex("84 02 70")) == mp.Decoded(0)  # wait for the last byte
    assert mp.decode_command(bytes.fromhex("AA 0C")) == mp.Decoded(0)
    assert mp.decode_command(bytes.fromhex("9F 02 00 70")) == mp.Decoded(0)
    # a byte with the high bit set inside the data starts a new command: the interrupted one is dropped
    assert mp.decode_command(bytes.fromhex("84 00 90 05")) == mp.Decoded(2, protocol_error=True)
    assert mp.decode_command(bytes.fromhex("05")) == mp.Decoded(1, protocol_error=True)  # stray data byte
    assert mp.decode_command(bytes.fromhex("80 00")) == mp.Decoded(1, protocol_error=True)  # unknown command
    assert mp.decode_command(bytes.fromhex("AA 8C 04")) == mp.Decoded(1, protocol_error=True)
