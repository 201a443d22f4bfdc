"""Rig file parsing and validation; ServoOutput end to end on simulated buses."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.face.basis import CHOE_KO_MUSCLES
from livebridge.servo.output import ServoOutput
from livebridge.servo.rig import demo_rig, load_rig, set_servo_limits

MUSCLES = [m.name for m in CHOE_KO_MUSCLES]

RIG = """
frame_rate = 40.0
[safety]
watchdog_s = 0.3
soft_start_s = 0.2
ease_s = 0.3
[buses.head]
url = "simdynamixel://?ids=1-3&model=XL330-M288&delay=0"
[servos.jaw]
bus = "head"
id = 1
model = "XL330-M288"
muscles = { jaw = 1.0, orbicularis_oris = -0.5 }
curve = "gamma"
gamma = 0.8
neutral = 2048
min = 1900
max = 2600
slew = 3000
filter = { kind = "exponential", tau = 0.02 }
[servos.smile_L]
bus = "head"
id = 2
muscles = { zygomatic_major_L = 1.0 }
curve = { kind = "piecewise", points = [[0, 0], [0.5, 0.8], [1, 1]] }
neutral = 2048
min = 2200
max = 1700
slew = 2000
filter = { kind = "one_euro", min_cutoff = 2.0, beta = 0.3 }
[servos.brow_L]
bus = "head"
id = 3
muscles = { frontalis_L = 1.0 }
neutral = 2048
min = 2000
max = 2300
"""


def _write(tmp_path, text):
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def test_load_rig(tmp_path):
    rig = load_rig(_write(tmp_path, RIG))
    assert rig.frame_rate == 40 and rig.watchdog_s == 0.3
    jaw, smile, brow = rig.servos
    assert jaw.muscles == (("jaw", 1.0), ("orbicularis_oris", -0.5)) and jaw.curve.kind == "gamma"
    assert smile.low == 1700 and smile.high == 2200 and smile.filter.kind == "one_euro"
    assert brow.slew == 600.0  # default: full range in half a second
    mapping = rig.mapping(MUSCLES)
    assert mapping.weights.shape == (3, 16)
    x = np.zeros(16)
    x[MUSCLES.index("zygomatic_major_L")] = 1.0
    assert mapping.raw(x)[1] == 1700  # inverted servo: max is the lower number
    rig.save(tmp_path / "again.toml")
    assert load_rig(tmp_path / "again.toml").servos == rig.servos


@pytest.mark.parametrize("change, match", [
    (("jaw = 1.0, orbicularis_oris", "jaw = 1.0, orbicularis_orbis"), "jaw.*orbicularis_orbis"),
    (("id = 3", "id = 2"), "brow_L.*smile_L.*id 2"),
    (("max = 2600", "max = 5000"), "jaw.*outside the dynamixel range"),
    (("neutral = 2048\nmin = 2000", "neutral = 1000\nmin = 2000"), "brow_L.*neutral"),
    (('curve = "gamma"', 'curve = "cubic"'), "jaw.*cubic"),
    (("bus = \"head\"\nid = 3", "bus = \"neck\"\nid = 3"), "brow_L.*unknown bus"),
])
def test_errors_name_the_servo(tmp_path, change, match):
    with pytest.raises(InputError, match=match) as info:
        load_rig(_write(tmp_path, RIG.replace(*change)))
    assert str(tmp_path) in str(info.value)


def test_set_servo_limits(tmp_path):
    path = _write(tmp_path, RIG)
    rig = set_servo_limits(path, "jaw", minimum=1950, maximum=2500)
    assert rig.servo("jaw").minimum == 1950 and load_rig(path).servo("jaw").maximum == 2500
    with pytest.raises(InputError, match="jaw"):
        set_servo_limits(path, "jaw", maximum=9000)
    assert load_rig(path).servo("jaw").maximum == 2500  # the bad value was not written


def test_servo_output_lifecycle(tmp_path):
    rig = load_rig(_write(tmp_path, RIG))
    out = ServoOutput(rig, MUSCLES)
    out.configure()
    try:
        sim = out.buses["head"].companion
        out.activate()
        assert all(s.torque_on for s in sim.servos.values())
        x = np.zeros(16)
        x[MUSCLES.index("jaw")] = 1.0
        for _ in range(30):
            raw = out.send(x)
            time.sleep(0.01)
        assert raw[0] == 2600
        time.sleep(0.1)
        out.send(x)
        assert out.status()["jaw"].position == pytest.approx(2600, abs=2)
        assert out.faults() == {}
        out.send(np.full(16, np.nan))  # nothing non-finite ever reaches a servo
        assert out.last_targets[0] == pytest.approx(2600)
    finally:
        out.close()
    # close eased to neutral, then torque off
    assert sim.servo(1).get("goal_position") == 2048 and not sim.servo(1).torque_on
    assert sim.servo(1).position == pytest.approx(2048, abs=30)


def test_servo_output_estop_and_bus_kinds():
    for url in ("simmaestro://?channels=16", "simssc32://"):
        rig = replace(demo_rig(url), soft_start_s=0.0)
        out = ServoOutput(rig, MUSCLES)
        out.configure()
        try:
            out.activate()
            for k in range(10):
                out.send(np.full(16, 0.5), t=k * 0.02)
            out.estop()
            sim = out.buses["head"].companion
            if url.startswith("simmaestro"):
                assert sim.wait_until(lambda s=sim: s.target[:16] == [0] * 16)  # pulses stopped
            else:
                assert sim.wait_until(lambda s=sim: s.goal[:16] == [0.0] * 16)
            assert out.send(np.full(16, 1.0)) is not None and out.state.estopped
        finally:
            out.close()
