"""``livebridge take``: recorded take directories (``livebridge run`` / ``demo --record``) and marker files of
other systems (C3D, TRC, CSV): export, inspect, convert."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import FiniteFloat, InputPath, OutputFile, force_option
from livebridge.take.c3d import MAX_RATE


@click.group()
def take() -> None:
    """Recorded take directories and marker files: export, show, convert."""


@take.command("export-c3d")
@click.argument("take_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The C3D file (default: TAKE_DIR/markers.c3d); its folder must exist.")
@click.option("--rate", type=FiniteFloat(0.0, MAX_RATE, low_open=True), default=None,
              help="Frames per second (default: the take's fps, else the rate of its timestamps).")
@click.option("--force", is_flag=True, help="Overwrite the C3D file when it exists.")
def export_c3d(take_dir: Path, out: Path | None, rate: float | None, force: bool) -> None:
    """Write the labelled markers of TAKE_DIR as C3D (mm; unseen markers are invalid points).

    A closed take already has markers.c3d; this exports one whose recording was cut short (a crash),
    up to its last flushed frame, or writes it again elsewhere (or in place with --force).
    """
    from livebridge.take.c3d import export_c3d as export

    written = export(take_dir, out, rate, force)
    click.echo(f"wrote {written}")


_UNITS = click.Choice(["mm", "cm", "m"])
_UNITS_HELP = "The unit of a file that does not say (CSV; default mm)."
_RATE_HELP = "Frames per second of a file with frame numbers but no times."


@take.command("show")
@click.argument("file", type=InputPath("file"))
@click.option("--units", type=_UNITS, default=None, help=_UNITS_HELP)
@click.option("--rate", type=FiniteFloat(0.0, MAX_RATE, low_open=True), default=None, help=_RATE_HELP)
def show(file: Path, units: str | None, rate: float | None) -> None:
    """Print what a marker file (C3D, TRC, CSV, .npz take) holds: markers, frames, rate, unit, and the
    fraction of frames each marker was seen in."""
    from livebridge.take.trajectories import read_trajectories

    trajectories = read_trajectories(file, units, rate)
    for line in describe(trajectories):
        click.echo(line)


def describe(trajectories) -> list[str]:
    """Lines saying what ``trajectories`` hold (for ``take show``)."""
    import numpy as np

    n_frames, names = len(trajectories.t), trajectories.names
    rate = trajectories.rate
    duration = float(trajectories.t[-1]) if n_frames else 0.0
    unit = trajectories.unit or "mm (assumed: the file does not say; give --units)"
    seen = trajectories.seen
    lines = [f"file: {trajectories.source}",
             f"frames: {n_frames} over {duration:.3f} s at {f'{rate:.6g} Hz' if rate else 'unknown rate'}",
             f"unit: {unit}",
             f"markers: {len(names)}, seen in {float(np.mean(seen)) if len(seen) else 0.0:.1%} of frames on average"]
    width = max(map(len, names)) + 8
    entries = [f"{name} {fraction:.1%}".ljust(width) for name, fraction in zip(names, seen)]
    per_line = max(1, 96 // width)  # several markers a line: a 68-landmark file stays short
    lines += ["  " + "".join(entries[k:k + per_line]).rstrip() for k in range(0, len(entries), per_line)]
    return lines


@take.command("convert")
@force_option
@click.argument("source", metavar="IN", type=InputPath("file"))
@click.argument("out", metavar="OUT", type=OutputFile())
@click.option("--units", type=_UNITS, default=None, help=_UNITS_HELP)
@click.option("--rate", type=FiniteFloat(0.0, MAX_RATE, low_open=True), default=None, help=_RATE_HELP)
def convert(source: Path, out: Path, units: str | None, rate: float | None, force: bool) -> None:
    """Convert a marker file (C3D, TRC, CSV, .npz take) to C3D, TRC or CSV (by OUT's suffix), in mm.

    C3D stores one frame per sample period: frames missing from IN's times are written as invalid points.
    """
    from livebridge.take.trajectories import WRITERS, read_trajectories, write_trajectories

    if out.suffix.lower() not in WRITERS:
        raise click.BadParameter(f"{out}: cannot write {out.suffix!r} files; known: {', '.join(sorted(WRITERS))}",
                                 param_hint="OUT")
    if out.resolve() == source.resolve():
        raise click.BadParameter(f"{out} is the input file; write elsewhere", param_hint="OUT")
    trajectories = read_trajectories(source, units, rate)
    write_trajectories(out, trajectories)
    click.echo(f"wrote {out} ({len(trajectories.names)} markers, {len(trajectories.t)} frames)")
