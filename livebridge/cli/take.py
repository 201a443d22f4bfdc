"""``livebridge take``: work on recorded take directories (``livebridge run`` / ``demo --record``)."""

from __future__ import annotations

import math
from pathlib import Path

import click


class _Rate(click.ParamType):
    """A frame rate in Hz: a finite number in (0, MAX_RATE] (click's FloatRange lets NaN and inf through)."""

    name = "rate"

    def convert(self, value, param, ctx) -> float:
        from livebridge.take.c3d import MAX_RATE

        try:
            rate = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not (math.isfinite(rate) and 0.0 < rate <= MAX_RATE):
            self.fail(f"{value!r} is not a frame rate in (0, {MAX_RATE:g}] Hz", param, ctx)
        return rate


@click.group()
def take() -> None:
    """Recorded take directories: exports."""


@take.command("export-c3d")
@click.argument("take_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The C3D file (default: TAKE_DIR/markers.c3d); its folder must exist.")
@click.option("--rate", type=_Rate(), default=None,
              help="Frames per second (default: the take's fps, else the rate of its timestamps).")
@click.option("--force", is_flag=True, help="Overwrite the C3D file when it exists.")
def export_c3d(take_dir: Path, out: Path | None, rate: float | None, force: bool) -> None:
    """Write the labelled markers of TAKE_DIR as C3D (mm; unseen markers are invalid points).

    A closed take already has markers.c3d; this exports one whose recording was cut short (a crash),
    up to its last flushed frame, or writes it again elsewhere (or in place with --force).
    """
    from livebridge.errors import InputError
    from livebridge.take.c3d import export_c3d as export

    try:
        written = export(take_dir, out, rate, force)
    except InputError as error:
        raise click.ClickException(str(error)) from None
    click.echo(f"wrote {written}")
