"""Servo commands under careless and hostile arguments: nothing outside limits or non-finite reaches a
servo, every refusal is one ``Error:`` line naming the option and sends nothing, every call returns."""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from unittest import mock

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

import livebridge.cli.servo as servo_cli
import livebridge.devices.registry as registry
from livebridge.cli import main
from livebridge.servo.rig import backup_path, load_rig

DXL = "simdynamixel://?ids=1-3&delay=0"
MAESTRO = "simmaestro://?channels=8"
SSC32 = "simssc32://?channels=8"
RAW_RANGE = {DXL: (0, 4095), MAESTRO: (64, 4080), SSC32: (500, 2500)}


class BusSpy:
    """Wraps ``open_bus``: remembers every bus opened and switches on the simulator's record of targets."""

    def __init__(self):
        self.buses = []
        self.sims = []  # the bus forgets its simulator when it closes
        self._open = registry.open_bus

    def __call__(self, url, **options):
        bus = self._open(url, **options)
        if hasattr(bus.companion, "log_goals"):
            bus.companion.log_goals = True
        self.buses.append(bus)
        self.sims.append(bus.companion)
        return bus

    def targets(self) -> list[float]:
        """Every raw target the simulators received (pulses-off commands left out), raw units of the bus."""
        out = []
        for sim in self.sims:
            if hasattr(sim, "goal_log"):
                out += [goal for _, _, goal in sim.goal_log]
            elif hasattr(sim, "target_log"):
                out += [quarters / 4 for _, quarters in sim.target_log if quarters]
            else:
                out += [pulse for _, pulse in sim.move_log if pulse]
        return out


@contextmanager
def spied(max_s: float = servo_cli.JOG_MAX_S, settle_s: float = servo_cli.JOG_SETTLE_S):
    """A :class:`BusSpy` in place of ``open_bus``; ``max_s``/``settle_s`` shorten jogs for fast tests."""
    spy = BusSpy()
    with mock.patch.object(registry, "open_bus", spy), mock.patch.object(servo_cli, "JOG_MAX_S", max_s), \
            mock.patch.object(servo_cli, "JOG_SETTLE_S", settle_s):
        yield spy


def assert_refused(result, option: str | None = None):
    """Exit != 0, exactly one ``Error:`` line (naming ``option``), no traceback."""
    assert result.exit_code != 0, result.output
    assert isinstance(result.exception, SystemExit), result.exception
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.output
    assert "Traceback" not in result.output
    if option is not None:
        assert option in errors[0], result.output


@pytest.mark.parametrize("args, option", [
    (["--to", "nan"], "--to"),
    (["--to", "inf"], "--to"),
    (["--to", "-inf"], "--to"),
    (["--to", "5000"], "--to"),
    (["--to", "-1"], "--to"),
    (["--to", "2500", "--high", "2400"], "--to"),
    (["--by", "nan"], "--by"),
    (["--by", "1e300"], "--by"),
    (["--by", "-inf"], "--by"),
    (["--by", "10", "--speed", "0"], "--speed"),
    (["--by", "10", "--speed", "-5"], "--speed"),
    (["--by", "10", "--speed", "nan"], "--speed"),
    (["--by", "10", "--speed", "inf"], "--speed"),
    (["--by", "10", "--speed", "5e-324"], "--speed"),
    (["--to", "0", "--speed", "1"], "--speed"),  # up to 2048 s: longer than a jog may take
    (["--by", "10", "--low", "nan"], "--low"),
    (["--by", "10", "--high", "1e9"], "--high"),
    (["--by", "10", "--low", "-100"], "--low"),
    (["--by", "10", "--low", "3000", "--high", "2000"], "--low/--high"),
    (["--by", "10", "--low", "2000", "--high", "2000"], "--low/--high"),
    (["--by", "10", "--id", "253"], "--id"),
    (["--by", "10", "--id", "-1"], "--id"),
    (["--to", "1", "--by", "1"], "--to"),
    ([], "--to"),
])
def test_jog_refuses_before_opening_the_bus(args, option):
    args = args if "--id" in args else [*args, "--id", "1"]
    with spied() as spy:
        t0 = time.monotonic()
        result = CliRunner().invoke(main, ["servo", "jog", DXL, *args])
        assert time.monotonic() - t0 < 5
    assert_refused(result, option)
    assert spy.buses == []  # nothing opened, so nothing sent


def test_jog_to_nan_used_to_move_to_raw_zero():
    """The reported probe: `--to nan` moved the servo from its position to raw 0."""
    with spied() as spy:
        result = CliRunner().invoke(main, ["servo", "jog", DXL, "--id", "1", "--to", "nan"])
    assert_refused(result, "--to")
    assert spy.targets() == []


@pytest.mark.parametrize("url, address, args, low, high", [
    (DXL, "2", ["--to", "2100", "--speed", "2000"], 0, 4095),
    (DXL, "1", ["--by", "-190", "--low", "1900", "--high", "2100"], 1900, 2100),  # from 2048: stops at --low
    (MAESTRO, "3", ["--to", "1600", "--speed", "2000"], 64, 4080),
    (SSC32, "5", ["--by", "300", "--high", "1600", "--speed", "2000"], 500, 1600),
])
def test_jog_moves_inside_the_limits(url, address, args, low, high):
    with spied() as spy:
        result = CliRunner().invoke(main, ["servo", "jog", url, "--id", address, *args])
    assert result.exit_code == 0, result.output
    targets = spy.targets()
    assert targets and all(math.isfinite(t) and low <= t <= high for t in targets)


@pytest.mark.parametrize("args, option", [
    (["--ids", "1-999999999"], "--ids"),  # refused before the range is expanded
    (["--ids", "-3"], "--ids"),
    (["--ids", "5-2"], "--ids"),
    (["--ids", "1,1"], "--ids"),
    (["--ids", "x"], "--ids"),
    (["--ids", ","], "--ids"),
])
def test_scan_refuses_bad_address_lists(args, option):
    with spied() as spy:
        result = CliRunner().invoke(main, ["servo", "scan", DXL, *args])
    assert_refused(result, option)
    assert spy.buses == []


@pytest.mark.parametrize("args, option", [
    (["dynamixel", "--corrupt", "nan"], "--corrupt"),
    (["dynamixel", "--drop", "1.5"], "--drop"),
    (["dynamixel", "--drop", "-0.1"], "--drop"),
    (["dynamixel", "--baud", "0"], "--baud"),
    (["dynamixel", "--baud", "123"], "--baud"),
    (["dynamixel", "--delay", "255"], "--delay"),
    (["dynamixel", "--delay", "-1"], "--delay"),
    (["dynamixel", "--ids", "0-1000000000"], "--ids"),
    (["dynamixel", "--ids", "253"], "--ids"),
    (["maestro", "--channels", "0"], "--channels"),
    (["maestro", "--channels", "1000000"], "--channels"),
    (["maestro", "--device", "128"], "--device"),
    (["maestro", "--corrupt", "inf"], "--corrupt"),
    (["ssc32", "--drop", "nan"], "--drop"),
])
def test_sim_refuses_bad_options_before_serving(args, option):
    with mock.patch("livebridge.cli.sim._serve", side_effect=AssertionError("served")):
        result = CliRunner().invoke(main, ["sim", *args])
    assert_refused(result, option)


_WILD = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "0", "-0", "1e308", "-1e308", "5e-324", "1e-300", "abc", ""]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**30, 10**30).map(str),
)
_RAW = st.one_of(st.integers(-100, 4200).map(str), st.floats(0, 4095).map(lambda v: f"{v:.3f}"))
_NUMBERS = st.one_of(_RAW, _RAW, _WILD)  # mostly plausible, so some moves are made, and every kind of nonsense
_SPEEDS = st.one_of(st.floats(2e4, 1e7).map(repr), st.floats(2e4, 1e7).map(repr), _WILD)


def _options(draw_values: dict) -> list[str]:
    return [part for key, value in draw_values.items() if value is not None for part in (key, value)]


_MOVE = st.one_of(st.fixed_dictionaries({"--to": _NUMBERS}), st.fixed_dictionaries({"--by": _NUMBERS}),
                  st.fixed_dictionaries({}, optional={"--to": _NUMBERS, "--by": _NUMBERS}))
_JOG = st.builds(lambda move, rest: {**move, **rest}, _MOVE,
                 st.fixed_dictionaries({"--speed": _SPEEDS}, optional={"--low": _NUMBERS, "--high": _NUMBERS}))


def _check_jog(url: str, address: str, options: dict, hold: bool):
    low_dev, high_dev = RAW_RANGE[url]
    args = ["servo", "jog", url, "--id", address, *_options(options)] + (["--hold"] if hold else [])
    with spied(max_s=0.3, settle_s=0.01) as spy:
        t0 = time.monotonic()
        result = CliRunner().invoke(main, args)
        elapsed = time.monotonic() - t0
    assert elapsed < 10, (args, elapsed)  # every call returns, a jog within its bounded time
    targets = spy.targets()
    assert all(math.isfinite(t) for t in targets)
    event("refused" if result.exit_code else "moved")
    if result.exit_code != 0:
        assert_refused(result)
        assert targets == [], args
        return
    low = float(options.get("--low", low_dev))
    high = float(options.get("--high", high_dev))
    assert all(low <= t <= high for t in targets), (args, targets)
    if "--to" in options:
        assert f"to {float(options['--to']):g}" in result.output


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(options=_JOG, address=st.sampled_from(["1", "3", "1", "3", "0", "253", "-1", "99999999999999999999"]),
       hold=st.booleans())
@example(options={"--to": "nan"}, address="1", hold=False)
@example(options={"--by": "10", "--speed": "0"}, address="1", hold=True)
@example(options={"--to": "2100", "--speed": "3000", "--low": "2000", "--high": "2200"}, address="1", hold=False)
def test_jog_fuzz_dynamixel(options, address, hold):
    _check_jog(DXL, address, options, hold)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(url=st.sampled_from([MAESTRO, SSC32]), options=_JOG,
       address=st.sampled_from(["0", "5", "0", "5", "24", "-1", "32"]))
@example(url=MAESTRO, options={"--to": "inf"}, address="0")
@example(url=SSC32, options={"--by": "-400", "--speed": "5000", "--low": "1200"}, address="5")
def test_jog_fuzz_hobby_servos(url, options, address):
    _check_jog(url, address, options, hold=False)


RIG = """\
# the test head
[buses.head]
url = "simdynamixel://?ids=1&delay=0"   # one servo

[servos.jaw]
bus = "head"
id = 1
muscles = { jaw = 1.0 }
neutral = 2000        # rest
min = 1900            # reached at drive -1
max = 2600            # reached at drive +1
"""


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(options=st.fixed_dictionaries({}, optional={"--min": _NUMBERS, "--neutral": _NUMBERS, "--max": _NUMBERS}))
@example(options={"--max": "nan"})
@example(options={"--min": "-inf", "--max": "2500"})
@example(options={"--max": "2500"})
def test_limits_fuzz(tmp_path, options):
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    backup_path(path).unlink(missing_ok=True)
    result = CliRunner().invoke(main, ["servo", "limits", str(path), "jaw", *_options(options)])
    if result.exit_code != 0:
        assert_refused(result)
        assert path.read_text() == RIG and not backup_path(path).exists()
        return
    jaw = load_rig(path).servo("jaw")
    values = (jaw.minimum, jaw.neutral, jaw.maximum)
    assert all(math.isfinite(v) and 0 <= v <= 4095 for v in values)
    assert backup_path(path).read_text() == RIG
