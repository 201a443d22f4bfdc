"""``livebridge retarget``: carry expressions between faces with thin-plate splines."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._attach import attach
from livebridge.cli._options import InputPath, OutputFile, force_option
from livebridge.cli.landmarks import MESH_TYPE, UNITS_TO_MM, load_mesh
from livebridge.retarget.landmarks import SHIPPED_LANDMARK_SETS

LANDMARKS_TYPE = InputPath(builtins=SHIPPED_LANDMARK_SETS)


@click.group("retarget")
def retarget() -> None:
    """Expression transfer between faces (thin-plate splines on facial landmarks)."""


@retarget.command("basis")
@click.option("--source", "source_spec", required=True, type=InputPath(builtins=("builtin",)),
              help="Source actuation basis (.npz) or 'builtin'.")
@click.option("--source-landmarks", required=True, type=LANDMARKS_TYPE,
              help="Landmarks on the source: builtin-22, ict-22 or a landmark file (.toml).")
@click.option("--target", "target_spec", required=True, type=MESH_TYPE,
              help="Target face: a mesh (.obj), a basis (.npz, its neutral) or 'builtin'.")
@click.option("--target-landmarks", required=True, type=LANDMARKS_TYPE,
              help="Landmarks on the target (same names as the source's): a landmark file or a shipped set.")
@click.option("--out", required=True, type=OutputFile(), help="Retargeted basis to write (.npz).")
@force_option
@click.option("--kernel", type=click.Choice(["r", "r2lnr2"]), default="r", show_default=True,
              help="TPS kernel: r (3D biharmonic) or r2lnr2 (the thesis's).")
@click.option("--units", type=click.Choice(sorted(UNITS_TO_MM)), default="mm", show_default=True,
              help="Units of an OBJ target (a basis is in mm).")
def basis(source_spec, source_landmarks, target_spec, target_landmarks, out: Path, force: bool, kernel: str,
          units: str) -> None:
    """Turn every element of a source basis into an element on a target mesh of any topology."""
    import numpy as np

    from livebridge.retarget.basis import retarget_basis
    from livebridge.retarget.landmarks import load_landmark_set

    if source_spec == "builtin":
        from livebridge.face.builtin import builtin_basis

        source = builtin_basis()
    else:
        from livebridge.face.basis import Basis

        source = Basis.load(source_spec)
    vertices, triangles = load_mesh(target_spec, units)
    on_source = load_landmark_set(source_landmarks).checked_on(len(source.triangles), source_landmarks)
    on_target = load_landmark_set(target_landmarks).checked_on(len(triangles), target_landmarks)
    result = retarget_basis(source, on_source, vertices, triangles, on_target, kernel)
    result.save(out)
    moving = int(np.count_nonzero(np.abs(result.elements).max(axis=(1, 2)) > 0))
    click.echo(f"wrote {out}: {result.n_muscles} elements ({moving} moving) on {result.n_vertices} vertices, "
               f"kernel {kernel}")



attach(retarget, (("livebridge.cli.retarget_scans", "scans"),))
