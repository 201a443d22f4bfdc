"""Session files: validated up front, errors name the field, paths relative to the file."""

from __future__ import annotations

import pytest

from livebridge.errors import InputError
from livebridge.reconstruct.pipeline import ReconstructConfig
from livebridge.runtime.session import load_session
from livebridge.solve.solver import SolverConfig


def _write(tmp_path, text, name="session.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_full_session_with_relative_paths(tmp_path):
    sub = tmp_path / "conf"
    sub.mkdir()
    for name in ("basis.npz", "markers.toml", "rig.toml", "head.toml"):
        (sub / name).write_text("")
    path = _write(sub, """
calibration = "rig.toml"
[cameras]
urls = ["v4l2:///dev/video0?fps=60", "v4l2:///dev/video2?fps=60"]
sync_tolerance = 0.25
[face]
basis = "basis.npz"
markers = "markers.toml"
[reconstruct]
tolerance_px = 1.5
[solver]
mode = "joint"
exaggerate = true
[servo]
rig = "head.toml"
[outputs.render]
port = 0
[outputs.vmc]
enabled = true
port = 39540
case = "pascal"
mapping = { jaw = { jawOpen = 1.0 } }
[recording]
enabled = true
directory = "../takes"
raw_frames = true
[runtime]
status_interval = 0.5
frames = 300
""")
    session = load_session(path)
    assert session.camera_urls == ("v4l2:///dev/video0?fps=60", "v4l2:///dev/video2?fps=60")
    assert session.basis == sub / "basis.npz" and session.markers == sub / "markers.toml"
    assert session.calibration == sub / "rig.toml" and session.servo_rig == sub / "head.toml"
    assert session.recording.directory == tmp_path / "takes" and session.recording.raw_frames
    assert session.solver == SolverConfig(mode="joint", exaggerate=True)
    assert session.reconstruct == ReconstructConfig(tolerance_px=1.5)
    assert session.vmc.enabled and session.vmc.port == 39540 and session.vmc.case == "pascal"
    assert session.vmc.mapping == {"jaw": {"jawOpen": 1.0}}
    assert session.render.port == 0 and session.render.host == "127.0.0.1"
    assert session.frames == 300 and session.status_interval == 0.5 and session.sync_tolerance == 0.25


def test_minimal_simulated_session_defaults(tmp_path):
    session = load_session(_write(tmp_path, '[cameras]\nurls = ["sim://rig?cameras=4"]\n'))
    assert session.basis == "builtin" and session.markers is None and session.calibration is None
    assert session.render.enabled and session.render.port == 8765
    assert not session.vmc.enabled and not session.recording.enabled and session.servo_rig is None
    assert session.render.allowed_origins == ()


def test_render_allowed_origins_reach_the_server(tmp_path):
    from livebridge.runtime.build import build_pipeline

    session = load_session(_write(tmp_path, '[cameras]\nurls = ["sim://rig?cameras=2&realtime=0&size=160x100"]\n'
                                            '[outputs.render]\nport = 0\n'
                                            'allowed_origins = ["https://studio.example:8443"]\n'))
    assert session.render.allowed_origins == ("https://studio.example:8443",)
    pipeline = build_pipeline(session, log=lambda message: None)
    try:
        assert pipeline.render.allowed_origins == {("https", "studio.example", 8443)}
    finally:
        pipeline.stop()


@pytest.mark.parametrize("text,field", [
    ("", "cameras.urls"),
    ('[cameras]\nurls = []\n', "cameras.urls"),
    ('[cameras]\nurls = ["webcam0"]\n', "cameras.urls"),
    ('[cameras]\nurls = ["v4l2:///dev/video0"]\n', "calibration"),
    ('[cameras]\nurls = ["sim://rig"]\nsync_tolerance = 0.9\n', "cameras.sync_tolerance"),
    ('[cameras]\nurls = ["sim://rig"]\nurl = "x"\n', "cameras.url"),
    ('[cameras]\nurls = ["sim://rig"]\n[face]\nbasis = "missing.npz"\n', "face.basis"),
    ('[cameras]\nurls = ["sim://rig"]\n[face]\nbasis = "ict"\n', "face.basis"),  # reference data: tests' only
    ('[cameras]\nurls = ["sim://rig"]\n[face]\nmarkers = "missing.toml"\n', "face.markers"),
    ('[cameras]\nurls = ["sim://rig"]\n[solver]\nmode = "fast"\n', "solver.mode"),
    ('[cameras]\nurls = ["sim://rig"]\n[solver]\nsweeps = "two"\n', "solver.sweeps"),
    ('[cameras]\nurls = ["sim://rig"]\n[servo]\nrig = "nope.toml"\n', "servo.rig"),
    ('[cameras]\nurls = ["sim://rig"]\n[outputs.render]\nport = 70000\n', "outputs.render.port"),
    ('[cameras]\nurls = ["sim://rig"]\n[outputs.render]\nenabled = "yes"\n', "outputs.render.enabled"),
    ('[cameras]\nurls = ["sim://rig"]\n[outputs.vmc]\ncase = "SHOUT"\n', "outputs.vmc.case"),
    ('[cameras]\nurls = ["sim://rig"]\n[outputs.osc]\nport = 1\n', "outputs.osc"),
    ('[cameras]\nurls = ["sim://rig"]\n[recording]\nenabled = true\n', "recording.directory"),
    ('[cameras]\nurls = ["sim://rig"]\n[recording]\nframe_format = "jpg"\n', "recording.frame_format"),
    ('[cameras]\nurls = ["sim://rig"]\n[runtime]\nframes = -3\n', "runtime.frames"),
    ('[cameras]\nurls = ["sim://rig"]\n[camera]\nurls = []\n', "camera"),
    ('[cameras]\nurls = ["sim://rig"]\n[outputs.render]\nallowed_origins = ["evil.example"]\n',
     "outputs.render.allowed_origins[0]"),
    ('[cameras]\nurls = ["sim://rig"]\n[outputs.render]\nallowed_origins = "http://a:1"\n',
     "outputs.render.allowed_origins"),
])
def test_errors_name_file_and_field(tmp_path, text, field):
    path = _write(tmp_path, text)
    with pytest.raises(InputError) as info:
        load_session(path)
    assert info.value.field == field, str(info.value)
    assert info.value.path == str(path.resolve())


@pytest.mark.parametrize("table,tolerance", [
    ("", ReconstructConfig().tolerance_px),
    ("tolerance_px = 2.5\n", 2.5),
    ("max_residual_px = 1.0\n", 1.0),
    ("tolerance_px = 2.5\nmax_residual_px = 2.0\n", 2.0),
    ("tolerance_px = 0.8\nmax_residual_px = 2.0\n", 0.8),
])
def test_the_session_holds_the_stage_configs(tmp_path, table, tolerance):
    """One tolerance gates and rejects: the smaller of tolerance_px and max_residual_px."""
    session = load_session(_write(tmp_path, f'[cameras]\nurls = ["sim://rig"]\n[reconstruct]\n{table}'))
    assert session.reconstruct == ReconstructConfig(tolerance_px=tolerance)
    assert session.solver == SolverConfig()


def test_a_simulated_rig_films_the_session_face(tmp_path):
    from livebridge.runtime.build import open_session_cameras

    session = load_session(_write(tmp_path, '[cameras]\nurls = ["sim://rig?basis=face.npz"]\n'))
    with pytest.raises(InputError) as info:
        open_session_cameras(session)
    assert info.value.field == "cameras.urls[0]" and "[face]" in info.value.message


def test_malformed_toml_names_the_file(tmp_path):
    path = _write(tmp_path, "[cameras\n")
    with pytest.raises(InputError, match="session.toml"):
        load_session(path)


def test_run_a_simulated_rig_with_a_calibration_file(tmp_path):
    """`livebridge run` on sim:// cameras + a calibration written by save_calibration: the rig films with
    the calibrated cameras (5 of them, not the URL's default 4) and the pipeline labels and solves."""
    import re

    from click.testing import CliRunner

    from livebridge.calibration.calibfile import save_calibration
    from livebridge.cli import main
    from livebridge.simulators.rig import RigConfig, default_face, generate_cameras

    basis, _ = default_face()
    save_calibration(tmp_path / "rig.toml", generate_cameras(basis, 5, RigConfig(size=(640, 400)), seed=7))
    session = _write(tmp_path, """
calibration = "rig.toml"
[cameras]
urls = ["sim://rig?seed=2&realtime=0&frames=400"]
[outputs.render]
enabled = false
[runtime]
frames = 40
""")
    result = CliRunner().invoke(main, ["run", str(session)])
    assert result.exit_code == 0, result.output
    labelled = float(re.search(r"labelled markers ([\d.]+)%", result.output).group(1))
    alive, total = re.search(r"cameras alive (\d+)/(\d+)", result.output).groups()
    upper, lower = (float(v) for v in re.search(r"error upper ([\d.]+) mm, lower ([\d.]+) mm", result.output).groups())
    assert int(re.search(r"frame sets solved: (\d+)", result.output).group(1)) >= 40  # before the take ends
    assert alive == total == "5" and labelled > 90 and upper < 0.5 and lower < 0.5, result.output


def test_a_bad_calibration_file_is_reported_before_anything_starts(tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main

    (tmp_path / "rig.toml").write_text('[cam_0]\nname = "cam0"\nsize = [640, 400]\n')
    session = _write(tmp_path, 'calibration = "rig.toml"\n[cameras]\nurls = ["sim://rig?realtime=0&frames=10"]\n')
    result = CliRunner().invoke(main, ["run", str(session)])
    assert result.exit_code != 0 and "rig.toml" in result.output and "cam_0.matrix" in result.output, result.output


def test_the_documented_example_session_is_valid(tmp_path):
    import textwrap

    import livebridge.runtime.session as module

    doc = module.__doc__
    example = textwrap.dedent(doc[doc.index("::\n") + 3:doc.index("\nUnknown keys")])
    for name in ("calibration.toml", "basis.npz", "markers.toml", "head.toml"):
        (tmp_path / name).write_text("")
    session = load_session(_write(tmp_path, example))
    assert session.calibration == tmp_path / "calibration.toml" and session.servo_rig == tmp_path / "head.toml"
    assert len(session.camera_urls) == 2 and session.solver.mode == "split-compensated"
    assert session.recording.directory == tmp_path / "takes" and not session.recording.raw_frames


def test_the_labelling_timeout_defaults_to_10_s_and_0_means_wait(tmp_path):
    assert load_session(_write(tmp_path, '[cameras]\nurls = ["sim://rig"]\n')).labelling_timeout_s == 10.0
    path = _write(tmp_path, '[cameras]\nurls = ["sim://rig"]\n[runtime]\nlabelling_timeout_s = 0\n')
    assert load_session(path).labelling_timeout_s == 0.0
    with pytest.raises(InputError) as error:
        load_session(_write(tmp_path, '[cameras]\nurls = ["sim://rig"]\n[runtime]\nlabelling_timeout_s = -2\n'))
    assert error.value.field == "runtime.labelling_timeout_s"
