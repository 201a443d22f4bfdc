"""``livebridge basis check`` and ``livebridge basis refine``: validate and refine a basis on a training take."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import FiniteFloat, InputPath, OutputFile, force_option, refuse_overwrite
from livebridge.face import SHIPPED_MARKER_SETS

_MODES = click.Choice(["split-compensated", "split", "joint"])


def _inputs(basis_help: str, take_help: str):
    """The ``--basis``, ``--markers`` and ``--take`` options both commands read with :func:`_load`."""
    options = [
        click.option("--basis", "basis_path", required=True, type=InputPath(), help=basis_help),
        click.option("--markers", "markers_path", required=True, type=InputPath(builtins=SHIPPED_MARKER_SETS),
                     help=f"Marker set (.toml) or a shipped one ({', '.join(SHIPPED_MARKER_SETS)})."),
        click.option("--take", "take_path", required=True, type=InputPath(), help=take_help),
        force_option,
    ]

    def decorate(command):
        for option in reversed(options):
            command = option(command)
        return command

    return decorate


def _load(basis_path: Path, markers_path: Path, take_path: Path):
    """Basis, marker set and the take's displacements in the marker set's order (n_frames, n_markers, 3)."""
    import numpy as np

    from livebridge.errors import InputError
    from livebridge.face.basis import Basis
    from livebridge.face.shipped import load_marker_set
    from livebridge.take.npz import Take

    basis = Basis.load(basis_path)
    markers = load_marker_set(markers_path)
    markers.check_mesh(len(basis.triangles))
    take = Take.load(take_path)
    if take.displacements is None:
        raise InputError("the take has marker positions but no displacements in the model frame; "
                         "run it through the tracker first", take_path, "displacements")
    column = {name: i for i, name in enumerate(take.marker_names)}
    face_names = [name for name, role in zip(markers.names, markers.roles) if role == "face"]
    if not any(name in column for name in face_names):
        raise InputError(f"no marker of {markers_path} appears in the take", take_path, "marker_names")
    displacements = np.full((take.n_frames, len(markers), 3), np.nan)
    for j, name in enumerate(markers.names):
        if name in column:
            displacements[:, j] = take.displacements[:, column[name]]
    return basis, markers, take, displacements


@click.command()
@_inputs("Basis file (.npz).", "Training take (.npz) with marker displacements.")
@click.option("--out-dir", type=click.Path(file_okay=False, path_type=Path),
              help="Where the summary (.txt) and plot (.png) go (default: beside the take; made if missing).")
@click.option("--mode", type=_MODES, default="split-compensated", show_default=True, help="Region mode.")
def check(basis_path: Path, markers_path: Path, take_path: Path, force: bool, out_dir: Path | None,
          mode: str) -> None:
    """Validate a basis on a training take: per-muscle range excursions and misfit, per-region marker error."""
    from livebridge.solve.solver import SolverConfig
    from livebridge.solve.validate import check_basis, plot_report

    out_dir = out_dir or take_path.parent
    written = [out_dir / f"{take_path.stem}.basis-check.txt", out_dir / f"{take_path.stem}.basis-check.png"]
    _check_outputs(out_dir, written, force)
    basis, markers, take, displacements = _load(basis_path, markers_path, take_path)
    report = check_basis(basis, markers, displacements, take.t, SolverConfig(mode=mode), progress=True)
    out_dir.mkdir(exist_ok=True)
    summary = report.summary()
    written[0].write_text(summary + "\n")
    plot_report(report, written[1])
    click.echo(summary)
    click.echo(f"wrote {written[0]} and {written[1]}")


def _check_outputs(out_dir: Path, files: list[Path], force: bool) -> None:
    """``--out-dir`` can hold ``files``: a folder, or one to make in an existing folder; ``files`` exist only
    with --force."""
    if out_dir.exists() and not out_dir.is_dir():
        raise click.BadParameter(f"{out_dir}: is a file, not a folder", param_hint="--out-dir")
    if not out_dir.exists() and not out_dir.parent.is_dir():
        raise click.BadParameter(f"{out_dir}: the folder {str(out_dir.parent)!r} does not exist; create it first",
                                 param_hint="--out-dir")
    refuse_overwrite(files, force, "--out-dir")


@click.command()
@_inputs("Draft basis file (.npz).",
         "Training take (.npz) with marker displacements; every muscle should reach full contraction.")
@click.option("--out", required=True, type=OutputFile(), help="Refined basis (.npz).")
@click.option("--mode", type=_MODES, default="split-compensated", show_default=True, help="Region mode.")
@click.option("--anchor", type=click.Choice(["extremes", "norm"]), default="extremes", show_default=True,
              help="Pin each element's scale by the take's full contractions, or by the draft's norm.")
@click.option("--max-iterations", type=click.IntRange(1, 10_000), default=30, show_default=True)
@click.option("--tolerance", type=FiniteFloat(0, 1), default=1e-2, show_default=True,
              help="Stop when the total error falls by less than this fraction.")
def refine(basis_path: Path, markers_path: Path, take_path: Path, force: bool, out: Path, mode: str, anchor: str,
           max_iterations: int, tolerance: float) -> None:
    """Refine a basis on a training take (fixed-point re-fit at the markers, thin-plate densification)."""
    from livebridge.solve.refine import refine_basis
    from livebridge.solve.solver import SolverConfig

    basis, markers, _, displacements = _load(basis_path, markers_path, take_path)
    result = refine_basis(basis, markers, displacements, SolverConfig(mode=mode), anchor=anchor,
                          max_iterations=max_iterations, tolerance=tolerance, progress=True, log=click.echo)
    result.basis.save(out)
    scales = ", ".join(f"{name} {scale:.3f}" for name, scale in zip(basis.names, result.scales))
    click.echo(f"kept {result.iterations} re-fit(s); marker RMS {result.rms_mm[0]:.4f} -> {result.rms_mm[-1]:.4f} mm; "
               f"densified to the mesh within {result.densify_error_mm:.4f} mm at the markers")
    click.echo(f"element scale factors ({anchor}): {scales}")
    click.echo(f"wrote {out}")
