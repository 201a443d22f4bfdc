import click
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
    result = CliRunner().invoke(main, ["basis", "show", str(tmp_path / "missing.npz"), "--out", str(out)])
    assert result.exit_code != 0 and "missing.npz" in result.output


def test_a_command_module_that_fails_to_import_is_an_error():
    import pytest

    from livebridge.cli._attach import attach

    group = click.Group("test")
    with pytest.raises(ModuleNotFoundError, match="livebridge.cli.not_written"):
        attach(group, (("livebridge.cli.not_written", "command"),))
    assert not group.commands
