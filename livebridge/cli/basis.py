"""``livebridge basis``: import, inspect, validate and refine actuation bases."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._attach import attach
from livebridge.cli._options import InputPath, OutputFile, force_option


@click.group()
def basis() -> None:
    """Actuation bases: import from meshes, show, check, refine."""


@basis.command("import")
@click.argument("manifest")
@click.option("--shapes", type=InputPath("any"),
              help="Folder of mesh files or .npz of named deltas (default: the manifest's folder).")
@click.option("--out", required=True, type=OutputFile(), help="Basis file to write (.npz).")
@force_option
def import_(manifest: str, shapes: Path | None, out: Path, force: bool) -> None:
    """Build a basis from MANIFEST (a TOML file, or a shipped name such as choe-ko-ict)."""
    from livebridge.face.basis_import import import_basis
    from livebridge.face.muscle_place import side_warnings

    result = import_basis(manifest, shapes)
    result.save(out)
    click.echo(f"wrote {out}: {result.n_muscles} muscles, {result.n_vertices} vertices, "
               f"{len(result.triangles)} triangles")
    for warning in side_warnings(result.muscles, result.elements, result.neutral):
        click.echo(f"warning: {warning}")


attach(basis, (
    ("livebridge.cli.basis_show", "show"),
    ("livebridge.cli.basis_quality", "check"),
    ("livebridge.cli.basis_quality", "refine"),
))
