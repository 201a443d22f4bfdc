"""Lynxmotion SSC-32U ASCII protocol: golden bytes from the SSC-32U User Guide."""

from __future__ import annotations

import pytest

from livebridge.drivers import ssc32_protocol as sp


def test_encode_moves():
    # the guide: "#5 P1600 S750 <cr>" (channel 5 to 1600 µs at 750 µs/s); the spaces are optional
    assert sp.move({5: 1600}, speeds={5: 750}) == b"#5P1600S750\r"
    # group move, all channels finish together: "#5 P1600 #10 P750 T2500 <cr>"
    assert sp.move({10: 750, 5: 1600}, 2500) == b"#5P1600#10P750T2500\r"
    assert sp.move({0: 1500, 5: 1999.6}, 100) == b"#0P1500#5P2000T100\r"
    assert sp.pulses_off([3, 0]) == b"#0P0#3P0\r"
    with pytest.raises(ValueError):
        sp.move({40: 1500})
    with pytest.raises(ValueError):
        sp.move({})


def test_encode_queries_and_replies():
    assert sp.query_moving() == b"Q\r"
    assert sp.query_pulses([5]) == b"QP5\r"
    assert sp.query_pulses([0, 1]) == b"QP0 QP1\r"
    assert sp.version() == b"VER\r"
    # QP answers one binary byte per channel, 10 µs resolution: 1500 µs is 150
    assert sp.encode_pulse(1500) == 150 and sp.encode_pulse(3000) == 255
    assert sp.decode_pulses(bytes([150, 200])) == [1500, 2000]


def test_decode_lines():
    assert sp.decode_line(b"#5 P1600 S750") == sp.Line((sp.Move(5, 1600, 750),))
    assert sp.decode_line(b"#5 P1600 #10 P750 T2500") == sp.Line((sp.Move(5, 1600), sp.Move(10, 750)), 2500)
    assert sp.decode_line(b"#0P1500#5P2000T100") == sp.Line((sp.Move(0, 1500), sp.Move(5, 2000)), 100)
    assert sp.decode_line(b"QP 5") == sp.Line(queries=(("QP", 5),))
    assert sp.decode_line(b"Q") == sp.Line(queries=(("Q", None),))
    assert sp.decode_line(b"ver") == sp.Line(queries=(("VER", None),))
    assert sp.decode_line(b"Q QP0 QP1 STOP 3") == sp.Line(queries=(("Q", None), ("QP", 0), ("QP", 1), ("STOP", 3)))
    assert sp.decode_line(b"#4") == sp.Line((sp.Move(4),))  # a channel without P: nothing moves
    assert sp.decode_line(b"hello") == sp.Line()  # not a command: ignored, as the controller does
    line = sp.move({0: 1500, 7: 900}, 40, speeds={7: 300})
    assert sp.decode_line(line.rstrip(b"\r")) == sp.Line((sp.Move(0, 1500), sp.Move(7, 900, 300)), 40)
