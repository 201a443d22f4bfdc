"""``livebridge retarget``: carry expressions between faces with thin-plate splines."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from livebridge.cli._attach import attach
from livebridge.cli._options import FiniteFloat, ImageFile, InputPath, MeshFile, OutputFile, force_option
from livebridge.cli.basis_show import _draw_mesh, _view
from livebridge.cli.landmarks import MESH_SUFFIXES, MESH_TYPE, UNITS_TO_MM, load_mesh
from livebridge.cli.markers import load_basis
from livebridge.errors import InputError
from livebridge.retarget.checks import check_mesh
from livebridge.retarget.landmarks import SHIPPED_LANDMARK_SETS

LANDMARKS_TYPE = InputPath(builtins=SHIPPED_LANDMARK_SETS)
SIZE_RATIO = 5.0
"""A target face whose landmarks spread more than this many times as far as the source's, or less than its
inverse, is refused: faces differ in size by tens of percent, a mesh read in the wrong ``--units`` by 10 or 1000."""


@click.group("retarget")
def retarget() -> None:
    """Expression transfer between faces (thin-plate splines on facial landmarks)."""


@retarget.command("basis")
@click.option("--source", "source_spec", required=True, type=InputPath(builtins=("builtin",)),
              help="Source actuation basis (.npz) or 'builtin'.")
@click.option("--source-landmarks", required=True, type=LANDMARKS_TYPE,
              help="Landmarks on the source: builtin-22, ict-22 or a landmark file (.toml).")
@click.option("--target", "target_spec", required=True, type=MESH_TYPE,
              help="Target face: a mesh (.obj, .ply, .stl), a basis (.npz, its neutral) or 'builtin'.")
@click.option("--target-landmarks", required=True, type=LANDMARKS_TYPE,
              help="Landmarks on the target (same names as the source's): a landmark file or a shipped set.")
@click.option("--out", required=True, type=OutputFile(), help="Retargeted basis to write (.npz).")
@force_option
@click.option("--kernel", type=click.Choice(["r", "r2lnr2"]), default="r", show_default=True,
              help="TPS kernel: r (3D biharmonic) or r2lnr2 (the thesis's).")
@click.option("--units", type=click.Choice(sorted(UNITS_TO_MM)), default="mm", show_default=True,
              help="Units of a mesh-file target (a basis is in mm).")
def basis(source_spec, source_landmarks, target_spec, target_landmarks, out: Path, force: bool, kernel: str,
          units: str) -> None:
    """Turn every element of a source basis into an element on a target mesh of any topology."""
    from livebridge.retarget.basis import retarget_basis
    from livebridge.retarget.inner_parts import bone_parts

    source = load_basis(source_spec)
    vertices, triangles = load_mesh(target_spec, units)
    check_mesh(vertices, triangles, target_spec)
    source_mesh = (source.neutral, source.triangles)
    on_source, on_target = _landmarks(source_landmarks, source_mesh, target_landmarks, vertices, triangles)
    _check_size(on_source, source_mesh, on_target, vertices, triangles, target_spec, units)
    parts = bone_parts(vertices, triangles, on_target)
    result = retarget_basis(source, on_source, vertices, triangles, on_target, kernel, parts)
    result.save(out)
    moving = int(np.count_nonzero(np.abs(result.elements).max(axis=(1, 2)) > 0))
    click.echo(f"wrote {out}: {result.n_muscles} elements ({moving} moving) on {result.n_vertices} vertices, "
               f"kernel {kernel}")
    _say_parts(parts)


@retarget.command("au")
@click.option("--source", "source_spec", required=True, type=InputPath(builtins=("builtin",)),
              help="Source face: an actuation basis (.npz) or 'builtin' (each AU's muscle recipe makes the "
                   "expression), or with --expression its neutral mesh (.obj, .ply, .stl).")
@click.option("--source-landmarks", required=True, type=LANDMARKS_TYPE, help="Landmarks on the source.")
@click.option("--expression", "expression_spec", type=MESH_TYPE, default=None,
              help="The source person showing the AUs (a mesh, any head pose; thesis §5.5): the chosen AUs' control "
                   "points move as it shows instead of by the basis's recipes.")
@click.option("--expression-landmarks", type=LANDMARKS_TYPE, default=None,
              help="Landmarks on --expression (default: --source-landmarks, when it has the source's triangles).")
@click.option("--target", "target_spec", required=True, type=MESH_TYPE,
              help="Target face: a mesh (.obj, .ply, .stl), a basis (.npz, its neutral) or 'builtin'.")
@click.option("--target-landmarks", required=True, type=LANDMARKS_TYPE, help="Landmarks on the target.")
@click.option("--au", "aus", required=True, multiple=True,
              help="Action unit (1, 2, 4, 12, 14, 15, 17, 20) or a muscle name; repeat to combine.")
@click.option("--magnitude", type=FiniteFloat(0, 1), default=1.0, show_default=True, help="m in [0, 1].")
@click.option("--side", type=click.Choice(["both", "left", "right"]), default="both", show_default=True,
              help="Move one side's control points only (the subject's left: +x).")
@click.option("--control-points", default="thesis", type=InputPath(builtins=("thesis",)), show_default=True,
              help="Control point set: 'thesis' (shipped) or a control-point TOML file.")
@click.option("--out", required=True, type=MeshFile(),
              help="AU mesh to write (.obj, .ply, .stl): for an OBJ target and an .obj, the target's own file with "
                   "its vertices moved (its texture coordinates, polygons and materials kept); else triangles. In "
                   "--units for a mesh-file target, in mm for a basis.")
@force_option
@click.option("--kernel", type=click.Choice(["r", "r2lnr2"]), default="r", show_default=True,
              help="TPS kernel: r (3D biharmonic) or r2lnr2 (the thesis's).")
@click.option("--units", type=click.Choice(sorted(UNITS_TO_MM)), default="mm", show_default=True,
              help="Units of the mesh files (a basis is in mm).")
def au(source_spec, source_landmarks, expression_spec, expression_landmarks, target_spec, target_landmarks, aus,
       magnitude: float, side: str, control_points, out: Path, force: bool, kernel: str, units: str) -> None:
    """Write the target face showing action units carried from the source (Erdoğdu §5.5-5.6) as a mesh file."""
    from livebridge.retarget.au import parse_aus, prepare_transfer, save_mesh, save_moved_obj
    from livebridge.retarget.control_points import load_control_points

    if expression_spec is None:
        if Path(source_spec).suffix.lower() in MESH_SUFFIXES:
            raise InputError("a source mesh has no muscles to make the AUs with: give the source person showing "
                             "them (--expression) or a basis (.npz)", source_spec, "--expression")
        source = load_basis(source_spec)
        source_mesh = (source.neutral, source.triangles)
    else:
        source = source_mesh = load_mesh(source_spec, units)
        check_mesh(*source_mesh, source_spec)
    vertices, triangles = load_mesh(target_spec, units)
    check_mesh(vertices, triangles, target_spec)
    on_source, on_target = _landmarks(source_landmarks, source_mesh, target_landmarks, vertices, triangles)
    _check_size(on_source, source_mesh, on_target, vertices, triangles, target_spec, units)
    expression = None if expression_spec is None else _expression(
        expression_spec, expression_landmarks, source_landmarks, source_mesh, units)
    points = load_control_points(control_points)
    _require_reference_names(points, (source_landmarks, on_source), (target_landmarks, on_target))
    sides = {"both": ("L", "R", "C"), "left": ("L",), "right": ("R",)}[side]
    transfer = prepare_transfer(points, parse_aus(aus), source, on_source, (vertices, triangles), on_target, sides,
                                kernel, expression)
    moved = transfer.mesh(magnitude)
    target_suffix = Path(target_spec).suffix.lower()
    as_target = (target_suffix == ".obj" and out.suffix.lower() == ".obj"
                 and save_moved_obj(out, target_spec, moved, UNITS_TO_MM[units]))
    written_units = units if target_suffix in MESH_SUFFIXES else "mm"
    if not as_target:
        save_mesh(out, moved, triangles, UNITS_TO_MM[written_units], written_units)
    written = (f"the target's own file moved, in {units} (its texture coordinates, polygons and materials kept, "
               "its normals dropped)" if as_target else f"triangles, {written_units}")
    click.echo(f"wrote {out}: {', '.join(aus)} at m = {magnitude:g} ({side}); largest move "
               f"{np.linalg.norm(moved - vertices, axis=1).max():.2f} mm; {written}")
    _say_parts(transfer.parts)


def _say_parts(parts) -> None:
    """Tell how many of the target's vertices are closed inner parts moved with a bone (``parts``: BoneParts)."""
    if parts.any:
        click.echo(f"note: closed parts inside the head move with their bone, not the skin: {int(parts.skull.sum())} "
                   f"vertices on the skull (still), {int(parts.jaw.sum())} on the jaw (teeth, eyes; see the README)")


def _expression(spec, landmarks_spec, source_landmarks, source_mesh, units: str):
    """(mesh, landmarks, spec) of ``--expression``; its landmarks are the source's when not given and it has
    the source's triangles (a blendshape of the source)."""
    vertices, triangles = load_mesh(spec, units)
    check_mesh(vertices, triangles, spec)
    if landmarks_spec is None:
        if not np.array_equal(triangles, source_mesh[1]):
            raise InputError("its triangles are not the source's, so the source's landmarks do not say where its "
                             "landmarks are: give them with --expression-landmarks", spec, "--expression-landmarks")
        landmarks_spec = source_landmarks
    _, on_expression = _landmarks(source_landmarks, source_mesh, landmarks_spec, vertices, triangles)
    return (vertices, triangles), on_expression, spec


def _landmarks(source_spec, source_mesh, target_spec, vertices, triangles):
    """(source landmarks, target landmarks), checked on their meshes (``source_mesh``: (vertices, triangles));
    errors name the file and the landmark."""
    from livebridge.retarget.checks import check_landmarks_on
    from livebridge.retarget.landmarks import load_landmark_set

    on_source = load_landmark_set(source_spec).checked_on(len(source_mesh[1]), source_spec)
    on_target = load_landmark_set(target_spec).checked_on(len(triangles), target_spec)
    try:
        on_target.index_of(on_source.names)
    except InputError as error:
        raise InputError(error.message + f" (the source set {source_spec} names them)", target_spec,
                         "landmarks") from None
    check_landmarks_on(on_source, *source_mesh, source_spec)
    check_landmarks_on(on_target, vertices, triangles, target_spec)
    return on_source, on_target


def _check_size(on_source, source_mesh, on_target, vertices, triangles, target_mesh, units: str) -> None:
    """Refuse a target whose landmarks spread :data:`SIZE_RATIO` times more or less than the source's: an OBJ
    read in the wrong ``--units``. The transfer itself would run and write a face moved in the wrong units (or
    find too few of its control points on the surface), so the error names the mesh and the option."""
    names = list(on_source.names)
    here = on_source.positions(*source_mesh)
    there = on_target.positions(vertices, triangles)[on_target.index_of(names)]
    check_size(here, there, "the source's", target_mesh, units)


def check_size(here: np.ndarray, there: np.ndarray, whose: str, path, units: str) -> None:
    """Refuse landmarks ``there`` (n, 3; of ``path``, read in ``units``) that spread :data:`SIZE_RATIO` times
    more or less than the same landmarks ``here`` (n, 3; ``whose``, e.g. "the source's"), naming ``--units``."""
    spread = [float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1)))) for p in (here, there)]
    ratio = spread[1] / spread[0] if spread[0] > 0 else float("inf")
    if not 1 / SIZE_RATIO <= ratio <= SIZE_RATIO:
        raise InputError(f"its landmarks spread {spread[1]:.3g} mm (RMS about their centre), {ratio:.3g} times "
                         f"{whose} {spread[0]:.3g} mm: is it in {units}? (give its unit with --units)", path,
                         "units")


def _require_reference_names(points, *landmark_sets) -> None:
    """Refuse, naming the landmark file, a source or target set that lacks a landmark the control points are
    carried by (``landmark_sets``: (spec, LandmarkSet) pairs)."""
    from livebridge.retarget.control_points import reference_face

    try:
        _, reference = reference_face(points.reference)
    except InputError:
        return  # a set defined on a face livebridge cannot load: carrying it says what is wrong
    for spec, landmarks in landmark_sets:
        try:
            landmarks.index_of(reference.names)
        except InputError as error:
            raise InputError(error.message + f" (the control points are carried by {points.reference})", spec,
                             "landmarks") from None


@retarget.command("show")
@click.argument("bases", nargs=-1, required=True, type=InputPath(builtins=("builtin",)))
@click.option("--contractions", "contractions_file", type=InputPath(), default=None,
              help="Contraction file (t + one column per muscle, as livebridge solve writes) to play; default: "
                   "each muscle in turn, then a smile, a frown and an open jaw.")
@click.option("--frames", type=click.IntRange(1, 24), default=6, show_default=True, help="Frames shown.")
@click.option("--out", required=True, type=ImageFile(), help="Image to write (.png).")
@force_option
def show(bases, contractions_file, frames: int, out: Path, force: bool) -> None:
    """Play one contraction take on several bases (a source and its retargeted copies), side by side."""
    faces = [(Path(spec).stem if spec != "builtin" else "built-in face", load_basis(spec)) for spec in bases]
    if contractions_file is None:
        names, values, labels = demo_take(faces[0][1].names)
    else:
        from livebridge.servo.playback import read_contractions

        track = read_contractions(contractions_file, faces[0][1].names, ignore_extra=True)
        names, values, labels = track.muscle_names, track.values, [f"t = {t:.2f} s" for t in track.t]
    render_take(faces, np.nan_to_num(values), names, out, frames=frames, labels=labels)
    click.echo(f"wrote {out}: {min(frames, len(values))} frames on {len(faces)} faces")


def demo_take(names) -> tuple[tuple[str, ...], np.ndarray, list[str]]:
    """(muscle names, contractions (frames, muscles), frame labels): a smile, a frown, an open jaw, a brow raise,
    a pucker and a one-sided sneer."""
    poses = (("smile", ("zygomatic_major_L", "zygomatic_major_R")), ("frown", ("corrugator_L", "corrugator_R")),
             ("jaw open", ("jaw",)), ("brows up", ("frontalis_L", "frontalis_R")), ("pucker", ("orbicularis_oris",)),
             ("sneer (left)", ("levator_labii_L",)))
    values = np.zeros((len(poses), len(names)))
    for k, (_, muscles) in enumerate(poses):
        for muscle in muscles:
            if muscle in names:
                values[k, list(names).index(muscle)] = 1.0
    return tuple(names), values, [label for label, _ in poses]


def render_take(faces, contractions: np.ndarray, muscle_names, path, frames: int = 6, dpi: int = 80,
                yaw_deg: float = 20.0, panel_inches: float = 2.6, labels=None) -> None:
    """A contraction take played on several faces, side by side: one column per face, one row per frame shown.

    Parameters
    ----------
    faces : sequence of (title, Basis)
    contractions : ndarray, shape (n_frames, n_muscles)
        Columns named by ``muscle_names``; each face uses the columns it has.
    muscle_names : sequence of str
    path : str or Path
        Image file.
    frames : int
        Frames shown, evenly spread over the take (the most active frames of each stretch).
    labels : sequence of str, optional
        One per frame of the take (row titles).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    contractions = np.asarray(contractions, dtype=np.float64)
    shown = np.linspace(0, len(contractions) - 1, min(frames, len(contractions))).round().astype(int)
    fig, axes = plt.subplots(len(shown), len(faces), figsize=(panel_inches * len(faces), panel_inches * len(shown)),
                             squeeze=False)
    skin = np.array([0.93, 0.80, 0.70, 1.0])
    for column, (title, basis) in enumerate(faces):
        x = np.zeros((len(contractions), basis.n_muscles))
        for j, name in enumerate(muscle_names):
            if name in basis.names:
                x[:, basis.index(name)] = contractions[:, j]
        neutral = _view(basis.neutral, yaw_deg, 0.0)
        low, high = neutral.min(axis=0), neutral.max(axis=0)
        for row, frame in enumerate(shown):
            ax = axes[row, column]
            ax.set_axis_off()
            moved = basis.synthesize(x[frame])
            size = np.linalg.norm(moved - basis.neutral, axis=1)[basis.triangles].mean(axis=1)
            level = np.clip(size / 6.0, 0, 1)[:, None]  # mm: warmer where the skin moved
            colour = np.tile(skin, (len(basis.triangles), 1))
            colour[:, :3] = (1 - 0.6 * level) * skin[:3] + 0.6 * level * np.array([0.85, 0.25, 0.2])
            _draw_mesh(ax, _view(moved, yaw_deg, 0.0), basis.triangles, colour)
            ax.set_xlim(low[0], high[0])
            ax.set_ylim(low[1], high[1])
            ax.set_aspect("equal")
            if row == 0:
                ax.set_title(title, fontsize=9)
            if column == 0 and labels is not None:
                ax.text(low[0], high[1], labels[frame], fontsize=7, va="top")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


attach(retarget, (("livebridge.cli.retarget_scans", "scans"),))
