"""``livebridge markers``: design and inspect marker layouts."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from livebridge.cli._options import FiniteFloat, InputPath, OutputFile, force_option, parse_correspond
from livebridge.face.rig_visibility import MAX_VIEW_DEG, VIEW_MARGIN_DEG

BASIS_HELP = "Basis file (.npz, from `livebridge basis import`) or 'builtin' (the procedural face)."
BASIS_TYPE = InputPath(builtins=("builtin",))
MAX_MARKERS = 1000
"""The most markers a layout option asks for (a face carries at most a few hundred)."""


class NeutralFrame(click.ParamType):
    """``--neutral-frame``: ``auto`` or a frame number from 0 (whether the take has it is known once read)."""

    name = "FRAME|auto"

    def convert(self, value, param, ctx) -> str | int:
        if value == "auto" or isinstance(value, int):
            return value
        text = str(value).strip()
        if not text.isdigit():
            self.fail(f"expected 'auto' or a frame number from 0, got {value!r}", param, ctx)
        return int(text)


NEUTRAL_FRAME_HELP = ("Frame number (from 0) of the neutral face, or 'auto' for the frame closest to rest "
                      "(see the README: how it chooses).")


def load_basis(spec: str):
    """The basis named by a command-line value: a ``.npz`` file or ``builtin``.

    Raises
    ------
    InputError
        Naming the file and what is wrong.
    """
    from livebridge.face.basis import Basis

    if spec == "builtin":
        from livebridge.face.builtin import builtin_basis

        return builtin_basis()
    return Basis.load(spec)


def rig_options(command):
    """The options that describe the camera rig a layout is for (``--cameras`` and how it must see markers)."""
    options = [
        click.option("--cameras", "calibration", type=InputPath(),
                     default=None, help="Calibration file (calibration.toml) of the rig the layout is for: markers "
                     "go only where enough of its cameras see them. The face is placed where the cameras' optical "
                     "axes meet, facing them."),
        click.option("--min-views", default=3, show_default=True, type=click.IntRange(1, 64),
                     help="With --cameras: cameras that must see every marker (2 to triangulate; each one more is a "
                     "spare view when a marker is occluded in another)."),
        click.option("--max-view-deg", default=MAX_VIEW_DEG, show_default=True,
                     type=FiniteFloat(0, 90, low_open=True),
                     help="With --cameras: largest angle between a marker's normal and a camera that still finds it."),
        click.option("--view-margin", default=VIEW_MARGIN_DEG, show_default=True, type=FiniteFloat(0, 90),
                     help="With --cameras: degrees kept spare for head motion (taken off --max-view-deg at neutral)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def load_rig(calibration: Path | None, min_views: int, max_view_deg: float, view_margin: float):
    """The :class:`~livebridge.face.rig_visibility.RigVisibility` the rig options ask for (None without ``--cameras``).

    Raises
    ------
    click.UsageError
        When a rig option is given without ``--cameras``.
    InputError
        Naming the file and what is wrong.
    """
    from livebridge.calibration.calibfile import load_calibration
    from livebridge.face.rig_visibility import RigVisibility

    if calibration is None:
        context = click.get_current_context()
        given = [f"--{name.replace('_', '-')}" for name in ("min_views", "max_view_deg", "view_margin")
                 if context.get_parameter_source(name) is click.core.ParameterSource.COMMANDLINE]
        if given:
            raise click.UsageError(f"--cameras is needed by {', '.join(given)}")
        return None
    return RigVisibility(load_calibration(calibration), min_views, max_view_deg, view_margin)


def describe_rig(rig) -> str:
    """Where the face is assumed to be in the rig, and what counts as a view, for the terminal."""
    from livebridge.face.rig_visibility import optical_axes_meet

    centre = optical_axes_meet(rig.cameras)
    distances = ", ".join(f"{camera.name} {np.linalg.norm(camera.center - centre):.0f}"
                          for camera in rig.cameras.cameras)
    return (f"face centre placed at ({centre[0]:.0f}, {centre[1]:.0f}, {centre[2]:.0f}) mm in the calibration's world "
            f"frame, facing the cameras (distances in mm: {distances})\nmarkers must be {rig.describe()}")


def format_report(report: dict, names) -> str:
    """Human-readable lines of :func:`livebridge.face.layout.layout_report`."""
    lines = [
        f"face markers: {report['n_face']}   head markers: {report['n_head']}",
        f"condition number, whole face: {report['condition_whole']:.1f}"
        f"   (worst with one marker lost: {report['condition_worst_loss_whole']:.1f})",
    ]
    for region, figures in report["regions"].items():
        lines.append(f"condition number, {region} face ({figures['n_markers']} markers, {figures['n_muscles']} "
                     f"muscles): {figures['condition']:.1f}   (worst with one marker lost: "
                     f"{figures['condition_worst_loss']:.1f})")
    lines.append("observers per muscle:")
    width = max(len(name) for name in names)
    lines += [f"  {name:<{width}}  {report['observers'][name]}" for name in names if name in report["observers"]]
    if "head_spread_mm" in report:
        lines.append(f"head markers: spread {report['head_spread_mm']:.1f} mm (smallest axis), "
                     f"largest motion with any element {report['head_motion_mm']:.2f} mm")
    if "views" in report:
        counts = np.bincount(list(report["views"].values()))
        histogram = ", ".join(f"{views} cameras: {n}" for views, n in reversed(list(enumerate(counts))) if n)
        lines.append(f"markers by the number of cameras that see them: {histogram}")
    return "\n".join(lines)


@click.group()
def markers() -> None:
    """Marker layouts: design a layout for a basis, report its observability."""


@markers.command("design")
@click.option("--basis", "basis_spec", type=BASIS_TYPE, default="builtin", show_default=True, help=BASIS_HELP)
@click.option("--count", default=64, show_default=True, type=click.IntRange(1, MAX_MARKERS),
              help="Number of face markers.")
@click.option("--min-spacing", type=FiniteFloat(0, 1000), default=None,
              help="Minimum distance between face markers in mm (default: from the face area and the count).")
@click.option("--head", "n_head", default=5, show_default=True, type=click.IntRange(0, MAX_MARKERS),
              help="Number of rigid head-rig markers (>= 4 recommended).")
@click.option("--min-observers", default=3, show_default=True, type=click.IntRange(1, MAX_MARKERS),
              help="Markers that must observe every muscle.")
@click.option("--out", required=True, type=OutputFile(), help="Marker file (.toml).")
@force_option
@click.option("--baseline/--no-baseline", default=True, show_default=True,
              help="Also print the farthest-point-sampling layout's figures for comparison.")
@rig_options
def design(basis_spec: str, count: int, min_spacing: float | None, n_head: int, min_observers: int, out: Path,
           force: bool, baseline: bool, calibration: Path | None, min_views: int, max_view_deg: float,
           view_margin: float) -> None:
    """Design a marker layout (greedy D-optimal per region, spacing-constrained) and print its figures.

    With --cameras, the layout is for that rig: face and head markers only where at least --min-views of its
    cameras see them well at the neutral pose.
    """
    from livebridge.face.layout import default_spacing, design_markers, farthest_point_markers, layout_report

    basis = load_basis(basis_spec)
    rig = load_rig(calibration, min_views, max_view_deg, view_margin)
    if rig is not None:
        click.echo(describe_rig(rig))
    spacing = default_spacing(basis, count, rig) if min_spacing is None else min_spacing
    layout = design_markers(basis, count, spacing, n_head=n_head, min_observers=min_observers, rig=rig)
    layout.save(out)
    click.echo(f"wrote {out}: {len(layout)} markers on {basis_spec} (min spacing {spacing:.1f} mm)")
    click.echo(format_report(layout_report(basis, layout, rig), basis.names))
    if baseline:
        report = layout_report(basis, farthest_point_markers(basis, count, seed=0))
        regions = ", ".join(f"{r} {f['condition']:.1f}" for r, f in report["regions"].items())
        click.echo(f"farthest-point sampling, same count: whole face {report['condition_whole']:.1f}, {regions}, "
                   f"fewest observers {report['min_observers']}")


@markers.command("report")
@click.argument("layout_file", type=InputPath())
@click.option("--basis", "basis_spec", type=BASIS_TYPE, default="builtin", show_default=True, help=BASIS_HELP)
@rig_options
def report(layout_file: Path, basis_spec: str, calibration: Path | None, min_views: int, max_view_deg: float,
           view_margin: float) -> None:
    """Print the observability figures of an existing LAYOUT_FILE on a basis (with --cameras: views per marker)."""
    from livebridge.errors import InputError
    from livebridge.face.layout import layout_report
    from livebridge.face.markers import MarkerSet

    basis = load_basis(basis_spec)
    rig = load_rig(calibration, min_views, max_view_deg, view_margin)
    layout = MarkerSet.load(layout_file)
    try:
        layout.check_mesh(len(basis.triangles))
    except InputError as error:
        raise InputError(error.message, layout_file, error.field) from None
    if rig is not None:
        click.echo(describe_rig(rig))
    figures = layout_report(basis, layout, rig)
    click.echo(format_report(figures, basis.names))
    if rig is not None:
        short = [name for name, views in figures["views"].items() if views < rig.min_views]
        if short:
            click.echo(f"seen by fewer than {rig.min_views} cameras: {', '.join(short)}")


@markers.command("place")
@click.argument("marker_file", type=InputPath())
@click.option("--basis", "basis_spec", type=BASIS_TYPE, default="builtin", show_default=True, help=BASIS_HELP)
@click.option("--neutral-frame", type=NeutralFrame(), default="auto", show_default=True, help=NEUTRAL_FRAME_HELP)
@click.option("--correspond", multiple=True, metavar="NAME=VERTEX",
              help="A marker at a basis vertex; >= 4 of them give the rough alignment instead of the shape fit.")
@click.option("--units", type=click.Choice(["mm", "cm", "m"]), default=None,
              help="Unit of a file that does not say (default: the file's own, else mm).")
@click.option("--out", required=True, type=OutputFile(), help="Marker set (.toml).")
@force_option
def place(marker_file: Path, basis_spec: str, neutral_frame: str | int, correspond: tuple[str, ...], units: str | None,
          out: Path, force: bool) -> None:
    """Place the markers of MARKER_FILE (any layout) on the basis: surface sites, regions, head markers."""
    from livebridge.solve.offline import parse_neutral, place_from_positions
    from livebridge.take.trajectories import read_trajectories

    pairs = parse_correspond(correspond)
    basis = load_basis(basis_spec)
    trajectories = read_trajectories(marker_file, units)
    frame = parse_neutral(neutral_frame, len(trajectories.t))
    placement, choice = place_from_positions(trajectories.points, trajectories.names, basis, frame, pairs)
    placement.markers.save(out)
    click.echo(choice.reason)
    click.echo(f"rough alignment: {placement.how}")
    layout = placement.markers
    click.echo(f"wrote {out}: {len(layout)} markers, surface RMS {placement.rms_mm:.2f} mm; upper "
               f"{layout.regions.count('upper')}, lower {layout.regions.count('lower')}")
    head = [f"{name} ({d:.2f} mm)" for name, role, d in zip(layout.names, layout.roles, placement.deviation_mm)
            if role == "head"]
    click.echo("head markers (rigid with the head over the take; 95th-percentile deviation): "
               f"{', '.join(head) or 'none'}")
