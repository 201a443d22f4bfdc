import errno
import json
import subprocess
import sys
import tempfile
import zipfile

import click
import pytest
from click.testing import CliRunner
from factories import random_basis

from livebridge import __version__
from livebridge.cli import main


def _all_commands(group, path=()):
    yield path, group
    if isinstance(group, click.Group):
        for name, command in group.commands.items():
            yield from _all_commands(command, path + (name,))


def test_version_and_help():
    runner = CliRunner()
    result = runner.invoke(main, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output
    result = runner.invoke(main, ["--help"])
    assert result.exit_code == 0
    for name in ("basis", "markers"):
        assert name in result.output


def test_help_on_every_level():
    runner = CliRunner()
    paths = list(_all_commands(main))
    assert ("basis", "show") in [p for p, _ in paths] and ("markers", "design") in [p for p, _ in paths]
    for path, _ in paths:
        result = runner.invoke(main, [*path, "--help"])
        assert result.exit_code == 0, (path, result.output)
        assert "Usage:" in result.output


def test_basis_show_renders_a_png(tmp_path, rng):
    basis = random_basis(rng, n_vertices=100, n_muscles=3)
    basis.save(tmp_path / "b.npz")
    out = tmp_path / "face.png"
    result = CliRunner().invoke(main, ["basis", "show", str(tmp_path / "b.npz"), "--out", str(out), "--dpi", "40"])
    assert result.exit_code == 0, result.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 1000
    missing = ["basis", "show", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x.png")]
    result = CliRunner().invoke(main, missing)
    assert result.exit_code != 0 and "missing.npz" in result.output


def test_a_command_module_that_fails_to_import_is_an_error():
    from livebridge.cli._attach import attach

    group = click.Group("test")
    with pytest.raises(ModuleNotFoundError, match="livebridge.cli.not_written"):
        attach(group, (("livebridge.cli.not_written", "command"),))
    assert not group.commands


def _error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("Error:")]


@pytest.fixture
def crash_dir(tmp_path, monkeypatch):
    folder = tmp_path / "crashes"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def _failing_render(error):
    def render_basis(*args, **kwargs):
        raise error
    return render_basis


def test_a_bug_prints_one_line_and_writes_the_traceback_to_a_file(tmp_path, rng, monkeypatch, crash_dir):
    import livebridge.cli.basis_show as basis_show

    random_basis(rng, n_vertices=25, n_muscles=2).save(tmp_path / "b.npz")
    monkeypatch.setattr(basis_show, "render_basis", _failing_render(RuntimeError("boom\nsecond line")))
    result = CliRunner().invoke(main, ["basis", "show", str(tmp_path / "b.npz"), "--out", str(tmp_path / "f.png")])
    assert result.exit_code == 1 and "Traceback" not in result.output and "Aborted" not in result.output
    (line,) = _error_lines(result.output)
    reports = list(crash_dir.iterdir())
    assert len(reports) == 1
    assert line == f"Error: internal error (RuntimeError: boom second line); full traceback written to {reports[0]}"
    text = reports[0].read_text()
    assert "Traceback" in text and "RuntimeError: boom" in text and "render_basis" in text


@pytest.mark.parametrize("error,words", [
    (PermissionError(errno.EACCES, "Permission denied", "/x/face.png"), "/x/face.png: permission denied"),
    (IsADirectoryError(errno.EISDIR, "Is a directory", "/x/out"), "/x/out: is a directory"),
    (FileNotFoundError(errno.ENOENT, "No such file", "/x/y"), "/x/y: file not found"),
    (OSError(errno.EADDRINUSE, "Address already in use"), "address already in use"),
    (OSError(errno.EADDRNOTAVAIL, "Cannot assign requested address"), "address not available"),
    (UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"), "not UTF-8 text"),
    (zipfile.BadZipFile("File is not a zip file"), "not a zip (.npz) file"),
    (json.JSONDecodeError("Expecting value", "{", 1), "not valid JSON"),
])
def test_errors_a_user_causes_print_one_line_without_a_traceback_file(tmp_path, rng, monkeypatch, crash_dir,
                                                                      error, words):
    import livebridge.cli.basis_show as basis_show

    random_basis(rng, n_vertices=25, n_muscles=2).save(tmp_path / "b.npz")
    monkeypatch.setattr(basis_show, "render_basis", _failing_render(error))
    result = CliRunner().invoke(main, ["basis", "show", str(tmp_path / "b.npz"), "--out", str(tmp_path / "f.png")])
    assert result.exit_code == 1 and "Traceback" not in result.output
    (line,) = _error_lines(result.output)
    assert words in line and not list(crash_dir.iterdir())


def test_ctrl_c_before_the_pipeline_runs_exits_130_without_aborted(tmp_path, rng, monkeypatch, crash_dir):
    import livebridge.cli.basis_show as basis_show

    random_basis(rng, n_vertices=25, n_muscles=2).save(tmp_path / "b.npz")
    monkeypatch.setattr(basis_show, "render_basis", _failing_render(KeyboardInterrupt()))
    result = CliRunner().invoke(main, ["basis", "show", str(tmp_path / "b.npz"), "--out", str(tmp_path / "f.png")])
    assert result.exit_code == 130 and "Aborted" not in result.output and "Traceback" not in result.output
    assert not _error_lines(result.output) and not list(crash_dir.iterdir())


def test_output_read_by_a_command_that_stops_reading_ends_quietly_with_141(tmp_path):
    """`livebridge ... | head -1`: the reader gone, the command exits as Unix tools do (128 + SIGPIPE), without an
    error line (it printed "Error: Broken pipe")."""
    reader_gone = subprocess.Popen([sys.executable, "-m", "livebridge", "landmarks", "template", "--out",
                                    str(tmp_path / "t.pptpl")], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    reader_gone.stdout.close()  # before the interpreter has started: its first line meets a closed pipe
    _, stderr = reader_gone.communicate(timeout=120)
    assert reader_gone.returncode == 141 and b"Error" not in stderr and b"Traceback" not in stderr, stderr
    assert (tmp_path / "t.pptpl").exists()  # the work was done; only its report had no reader


def test_python_dash_m_livebridge_runs_the_same_command_line(tmp_path):
    missing = tmp_path / "nothing.npz"
    result = subprocess.run([sys.executable, "-m", "livebridge", "basis", "show", str(missing), "--out",
                             str(tmp_path / "f.png")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "Traceback" not in result.stderr  # click's exit code for a bad argument
    assert _error_lines(result.stderr) == [f"Error: Invalid value for 'BASIS': {missing}: file not found"]


def _hold_port():
    import socket

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    return busy


def _no_set_up(*args, **kwargs):
    raise AssertionError("the pipeline was set up although its render port is taken")


@pytest.mark.parametrize("command", ["demo", "run"])
def test_a_render_port_in_use_is_refused_before_the_set_up(tmp_path, monkeypatch, crash_dir, command):
    import livebridge.runtime.build as build

    monkeypatch.setattr(build, "build_pipeline", _no_set_up)
    with _hold_port() as busy:
        port = busy.getsockname()[1]
        session = tmp_path / "session.toml"
        session.write_text(f'[cameras]\nurls = ["sim://rig?realtime=0"]\n[outputs.render]\nport = {port}\n')
        args = ["demo", "--port", str(port)] if command == "demo" else ["run", str(session)]
        result = CliRunner().invoke(main, args)
    (line,) = _error_lines(result.output)
    assert result.exit_code != 0 and f"127.0.0.1:{port}" in line and "address already in use" in line
    assert ("--port" if command == "demo" else "outputs.render.port") in line
    assert not list(crash_dir.iterdir())


def test_a_render_port_taken_after_the_check_is_still_one_error_line(tmp_path, monkeypatch, crash_dir):
    """Another program may take the port between the early check and the server's bind (a race)."""
    import livebridge.cli.runtime as runtime_cli

    monkeypatch.setattr(runtime_cli, "render_bind_problem", lambda host, port: None)
    with _hold_port() as busy:
        port = busy.getsockname()[1]
        result = CliRunner().invoke(main, ["demo", "--port", str(port), "--no-servo", "--unpaced", "--frames", "1",
                                           "--size", "160x100"])
    (line,) = _error_lines(result.output)
    assert result.exit_code == 1 and f"render server 127.0.0.1:{port}" in line and "address already in use" in line
    assert "Traceback" not in result.output and not list(crash_dir.iterdir())


def test_allow_remote_lets_the_render_server_listen_on_every_interface(monkeypatch, crash_dir):
    import livebridge.runtime.demo as demo

    seen = {}

    def record(**options):
        seen.update(options)
        raise KeyboardInterrupt  # stop before anything is built

    monkeypatch.setattr(demo, "build_demo", record)
    result = CliRunner().invoke(main, ["demo", "--host", "0.0.0.0", "--allow-remote", "--port", "0"])
    assert result.exit_code == 130 and seen["host"] == "0.0.0.0", result.output


def test_the_demo_camera_options_are_bounded_as_the_simulated_rig():
    from livebridge.cli.runtime import DEMO_FPS, DEMO_SIZE
    from livebridge.simulators.rig import _CONFIG_RANGES, SIZE_RANGE

    assert DEMO_SIZE == SIZE_RANGE and DEMO_FPS == _CONFIG_RANGES["fps"][:2]


def test_an_id_range_is_bounded_before_it_is_expanded():
    from livebridge.devices.url import parse_ranges
    from livebridge.errors import InputError

    assert parse_ranges("1-3, 7", 0, 252) == [1, 2, 3, 7]
    for text in ("1-999999999", "0-99999999999999999999", "3-1", "-1", "1,1", "", "a-b"):
        with pytest.raises(InputError):
            parse_ranges(text, 0, 252)
