"""Recording a phone session and playing it back: a simulated iPhone (real UDP on loopback) through the real
pipeline into a take directory; the take read back against what the phone sent; the take solved again through
``replay://`` to a simulated servo bus; old takes still read; a take lacking what a command needs refused."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from livebridge.arkit.head import head_pose_from_rotation
from livebridge.errors import InputError
from livebridge.runtime.build import build_pipeline
from livebridge.runtime.session import load_session
from livebridge.servo.rig import demo_rig
from livebridge.servo.safety import to_raw_int
from livebridge.simulators.iphone import SimulatedIPhone
from livebridge.take.directory import load_take_dir
from livebridge.take.phone_replay import PhoneReplay
from livebridge.take.recorder import TakeRecorder

SERVO_URL = "simdynamixel://?ids=1-16&model=XL330-M288&delay=0"
N_PACKETS = 150  # 2.5 s at 60 Hz: past the servos' 1 s soft start
PHONE_SESSION = '[source]\nkind = "livelinkface"\nurl = "{url}"\n[outputs.render]\nenabled = false\n'


def _wait(condition, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)


@pytest.fixture(scope="module")
def phone_take(tmp_path_factory):
    """A phone session recorded through the real pipeline: ``(take folder, phone, solved frames)``."""
    folder = tmp_path_factory.mktemp("phone")
    session = folder / "phone.toml"
    session.write_text(PHONE_SESSION.format(url="livelinkface://127.0.0.1:0")
                       + '[recording]\nenabled = true\ndirectory = "takes"\n')
    loaded = dataclasses.replace(load_session(session), recording=dataclasses.replace(
        load_session(session).recording, take_name="take1"))
    frames = []
    pipeline = build_pipeline(loaded, log=lambda message: None, on_frame=frames.append)
    receiver = pipeline.front.receiver
    phone = SimulatedIPhone(pipeline.front.muscle_names, *receiver.bound, script="everyday", seed=4, noise=0.02)
    with pipeline:
        phone.run(N_PACKETS)
        _wait(lambda: receiver.accepted == N_PACKETS
              and pipeline.front.frames + receiver.superseded == receiver.accepted)
        time.sleep(0.2)  # the outputs (the recorder) of the last frame
    return folder / "takes" / "take1", phone, frames


def test_a_phone_take_holds_the_packets_the_phone_sent_and_the_contractions_solved(phone_take):
    path, phone, frames = phone_take
    take = load_take_dir(path)
    assert take.complete and take.manifest["source"] == "livelinkface" and take.manifest["version"] == 2
    assert take.manifest["device_id"] == phone.device_id and take.manifest["subject"] == phone.subject
    assert take.manifest["fps"] == 60.0 and take.marker_names == () and take.markers.shape == (take.n_frames, 0, 3)
    assert take.n_frames >= N_PACKETS // 2  # the newest packet wins under load; most are solved

    arkit = take.arkit
    sent = [phone.packet(int(k)) for k in arkit.frame_number]
    # every recorded value is exactly the float32 the phone sent
    assert np.array_equal(arkit.values.astype(np.float32), np.array([p.values for p in sent]).astype(np.float32))
    assert np.array_equal(arkit.sub_frame, [p.sub_frame for p in sent])
    assert np.array_equal(arkit.rate, [p.rate for p in sent])
    assert np.array_equal(arkit.frame_number, take.seq) and np.all(np.diff(arkit.frame_number) > 0)
    assert set(arkit.frame_number) <= set(range(phone.frame0, phone.frame0 + N_PACKETS))
    assert np.ptp(arkit.head_rotation[:, 0]) > 1e-3 and arkit.weights.max() > 0.2  # the performer moved

    # the contractions and times the pipeline solved, row for row (written with 6 decimals)
    by_seq = {f.seq: f for f in frames}
    solved = np.array([by_seq[s].contractions for s in take.seq])
    assert np.abs(take.contractions - solved).max() <= 5e-7
    # written to the microsecond: half of one, plus float64's rounding of a time of ~1e4 s
    assert np.abs(take.t - [by_seq[s].timing.capture for s in take.seq]).max() <= 5e-7 + 1e-9
    truth = phone.truth(arkit.frame_number)
    assert float(np.sqrt(np.mean((take.contractions - truth) ** 2))) < 0.05  # noise 0.02 on the weights


def test_a_phone_take_replays_through_the_pipeline_to_the_servo_bus(phone_take, tmp_path):
    path, _, _ = phone_take
    take = load_take_dir(path)
    session = tmp_path / "replay.toml"
    session.write_text(PHONE_SESSION.format(url=f"replay://{path}?realtime=1"))
    loaded = dataclasses.replace(load_session(session), servo_rig=demo_rig(SERVO_URL))
    frames, lines = [], []
    pipeline = build_pipeline(loaded, log=lines.append, on_frame=frames.append)
    sim = pipeline.servo.buses["head"].companion
    sim.log_goals = True
    with pipeline:
        assert pipeline.wait(30.0), "the replay never ended"
        time.sleep(0.1)
        t_start = pipeline.servo.state.t_start  # the servos' activation (their soft start)
    assert any("every phone has ended" in line for line in lines)
    replay = pipeline.front.receiver
    assert replay.received == take.n_frames

    # solved again from the recorded weights: the same contractions, the recorded head rotation
    by_seq = {f.seq: f for f in frames}
    assert len(by_seq) >= take.n_frames // 2  # paced at 60 Hz: a loaded outputs stage may drop some
    rows = [k for k, s in enumerate(take.seq) if s in by_seq]
    again = np.array([by_seq[take.seq[k]].contractions for k in rows])
    assert np.abs(again - take.contractions[rows]).max() <= 1e-5
    assert all(np.allclose(by_seq[take.seq[k]].head_pose, head_pose_from_rotation(take.arkit.head_rotation[k]))
               for k in rows)

    # the servo bus got, after one goal per servo at activation, one goal per servo for every packet of the take
    # (written on the front thread, whatever the outputs stage drops): what the live path's safety stage makes
    # of the take's contractions at its recorded times (moved to the replay's start), within one count
    rig, mapper = pipeline.servo.rig, pipeline.servo.mapper
    logged = [np.array([goal for _, servo_id, goal in sim.goal_log if servo_id == spec.address]) for spec in rig.servos]
    assert all(len(goals) > take.n_frames for goals in logged)
    written = np.array([goals[1:1 + take.n_frames] for goals in logged]).T  # (n_frames, n_servos)
    offset = frames[0].timing.complete - take.t[rows[0]]
    state = mapper.start(np.array([goals[0] for goals in logged], dtype=float), t_start)
    expected = []
    for x, t in zip(take.contractions, take.t + offset):
        state, targets = mapper.step(state, x, t)
        expected.append(to_raw_int(targets, mapper.low, mapper.high))
    assert np.abs(written - np.array(expected)).max() <= 1
    low = np.minimum([s.low for s in rig.servos], [s.high for s in rig.servos])
    high = np.maximum([s.low for s in rig.servos], [s.high for s in rig.servos])
    assert np.all(written >= low) and np.all(written <= high)
    assert np.ptp(written, axis=0).max() > 0.2 * (high - low).max()  # the replayed face moved the head


def test_an_unpaced_replay_solves_every_packet_and_records_a_phone_take_again(phone_take, tmp_path):
    path, _, _ = phone_take
    take = load_take_dir(path)
    session = tmp_path / "again.toml"
    session.write_text(PHONE_SESSION.format(url=f"replay://{path}?realtime=0")
                       + '[recording]\nenabled = true\ndirectory = "takes"\n')
    pipeline = build_pipeline(load_session(session), log=lambda message: None)
    assert not pipeline.front.realtime
    with pipeline:
        assert pipeline.wait(30.0)
    (again_path,) = (tmp_path / "takes").iterdir()
    again = load_take_dir(again_path)
    assert again.complete and again.n_frames == take.n_frames  # unpaced: nothing dropped
    assert np.array_equal(again.arkit.values, take.arkit.values)
    assert np.array_equal(again.seq, take.seq) and np.abs(again.contractions - take.contractions).max() <= 1e-6


def test_a_camera_take_is_still_version_1_and_reads_without_arkit(tmp_path):
    with TakeRecorder(tmp_path / "cams", ["jaw"], ["m1"]) as recorder:
        recorder.record(0, 1.0, np.array([0.5]), np.zeros((1, 3)))
    take = load_take_dir(tmp_path / "cams")
    assert take.manifest["version"] == 1 and take.arkit is None and "source" not in take.manifest
    with pytest.raises(InputError, match="recorded from cameras") as error:
        PhoneReplay(tmp_path / "cams")
    assert error.value.field == "arkit" and str(error.value.path).endswith("take.toml")


def test_a_phone_recorder_needs_the_packet_of_every_frame(tmp_path):
    with TakeRecorder(tmp_path / "phone", ["jaw"], (), phone=True) as recorder, pytest.raises(ValueError):
        recorder.record(0, 1.0, np.array([0.5]))


def test_a_phone_session_may_record_but_not_raw_frames(tmp_path):
    path = tmp_path / "phone.toml"
    path.write_text('[source]\nkind = "livelinkface"\n[recording]\nenabled = true\ndirectory = "takes"\n')
    assert load_session(path).recording.enabled
    path.write_text('[source]\nkind = "livelinkface"\n[recording]\nenabled = true\ndirectory = "takes"\n'
                    "raw_frames = true\n")
    with pytest.raises(InputError, match="camera images") as error:
        load_session(path)
    assert error.value.field == "recording.raw_frames"


def test_a_relative_replay_url_is_relative_to_the_session_file(tmp_path):
    path = tmp_path / "sub" / "phone.toml"
    path.parent.mkdir()
    path.write_text('[source]\nkind = "livelinkface"\nurl = "replay://takes/t1?realtime=0"\n')
    assert load_session(path).source.url == f"replay://{tmp_path / 'sub' / 'takes' / 't1'}?realtime=0"


def test_the_demo_records_a_phone_take_that_run_replays(tmp_path):
    import re

    from click.testing import CliRunner

    from livebridge.cli import main

    take = tmp_path / "demo-take"
    result = CliRunner().invoke(main, ["demo", "--source", "livelinkface", "--frames", "60", "--no-render",
                                       "--no-servo", "--record", str(take)])
    assert result.exit_code == 0, result.output
    recorded = load_take_dir(take)
    assert recorded.complete and recorded.n_frames >= 60 and recorded.arkit is not None
    session = tmp_path / "replay.toml"
    session.write_text(PHONE_SESSION.format(url="replay://demo-take?realtime=0"))  # relative to the session
    result = CliRunner().invoke(main, ["run", str(session)])
    assert result.exit_code == 0, result.output
    assert int(re.search(r"packets solved: (\d+)", result.output).group(1)) == recorded.n_frames
    assert re.search(rf"phone: {recorded.n_frames} datagrams, 0 lost, refused 0", result.output)


def test_a_phone_take_replayed_as_cameras_says_how_to_replay_it(tmp_path):
    from livebridge.take.replay import open_take

    phone = SimulatedIPhone(("jaw",))
    with TakeRecorder(tmp_path / "phone", ("jaw",), (), phone=True) as recorder:
        recorder.record(phone.frame0, 1.0, np.array([0.5]), packet=phone.packet(phone.frame0))
    with pytest.raises(InputError, match='a phone take has no camera frames.*url = "replay://'):
        open_take(tmp_path / "phone")


def test_a_looping_replay_plays_the_take_again_with_time_running_on(tmp_path):
    phone = SimulatedIPhone(("jaw",))
    with TakeRecorder(tmp_path / "phone", ("jaw",), (), phone=True) as recorder:
        for k in range(3):
            recorder.record(phone.frame0 + k, 5.0 + k / 60, np.array([0.1]), packet=phone.packet(phone.frame0 + k))
    replay = PhoneReplay(tmp_path / "phone", realtime=False, loop=True)
    assert replay.receive(0.0) is None  # not open yet
    replay.open()
    arrivals = [replay.receive(0.0) for _ in range(7)]
    assert [a.packet.frame_number - phone.frame0 for a in arrivals] == [0, 1, 2, 0, 1, 2, 0]
    assert all(np.allclose(a.packet.values, phone.packet(a.packet.frame_number).values, rtol=1e-8, atol=1e-9)
               for a in arrivals)  # 9 digits of what the recorder got (from a phone: float32, exactly)
    assert all(b.t_arrival >= a.t_arrival for a, b in zip(arrivals, arrivals[1:])) and not replay.ended
    replay.stop()
    assert replay.ended and replay.receive(0.0) is None
    once = PhoneReplay(tmp_path / "phone", realtime=False)
    once.open()
    assert [once.receive(0.0) is not None for _ in range(4)] == [True, True, True, False] and once.ended
