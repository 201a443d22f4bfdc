"""``livebridge markers``: design and inspect marker layouts."""

from __future__ import annotations

from pathlib import Path

import click

BASIS_HELP = "Basis file (.npz), 'builtin' (the procedural face) or 'ict' (ICT-FaceKit from ../shared/data)."


def load_basis(spec: str):
    """The basis named by a command-line value: a ``.npz`` file, ``builtin`` or ``ict``.

    Raises
    ------
    click.ClickException
        Naming the file and what is wrong.
    """
    from livebridge.errors import InputError
    from livebridge.face.basis import Basis

    if spec == "builtin":
        from livebridge.face.builtin import builtin_basis

        return builtin_basis()
    if spec == "ict":
        from livebridge.face.reference import ict_basis

        basis = ict_basis()
        if basis is None:
            raise click.ClickException("ict: the reference data ../shared/data/ict-facekit is not on this machine")
        return basis
    try:
        return Basis.load(spec)
    except InputError as error:
        raise click.ClickException(str(error)) from None


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
    return "\n".join(lines)


@click.group()
def markers() -> None:
    """Marker layouts: design a layout for a basis, report its observability."""


@markers.command("design")
@click.option("--basis", "basis_spec", default="builtin", show_default=True, help=BASIS_HELP)
@click.option("--count", default=64, show_default=True, type=click.IntRange(1), help="Number of face markers.")
@click.option("--min-spacing", type=click.FloatRange(0), default=None,
              help="Minimum distance between face markers in mm (default: from the face area and the count).")
@click.option("--head", "n_head", default=5, show_default=True, type=click.IntRange(0),
              help="Number of rigid head-rig markers (>= 4 recommended).")
@click.option("--min-observers", default=3, show_default=True, type=click.IntRange(1),
              help="Markers that must observe every muscle.")
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="Marker file (.toml).")
@click.option("--baseline/--no-baseline", default=True, show_default=True,
              help="Also print the farthest-point-sampling layout's figures for comparison.")
def design(basis_spec: str, count: int, min_spacing: float | None, n_head: int, min_observers: int, out: Path,
           baseline: bool) -> None:
    """Design a marker layout (greedy D-optimal per region, spacing-constrained) and print its figures."""
    from livebridge.face.layout import default_spacing, design_markers, farthest_point_markers, layout_report

    basis = load_basis(basis_spec)
    spacing = default_spacing(basis, count) if min_spacing is None else min_spacing
    layout = design_markers(basis, count, spacing, n_head=n_head, min_observers=min_observers)
    layout.save(out)
    click.echo(f"wrote {out}: {len(layout)} markers on {basis_spec} (min spacing {spacing:.1f} mm)")
    click.echo(format_report(layout_report(basis, layout), basis.names))
    if baseline:
        report = layout_report(basis, farthest_point_markers(basis, count, seed=0))
        regions = ", ".join(f"{r} {f['condition']:.1f}" for r, f in report["regions"].items())
        click.echo(f"farthest-point sampling, same count: whole face {report['condition_whole']:.1f}, {regions}, "
                   f"fewest observers {report['min_observers']}")


@markers.command("report")
@click.argument("layout_file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--basis", "basis_spec", default="builtin", show_default=True, help=BASIS_HELP)
def report(layout_file: Path, basis_spec: str) -> None:
    """Print the observability figures of an existing LAYOUT_FILE on a basis."""
    from livebridge.errors import InputError
    from livebridge.face.layout import layout_report
    from livebridge.face.markers import MarkerSet

    basis = load_basis(basis_spec)
    try:
        layout = MarkerSet.load(layout_file)
        layout.check_mesh(len(basis.triangles))
    except InputError as error:
        raise click.ClickException(str(error)) from None
    click.echo(format_report(layout_report(basis, layout), basis.names))
