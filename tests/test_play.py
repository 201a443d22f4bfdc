"""``livebridge play``: contraction files drive the simulated Dynamixel bus through the live path's safety stage.

A fake monotonic clock stands in for time (its sleep advances it), so the tests do not sleep through files;
what the servos received is read from the simulator's log of goal positions.
"""

from __future__ import annotations

import math
from unittest import mock

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import livebridge.servo.output as output_module
from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.servo import playback
from livebridge.servo.output import ServoOutput
from livebridge.servo.rig import default_muscle_names, demo_rig

MUSCLES = default_muscle_names()
URL = "simdynamixel://?ids=1-16&model=XL330-M288&delay=0"


class FakeClock:
    """Monotonic time that moves only when slept on; ``interrupt_at``: Ctrl-C once time reaches it."""

    def __init__(self, start: float = 100.0, interrupt_at: float = math.inf):
        self.now, self.interrupt_at = start, interrupt_at

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert math.isfinite(seconds) and seconds >= 0
        self.now += seconds
        if self.now >= self.interrupt_at:
            self.interrupt_at = math.inf
            raise KeyboardInterrupt


class Sims:
    """Wraps the output's ``open_bus``: keeps each simulator and switches on its log of goal positions."""

    def __init__(self):
        self.sims = []
        self._open = output_module.open_bus

    def __call__(self, url, **options):
        bus = self._open(url, **options)
        bus.companion.log_goals = True
        self.sims.append(bus.companion)
        return bus

    def goals(self) -> dict[int, list[int]]:
        """Servo id -> every goal position it received, in order."""
        out: dict[int, list[int]] = {}
        for sim in self.sims:
            for _, servo_id, goal in sim.goal_log:
                out.setdefault(servo_id, []).append(goal)
        return out


def write_csv(path, header, rows) -> None:
    path.write_text(",".join(header) + "\n" + "".join(",".join(map(str, row)) + "\n" for row in rows))


def steady_targets(rig, x) -> np.ndarray:
    """Raw targets the safety stage settles on for constant contractions ``x`` (ground truth for a hold)."""
    mapper = rig.safety(MUSCLES)
    state = mapper.start(mapper.neutral, 0.0)
    for k in range(1, 2000):
        state, targets = mapper.step(state, x, k * 0.01)
    return np.rint(targets)


@pytest.fixture
def rig_file(tmp_path):
    rig = demo_rig(URL)
    path = tmp_path / "head.toml"
    rig.save(path)
    return rig, path


def run_play(args, clock):
    sims = Sims()
    with mock.patch.object(playback, "CLOCK", clock), mock.patch.object(playback, "SLEEP", clock.sleep), \
            mock.patch.object(output_module, "open_bus", sims):
        result = CliRunner().invoke(main, ["play", *map(str, args)])
    return result, sims


def test_play_drives_the_bus_to_the_file_pose_and_back_to_neutral(tmp_path, rig_file):
    rig, path = rig_file
    x = np.linspace(0.1, 0.9, len(MUSCLES))
    rows = [[f"{t:.2f}", *x] for t in np.arange(0, 4, 0.02)]
    # the recorder's layout: frame, seq, t, muscles..., error columns
    write_csv(tmp_path / "c.csv", ["frame", "seq", "t", *MUSCLES, "error_upper_mm", "error_lower_mm"],
              [[k, k, *row, 0.1, 0.2] for k, row in enumerate(rows)])
    result, sims = run_play([tmp_path / "c.csv", "--rig", path], FakeClock())
    assert result.exit_code == 0, result.output
    goals = sims.goals()
    expected = steady_targets(rig, x)
    neutral = np.array([s.neutral for s in rig.servos])
    for i, servo in enumerate(rig.servos):
        seen = np.array(goals[servo.address])
        assert np.min(np.abs(seen - expected[i])) <= 1, servo.name  # reached the file's pose
        assert abs(seen[-1] - neutral[i]) <= 1, servo.name  # and eased back at the end
        assert np.all((seen >= servo.low) & (seen <= servo.high))
    sim = sims.sims[0]
    assert not any(sim.servo(s.address).torque_on for s in rig.servos)  # torque off


def test_speed_scales_time(tmp_path, rig_file):
    _, path = rig_file
    write_csv(tmp_path / "c.csv", ["time", *MUSCLES], [[t, *[0.5] * len(MUSCLES)] for t in np.arange(0, 2, 0.01)])
    frames = {}
    for speed in (0.5, 2.0):
        result, _ = run_play([tmp_path / "c.csv", "--rig", path, "--speed", speed], FakeClock())
        assert result.exit_code == 0, result.output
        frames[speed] = int(result.output.split("played ")[1].split()[0])
    # 2 s of file at 50 frames/s: 200 frames at half speed, 50 at double speed
    assert frames[0.5] == pytest.approx(200, abs=2) and frames[2.0] == pytest.approx(50, abs=2)


def test_ctrl_c_eases_to_neutral_and_turns_torque_off(tmp_path, rig_file):
    rig, path = rig_file
    write_csv(tmp_path / "c.csv", ["t", *MUSCLES], [[t, *[1.0] * len(MUSCLES)] for t in np.arange(0, 3, 0.02)])
    result, sims = run_play([tmp_path / "c.csv", "--rig", path, "--loop"], FakeClock(start=100.0, interrupt_at=103.0))
    assert result.exit_code == 130, result.output
    assert "easing to neutral" in result.output
    goals = sims.goals()
    for servo in rig.servos:
        assert abs(goals[servo.address][-1] - servo.neutral) <= 1
        assert not sims.sims[0].servo(servo.address).torque_on


def test_loop_plays_the_file_again(tmp_path, rig_file):
    rig, path = rig_file
    # one muscle steps up half way through the file: with --loop it steps up again on the second pass
    rows = [[t, *([1.0 if t >= 0.5 else 0.0] + [0.0] * (len(MUSCLES) - 1))] for t in np.arange(0, 1, 0.02)]
    write_csv(tmp_path / "c.csv", ["t", *MUSCLES], rows)
    result, sims = run_play([tmp_path / "c.csv", "--rig", path, "--loop"], FakeClock(start=0.0, interrupt_at=2.9))
    assert result.exit_code == 130, result.output
    seen = np.array(sims.goals()[rig.servos[0].address], dtype=float)
    rising = np.flatnonzero(np.diff(seen) > 0)
    assert len(rising) and np.any(np.diff(rising) > 10)  # rises in more than one pass


def test_file_errors_name_file_line_and_column(tmp_path, rig_file):
    _, path = rig_file
    cases = {
        "unknown.csv": ("t,frontalis_L,smile\n0,0.1,0.2\n", ("'smile'", "line 1")),
        "text.csv": ("t,frontalis_L\n0,0.1\n0.1,high\n", ("line 3", "column 2", "frontalis_L")),
        "ragged.csv": ("t,frontalis_L\n0,0.1\n0.1,0.2,0.3\n0.2,0\n", ("line 3", "3 fields")),
        "notime.csv": ("frontalis_L\n0.1\n", ("no time column",)),
        "badtime.csv": ("t,frontalis_L\n0,0.1\nnan,0.2\n", ("line 3", "column 1", "finite time")),
    }
    for name, (text, words) in cases.items():
        (tmp_path / name).write_text(text)
        result, sims = run_play([tmp_path / name, "--rig", path], FakeClock())
        assert result.exit_code == 1, result.output
        assert not sims.sims  # refused before any bus was opened
        error = [line for line in result.output.splitlines() if line.startswith("Error:")]
        assert len(error) == 1 and name in error[0], result.output
        for word in words:
            assert word in error[0], (name, result.output)


def test_ignore_extra_and_missing_muscles(tmp_path):
    write_csv(tmp_path / "c.csv", ["t", "jaw", "blink_rate"], [[0, 0.5, 3], [0.1, "", 4], [0.2, 2.0, 5]])
    with pytest.raises(InputError, match="blink_rate"):
        playback.read_contractions(tmp_path / "c.csv", MUSCLES)
    track = playback.read_contractions(tmp_path / "c.csv", MUSCLES, ignore_extra=True)
    jaw = MUSCLES.index("jaw")
    np.testing.assert_array_equal(track.values[:, jaw], [0.5, 0.5, 1.0])  # held, then clipped
    assert np.all(np.delete(track.values, jaw, axis=1) == 0)  # missing muscles: neutral
    assert any("no column for" in note for note in track.notes)


def test_semicolons_na_and_time_going_backwards(tmp_path):
    (tmp_path / "c.csv").write_text("time;jaw\n0;NA\n0.5;0.4\n0.25;0.9\n0.5;0.9\n1.0;0.6\n")
    track = playback.read_contractions(tmp_path / "c.csv", MUSCLES)
    np.testing.assert_array_equal(track.t, [0, 0.5, 1.0])
    np.testing.assert_array_equal(track.values[:, MUSCLES.index("jaw")], [0.0, 0.4, 0.6])
    assert any("skipped" in note and "line 4" in note for note in track.notes)


# ------------------------------------------------------------------------------------- the safety property
_cell = st.one_of(st.floats(-5, 5), st.just(math.nan), st.just(math.inf), st.just(-math.inf), st.just(""),
                  st.just("NA"))
_step = st.one_of(st.floats(0.001, 0.1), st.floats(0.3, 1.5), st.floats(-1.0, 0.0))  # frames, gaps, backwards
_rows = st.lists(st.tuples(_step, st.lists(_cell, min_size=4, max_size=4)), min_size=1, max_size=25)


@pytest.fixture(scope="module")
def shared_output():
    """One configured simulated bus for every example (activated and released by each)."""
    sims = Sims()
    rig = demo_rig(URL)
    with mock.patch.object(output_module, "open_bus", sims):
        output = ServoOutput(rig, MUSCLES, poll_every=25)
        output.configure()
    yield rig, output, sims
    output.close(ease=False)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=_rows, speed=st.sampled_from([0.5, 1.0, 3.0]))
def test_nothing_unsafe_reaches_a_servo_from_any_file(tmp_path_factory, shared_output, rows, speed):
    rig, output, sims = shared_output
    columns = ["jaw", "frontalis_L", "zygomatic_major_R", "orbicularis_oris"]
    t, table = 0.0, []
    for step, cells in rows:
        t += step
        table.append([repr(t), *[c if isinstance(c, str) else repr(c) for c in cells]])
    path = tmp_path_factory.mktemp("play") / "c.csv"
    write_csv(path, ["t", *columns], table)
    track = playback.read_contractions(path, MUSCLES)
    assert np.all(np.isfinite(track.values)) and np.all((track.values >= 0) & (track.values <= 1))
    assert np.all(np.diff(track.t) > 0)
    clock = FakeClock()
    sent = []
    real_send = output.send

    def send(x, t=None, poll=None):
        raw = real_send(x, t, poll)
        sent.append((clock(), raw))
        return raw

    for sim in sims.sims:
        sim.goal_log.clear()
    with mock.patch.object(output, "send", send):
        playback.play(track, output, speed, clock=clock, sleep=clock.sleep)  # returns: nothing to interrupt
    output.deactivate()
    low, high = np.ceil(output.mapper.low), np.floor(output.mapper.high)
    times = np.array([s for s, _ in sent])
    raw = np.array([r for _, r in sent], dtype=float)
    assert np.all(np.isfinite(raw)) and np.all((raw >= low) & (raw <= high))
    slew = output.mapper.slew
    assert np.all(np.abs(np.diff(raw, axis=0)) <= slew * np.diff(times)[:, None] + 1.0)  # +1: integer rounding
    goals = sims.goals()
    for i, servo in enumerate(rig.servos):  # what the bus received: the same safe targets, in order
        seen = np.array(goals[servo.address], dtype=float)
        assert np.all((seen >= low[i]) & (seen <= high[i]))
        # besides the sent targets, only the present position held at torque-on (sent first; on a loaded
        # machine the simulator may log it again after the previous example's release)
        assert set(seen[1:]) <= set(raw[:, i]) | {seen[0]}
