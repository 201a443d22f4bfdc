"""``livebridge basis``: import, inspect, validate and refine actuation bases."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._attach import attach
from livebridge.cli._options import InputPath, OutputFile, force_option


@click.group()
def basis() -> None:
    """Actuation bases: import from meshes, export as meshes, show, check, refine."""


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


@basis.command("export")
@click.argument("basis_file", metavar="BASIS", type=InputPath(builtins=("builtin",)))
@click.option("--out", "folder", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder to write neutral.obj, one OBJ per muscle and basis.toml into (created if need be).")
@click.option("--like", type=InputPath(), default=None,
              help="The OBJ the basis lives on (e.g. the target of `retarget basis`): every file keeps its "
                   "texture coordinates, polygons and materials.")
@click.option("--units", type=click.Choice(["mm", "cm", "m"]), default="mm", show_default=True,
              help="Units to write (and of --like).")
@force_option
def export(basis_file, folder: Path, like: Path | None, units: str, force: bool) -> None:
    """Write BASIS (a basis file or 'builtin') as OBJ meshes: the neutral and one blendshape per muscle, with the
    manifest `basis import` reads them back by."""
    from livebridge.cli.markers import load_basis
    from livebridge.errors import InputError
    from livebridge.face.basis_export import export_basis, export_files

    if like is not None and like.suffix.lower() != ".obj":
        raise InputError(f"not an OBJ: the layout kept is an OBJ's (texture coordinates, polygons, materials), and "
                         f"a {like.suffix or 'suffix-less'} file has none; leave --like out to write triangles",
                         like, "--like")
    loaded = load_basis(basis_file)
    there = [path.name for path in export_files(loaded, folder) if path.exists()]
    if there and not force:
        raise InputError(f"{', '.join(there[:3])}{' ...' if len(there) > 3 else ''} already there; add --force to "
                         "overwrite", folder)
    files = export_basis(loaded, folder, units, like)
    click.echo(f"wrote {len(files) - 1} OBJ files ({units}{', laid out as ' + str(like) if like else ', triangles'}) "
               f"and {files[-1].name} into {folder}: `livebridge basis import {files[-1]} --out BASIS.npz` reads "
               "them back")


attach(basis, (
    ("livebridge.cli.basis_show", "show"),
    ("livebridge.cli.basis_quality", "check"),
    ("livebridge.cli.basis_quality", "refine"),
))
