"""``livebridge take``: work on recorded take directories (``livebridge run`` / ``demo --record``)."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import FiniteFloat
from livebridge.take.c3d import MAX_RATE


@click.group()
def take() -> None:
    """Recorded take directories: exports."""


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
