"""``livebridge landmarks``: place named landmarks on a mesh and render them for checking."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click
import numpy as np

from livebridge.cli._options import FiniteFloat, ImageFile, InputPath, OutputFile, force_option
from livebridge.retarget.landmarks import SHIPPED_LANDMARK_SETS

UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
MESH_TYPE = InputPath(builtins=("builtin",))
MESH_SUFFIXES = (".obj", ".ply", ".stl")
"""Mesh files :func:`load_mesh` reads (in a command's ``--units``)."""
MESH_HELP = ("MESH: a basis (.npz, its neutral face), a mesh (.obj, .ply, .stl), or 'builtin' (the procedural "
             "face).")


def load_mesh(spec, units: str = "mm") -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) in mm, triangles (m, 3)) of a basis .npz (mm), a mesh file (.obj, .ply, .stl; in
    ``units``) or ``builtin``."""
    from livebridge.errors import InputError

    if spec == "builtin":
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
        return basis.neutral, basis.triangles
    suffix = Path(spec).suffix.lower()
    if suffix == ".npz":
        from livebridge.face.basis import Basis

        basis = Basis.load(spec)
        return basis.neutral, basis.triangles
    if suffix == ".obj":
        from livebridge.face.meshio import read_obj

        mesh = read_obj(spec)
        vertices, triangles = mesh.vertices, mesh.triangles
    elif suffix in MESH_SUFFIXES:
        from livebridge.retarget.scan import read_scan

        scan = read_scan(spec)
        vertices, triangles = scan.points, scan.triangles
    else:
        raise InputError(f"unknown mesh type {suffix or '(no suffix)'!r}: give a basis .npz, a mesh (.obj, .ply, "
                         ".stl) or 'builtin'", spec)
    if not len(triangles):
        raise InputError("no faces: landmarks need a surface, not a point cloud", spec)
    return vertices * UNITS_TO_MM[units], triangles


@click.group("landmarks")
def landmarks() -> None:
    """Named facial landmarks on a mesh (the thesis's 22: shipped as builtin-22 and ict-22)."""


@landmarks.command("place")
@click.argument("mesh", type=MESH_TYPE)
@click.option("--vertices", "vertices_file", type=InputPath(), default=None,
              help="TOML file of 'name = vertex id' lines (ids from 0).")
@click.option("--points", "points_file", type=InputPath(), default=None,
              help="Named points (in --units), each snapped to the nearest surface point: a CSV of name,x,y,z "
                   "rows, a TOML of name = [x, y, z] lines or a MeshLab PickPoints file (.pp).")
@click.option("--out", required=True, type=OutputFile(), help="Landmark file to write (.toml).")
@force_option
@click.option("--units", type=click.Choice(sorted(UNITS_TO_MM)), default="mm", show_default=True,
              help="Units of a mesh file and of --points (a basis is in mm).")
@click.option("--max-distance", type=FiniteFloat(0, 1e4, low_open=True), default=3.0, show_default=True,
              help="Farthest a --points point may be from the surface, mm.")
@click.option("--require-22", is_flag=True, help="Refuse unless all 22 thesis landmarks are given.")
def place(mesh, vertices_file: Path | None, points_file: Path | None, out: Path, force: bool, units: str,
          max_distance: float, require_22: bool) -> None:
    """Place landmarks on MESH from vertex ids or 3D points and write them as a landmark (marker-set) file.

    MESH: a basis (.npz), a mesh (.obj, .ply, .stl) or 'builtin'. Names are free; the thesis's 22 are brow_outer_L ...
    chin (see the README).
    """
    from livebridge.retarget.landmarks import place_at_points, place_at_vertices, read_vertex_ids
    from livebridge.retarget.point_files import read_points

    if (vertices_file is None) == (points_file is None):
        raise click.UsageError("give one of --vertices and --points")
    vertices, triangles = load_mesh(mesh, units)
    if vertices_file is not None:
        source = vertices_file
        placed = place_at_vertices(read_vertex_ids(vertices_file), len(vertices), triangles, vertices_file,
                                   vertices)
    else:
        source = points_file
        points = read_points(points_file, UNITS_TO_MM[units])
        placed = place_at_points(points, vertices, triangles, max_distance, points_file)
    if require_22:
        placed.require_thesis_22(source)
    # the mesh's triangle count goes with the file: on a mesh of another topology its triangles are other places
    placed = dataclasses.replace(placed, mesh_triangles=len(triangles))
    placed.save(out)
    click.echo(f"wrote {out}: {len(placed)} landmarks on {mesh}")


@landmarks.command("template")
@click.option("--out", required=True, type=OutputFile(), help="MeshLab PickPoints template to write (.pptpl).")
@force_option
@click.option("--lids", is_flag=True, help="Add the 8 eyelid points of the 68-point iBUG layout (lm_37 ... lm_47): "
                                           "retarget scans reads an eye's lid motion from them when its scans show "
                                           "no eye opening.")
def template(out: Path, force: bool, lids: bool) -> None:
    """Write the thesis's 22 landmark names as a MeshLab PickPoints template, to pick them on scans.

    In MeshLab: open a scan, Edit > PickPoints, load this template, click each named point in turn, and save
    (MeshLab's default name, SCAN_picked_points.pp, is where retarget scans looks for an expression's landmarks).
    """
    from livebridge.retarget.eyelids import LID_LANDMARK_NAMES
    from livebridge.retarget.landmarks import THESIS_22_NAMES
    from livebridge.retarget.point_files import write_pick_template

    names = list(THESIS_22_NAMES)
    if lids:
        names += sorted(LID_LANDMARK_NAMES)
    write_pick_template(out, names)
    click.echo(f"wrote {out}: {len(names)} names to pick (MeshLab: Edit > PickPoints, Load Template)")


@landmarks.command("show")
@click.argument("mesh", type=MESH_TYPE)
@click.argument("landmarks_spec", metavar="LANDMARKS", type=InputPath(builtins=SHIPPED_LANDMARK_SETS))
@click.option("--out", required=True, type=ImageFile(), help="Image file (.png).")
@force_option
@click.option("--units", type=click.Choice(sorted(UNITS_TO_MM)), default="mm", show_default=True,
              help="Units of a mesh file (a basis is in mm).")
@click.option("--yaw", type=FiniteFloat(-90, 90), default=35.0, show_default=True,
              help="View angle of the second panel about the vertical axis, degrees (the first is frontal).")
@click.option("--dpi", default=110, show_default=True, type=click.IntRange(30, 600))
def show(mesh, landmarks_spec, out: Path, force: bool, units: str, yaw: float, dpi: int) -> None:
    """Render MESH with LANDMARKS (a landmark file, builtin-22 or ict-22) numbered and named, to check them."""
    from livebridge.retarget.landmarks import load_landmark_set

    vertices, triangles = load_mesh(mesh, units)
    placed = load_landmark_set(landmarks_spec).checked_on(len(triangles), landmarks_spec)
    render_landmarks(vertices, triangles, placed, out, yaw_deg=yaw, dpi=dpi, title=f"{landmarks_spec} on {mesh}")
    click.echo(f"wrote {out}: {len(placed)} landmarks on {mesh}")


def render_landmarks(vertices: np.ndarray, triangles: np.ndarray, placed, path, yaw_deg: float = 35.0,
                     dpi: int = 110, title: str = "") -> None:
    """A frontal and a turned view of the mesh with each landmark numbered (1..n), and the names listed.

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    placed : LandmarkSet
    path : str or Path
        Image file (format from the suffix).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from livebridge.cli.basis_show import _draw_mesh, _view

    positions = placed.positions(vertices, triangles)
    skin = np.tile([0.93, 0.80, 0.70, 1.0], (len(triangles), 1))
    fig, axes = plt.subplots(1, 3, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1, 1, 0.55]})
    for ax, view_yaw in zip(axes[:2], (0.0, yaw_deg)):
        view, points = _view(vertices, view_yaw, 0.0), _view(positions, view_yaw, 0.0)
        low, high = view.min(axis=0), view.max(axis=0)
        pad = 0.04 * (high - low)
        ax.set_xlim(low[0] - pad[0], high[0] + pad[0])
        ax.set_ylim(low[1] - pad[1], high[1] + pad[1])
        ax.set_aspect("equal")
        ax.set_axis_off()
        _draw_mesh(ax, view, triangles, skin)
        ax.scatter(points[:, 0], points[:, 1], s=14, c="tab:red", edgecolors="black", linewidths=0.4, zorder=3)
        for number, (x, y) in enumerate(points[:, :2], 1):
            ax.annotate(str(number), (x, y), xytext=(3, 3), textcoords="offset points", fontsize=7, zorder=4,
                        color="navy")
        ax.set_title(f"yaw {view_yaw:g} deg", fontsize=9)
    axes[2].set_axis_off()
    listing = "\n".join(f"{k:2d}  {name}" for k, name in enumerate(placed.names, 1))
    axes[2].text(0.0, 1.0, listing, va="top", family="monospace", fontsize=max(5.0, min(9.0, 300 / len(placed))),
                 transform=axes[2].transAxes)
    fig.suptitle(title or "landmarks", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
