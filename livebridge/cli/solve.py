"""``livebridge solve``: contractions from a file of labelled marker trajectories (offline)."""

from __future__ import annotations

import sys
from pathlib import Path

import click
import numpy as np

from livebridge.cli._options import InputPath, OutputFile, force_option, parse_correspond, refuse_overwrite
from livebridge.cli.markers import BASIS_HELP, BASIS_TYPE, NEUTRAL_FRAME_HELP, NeutralFrame, load_basis
from livebridge.face import SHIPPED_MARKER_SETS


def rms_path(out: Path) -> Path:
    """Where the per-region marker RMS goes: next to the contractions, ``NAME.rms.csv``."""
    return out.with_name(out.stem + ".rms.csv")


def plot_path(out: Path) -> Path:
    """Where the contraction curves go: ``NAME.png``."""
    return out.with_suffix(".png")


def write_contractions(path: Path, t: np.ndarray, names, contractions: np.ndarray) -> None:
    """CSV: ``time`` (s) then one column per muscle, header naming them."""
    header = ",".join(["time", *names])
    np.savetxt(path, np.column_stack([t, contractions]), delimiter=",", header=header, comments="", fmt="%.10g")


def write_rms(path: Path, t: np.ndarray, rms: np.ndarray) -> None:
    """CSV: ``time``, ``upper_rms_mm``, ``lower_rms_mm`` (empty where a region had no marker)."""
    with path.open("w") as stream:
        stream.write("time,upper_rms_mm,lower_rms_mm\n")
        for time, row in zip(t, rms):
            stream.write(",".join([f"{time:.10g}"] + [f"{v:.6g}" if np.isfinite(v) else "" for v in row]) + "\n")


def plot_contractions(path: Path, t: np.ndarray, names, contractions: np.ndarray) -> None:
    """PNG of every muscle's contraction over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(12, 6))
    for k, name in enumerate(names):
        axes.plot(t, contractions[:, k], label=name, linewidth=1)
    axes.set_xlabel("time (s)")
    axes.set_ylabel("contraction")
    axes.legend(fontsize=7, ncol=2, loc="upper right")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


@click.command("solve")
@click.argument("marker_file", type=InputPath())
@click.option("--basis", "basis_spec", type=BASIS_TYPE, default="builtin", show_default=True, help=BASIS_HELP)
@click.option("--markers", "markers_spec", required=True,
              help="Marker set whose names match the file's markers (.toml, or a shipped set: builtin, builtin-68, "
              "ict-68), or 'auto' to place the file's layout on the basis automatically.")
@click.option("--neutral-frame", type=NeutralFrame(), default="auto", show_default=True, help=NEUTRAL_FRAME_HELP)
@click.option("--mode", type=click.Choice(["split-compensated", "split", "joint"]), default="split-compensated",
              show_default=True, help="Solver region mode.")
@click.option("--units", type=click.Choice(["mm", "cm", "m"]), default=None,
              help="Unit of a file that does not say (default: the file's own, else mm).")
@click.option("--correspond", multiple=True, metavar="NAME=VERTEX",
              help="With --markers auto: a marker at a basis vertex (>= 4 of them replace the shape fit).")
@click.option("--out", required=True, type=OutputFile(),
              help="Contractions CSV (time + one column per muscle). Also written: NAME.rms.csv (per-region "
              "marker RMS per frame) and NAME.png (the curves).")
@click.option("--take", "take_out", type=OutputFile(), default=None,
              help="Also write the take (.npz, model-frame displacements) for `basis check` / `basis refine`.")
@click.option("--markers-out", type=OutputFile(), default=None,
              help="Also write the marker set solved with (placed on the surface; with 'auto' the layout found).")
@force_option
def solve(marker_file: Path, basis_spec: str, markers_spec: str, neutral_frame: str | int, mode: str, units: str | None,
          correspond: tuple[str, ...], out: Path, take_out: Path | None, markers_out: Path | None,
          force: bool) -> None:
    """Solve contractions from MARKER_FILE (labelled marker trajectories) with the live path's solver."""
    from livebridge.errors import InputError
    from livebridge.face.shipped import load_marker_set
    from livebridge.solve.offline import (
        match_markers,
        neutral_for_set,
        parse_neutral,
        place_from_positions,
        solve_positions,
    )
    from livebridge.solve.solver import SolverConfig
    from livebridge.take.trajectories import read_trajectories

    refuse_overwrite([rms_path(out), plot_path(out)], force, "--out")
    pairs = parse_correspond(correspond)
    if pairs and markers_spec != "auto":
        raise click.BadParameter("only with --markers auto", param_hint="--correspond")
    if markers_spec not in ("auto", *SHIPPED_MARKER_SETS) and not Path(markers_spec).is_file():
        raise InputError("marker set not found", markers_spec, "--markers")
    basis = load_basis(basis_spec)
    trajectories = read_trajectories(marker_file, units)
    frame = parse_neutral(neutral_frame, len(trajectories.t))
    if markers_spec == "auto":
        placement, choice = place_from_positions(trajectories.points, trajectories.names, basis, frame, pairs)
        markers, positions = placement.markers, trajectories.points
        click.echo(f"placed {len(markers)} markers ({placement.how}); surface RMS {placement.rms_mm:.2f} mm; "
                   f"head markers: {', '.join(n for n, r in zip(markers.names, markers.roles) if r == 'head')}")
    else:
        markers = load_marker_set(markers_spec)
        positions = match_markers(trajectories, markers)
        choice = neutral_for_set(positions, basis, markers, frame)
    click.echo(choice.reason)
    result = solve_positions(trajectories.t, positions, basis, markers, choice, SolverConfig(mode=mode),
                             progress=sys.stderr.isatty())
    contractions = result.solution.contractions
    write_contractions(out, result.t, basis.names, contractions)
    write_rms(rms_path(out), result.t, result.solution.rms_error_mm)
    plot_contractions(plot_path(out), result.t, basis.names, contractions)
    click.echo(f"wrote {out} ({len(result.t)} frames, {len(basis.names)} muscles), {rms_path(out)}, {plot_path(out)}")
    rms = result.solution.rms_error_mm
    click.echo(f"marker RMS (median over frames): upper {np.nanmedian(rms[:, 0]):.3f} mm, "
               f"lower {np.nanmedian(rms[:, 1]):.3f} mm; alignment RMS {result.alignment.rms_mm:.3f} mm")
    if take_out is not None:
        from livebridge.take.npz import Take

        Take(t=result.t, marker_names=markers.names, displacements=result.displacements, positions=positions,
             head2world=result.head2world, fps=trajectories.rate).save(take_out)
        click.echo(f"wrote {take_out}")
    if markers_out is not None:
        result.markers.save(markers_out)
        click.echo(f"wrote {markers_out}")
