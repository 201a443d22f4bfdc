"""``livebridge retarget scans``: an actuation basis from a neutral scan and one scan per muscle."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import FiniteFloat, InputPath, Named, OutputFile, Size, force_option, unique_names
from livebridge.cli.landmarks import UNITS_TO_MM
from livebridge.cli.retarget import check_size
from livebridge.retarget.landmarks import SHIPPED_LANDMARK_SETS

SCAN_HELP = ("Scans: PLY (ascii or binary, point cloud or mesh), OBJ, STL (a mesh), or XYZ/CSV text (x y z per "
             "line), with colour when the scanner recorded it: per point (PLY red/green/blue, OBJ v x y z r g b, "
             "XYZ r g b columns) or as a textured OBJ mesh (vt coordinates, mtllib with map_Kd images next to it) or "
             "PLY mesh (comment TextureFile images next to it, face texcoord or vertex s t). "
             "Landmarks: "
             "a CSV of name,x,y,z rows, a TOML of name = [x, y, z] lines, or a MeshLab PickPoints file (.pp; "
             "'livebridge landmarks template' writes the names to pick), in the scan's coordinates and units; "
             "an expression's landmark file defaults to SCAN with the suffix .landmarks.csv, or else MeshLab's "
             "SCAN_picked_points.pp.")


def split_scan_spec(text: str) -> tuple[Path, Path]:
    """``SCAN[:LANDMARKS]`` -> (scan, landmarks); the default landmarks are ``SCAN.landmarks.csv``, or MeshLab's
    ``SCAN_picked_points.pp`` when only that one is there."""
    from livebridge.retarget.point_files import POINT_FILE_SUFFIXES, picked_points_file

    scan, sep, landmarks = text.rpartition(":")
    if sep and Path(landmarks).suffix.lower() in POINT_FILE_SUFFIXES and scan:
        return Path(scan), Path(landmarks)
    default = Path(text).with_suffix(".landmarks.csv")
    picked = picked_points_file(text)
    return Path(text), picked if picked.exists() and not default.exists() else default


def reference_landmarks(spec: str, scale: float) -> dict:
    """The reference face's landmarks: ``builtin`` (the built-in face's builtin-22) or a landmark points file."""
    if spec != "builtin":
        from livebridge.errors import InputError
        from livebridge.retarget.normalise import NORMALISATION_LANDMARKS
        from livebridge.retarget.point_files import read_points

        points = read_points(spec, scale)
        missing = [name for name in NORMALISATION_LANDMARKS if name not in points]
        if missing:  # named here: the normalisation knows it only as the reference face
            raise InputError(f"the reference face needs the landmarks {', '.join(NORMALISATION_LANDMARKS)}; "
                             f"missing: {', '.join(missing)}", spec, "landmarks")
        return points
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    face = builtin_basis()
    return load_landmark_set("builtin-22").as_dict(face.neutral, face.triangles)


@click.command("scans", epilog=SCAN_HELP)
@click.option("--neutral", "neutral_scan", required=True, type=InputPath(), help="The neutral scan.")
@click.option("--neutral-landmarks", default=None, type=InputPath(),
              help="Landmarks of the neutral scan (default: NEUTRAL.landmarks.csv, or MeshLab's "
                   "NEUTRAL_picked_points.pp when only that one is there).")
@click.option("--expression", "expressions", multiple=True, required=True, type=Named(click.STRING, "SCAN[:LM]"),
              help="MUSCLE=SCAN[:LANDMARKS], once per element (Choe-Ko names get their region and side).")
@click.option("--out", required=True, type=OutputFile(), help="Basis to write (.npz).")
@force_option
@click.option("--reference", default="builtin", show_default=True, type=InputPath(builtins=("builtin",)),
              help="Reference face for the normalisation: 'builtin' or a landmark points file (CSV/TOML, mm).")
@click.option("--normalise", "method", type=click.Choice(["rigid", "similarity", "affine"]), default="rigid",
              show_default=True, help="rigid/similarity keep the person's shape; affine is the thesis's T = A B^-1 "
                                      "(the face takes the reference's proportions).")
@click.option("--frame", type=click.Choice(["face", "scan"]), default="face", show_default=True,
              help="Coordinates of the basis and --grid-obj: face (the normalised face: nose tip at the origin, "
                   "looking along +z with +y up, as the render client shows a face) or scan (the neutral scan's "
                   "own axes and origin, in mm: the basis lies on the scan, in its proportions whatever "
                   "--normalise).")
@click.option("--grid", "grid_size", type=Size(2, 2000), default="150x150", show_default=True,
              help="Resampling grid, columns x rows.")
@click.option("--crop-radius", type=FiniteFloat(0, 1e4, low_open=True), default=None,
              help="Face crop around the nose tip, mm (default: 1.2 x the farthest landmark).")
@click.option("--units", type=click.Choice(sorted(UNITS_TO_MM)), default="mm", show_default=True,
              help="Units of the scans and landmark files.")
@click.option("--kernel", type=click.Choice(["r", "r2lnr2"]), default="r", show_default=True,
              help="TPS kernel: r (3D biharmonic) or r2lnr2 (the thesis's).")
@click.option("--grid-obj", type=OutputFile(), default=None, help="Also write the neutral grid (OBJ with UVs).")
@click.option("--landmarks-out", type=OutputFile(), default=None,
              help="Also write the landmarks on the neutral grid (landmark .toml, for retarget basis).")
@click.option("--mesh-spacing", "--texture-spacing", "mesh_spacing", type=FiniteFloat(0.05, 5.0), default=None,
              help="A mesh scan is sampled into points this far apart, mm (default 0.5, the skin images' pixel; a "
                   "finer texture is blurred to it): its vertices, dense where it curves and sparse where it "
                   "does not, are no even sample of its surface.")
@click.option("--lighting", type=click.Choice(["auto", "remove", "keep"]), default="auto", show_default=True,
              help="The scans' colours hold the scanner's light as well as the skin: remove divides the shading "
                   "the surface's normals explain out of every scan's colours (an opened jaw or a frown turns skin "
                   "towards the light), keep leaves the colours as they are (a texture already delit); auto "
                   "removes it when it explains at least 10% of the neutral's brightness.")
@click.option("--keep-eyeballs", is_flag=True,
              help="Keep the points whose colour reads as an eyeball seen between the lids (the sclera, the iris; "
                   "by default left out of every scan, so each eye's opening is a hole whose edges are the lids' "
                   "margins). Give it when the detection takes skin for eyes (bright or coloured eye make-up).")
@click.option("--fill-from", "template_spec", type=InputPath(builtins=("builtin",)), default=None,
              help="Complete the basis: every muscle of this basis ('builtin' or .npz) that no --expression shows is "
                   "retargeted onto the scanned neutral (it moves as that face's does, not as this person's).")
@click.option("--fill-landmarks", type=InputPath(builtins=SHIPPED_LANDMARK_SETS), default=None,
              help="Landmarks on the --fill-from face (default builtin-22 for 'builtin'); the neutral scan's "
                   "landmarks must name them all.")
@click.option("--workers", type=click.IntRange(1, 256), default=None,
              help="Expression scans prepared at once, each in its own process holding one scan (about 1.2 GB a "
                   "million points). Default: one per core, as many as the free memory holds, when the expression "
                   "scans are over 8 MB in all (smaller ones prepare faster than processes start).")
def scans(neutral_scan: Path, neutral_landmarks: Path | None, expressions, out: Path, force: bool, reference: str,
          method: str, frame: str, grid_size, crop_radius, units: str, kernel: str, grid_obj, landmarks_out,
          mesh_spacing: float | None, lighting: str, keep_eyeballs: bool, template_spec, fill_landmarks,
          workers: int | None) -> None:
    """Build an actuation basis for a scanned person from a neutral scan and one scan per muscle.

    Each scan is normalised (nose tip at the origin, facing +z), cropped to the face and resampled on a
    regular grid; each expression's displacement of the neutral grid comes from a landmark TPS, control
    points snapped to the expressive surface and a TPS warp (Erdoğdu §5.4-5.5). When the neutral and an
    expression scan both carry colour, the skin's pattern is tracked between them, so the motion along the
    skin is measured everywhere; without colour it is known only at the landmarks (held still where the
    surface did not change, and a closing eyelid's read from where the eye opening went).
    """
    import numpy as np

    from livebridge.face.muscle_place import misplaced
    from livebridge.retarget.face_scan import OFF_FACE_MM, prepare_neutral
    from livebridge.retarget.facing import facing_said
    from livebridge.retarget.point_files import picked_points_file, read_points
    from livebridge.retarget.same_face import another_face, neutral_off_expressions, off_expressions
    from livebridge.retarget.scan import read_scan
    from livebridge.retarget.scans import basis_from_scans, in_scan_frame
    from livebridge.retarget.shading import lighting_said

    outputs = [(option, path) for option, path in (("--out", out), ("--grid-obj", grid_obj),
                                                    ("--landmarks-out", landmarks_out)) if path is not None]
    for k, (option, path) in enumerate(outputs):
        same = [other for other, there in outputs[:k] if there.resolve() == path.resolve()]
        if same:  # the later file would overwrite the earlier
            raise click.BadParameter(f"{path}: {same[0]} writes there already; give each output its own file",
                                     param_hint=option)
    template = _template(template_spec, fill_landmarks)
    if neutral_landmarks is None:  # as for an expression's SCAN without :LANDMARKS
        neutral_landmarks = split_scan_spec(str(neutral_scan))[1]
        if not neutral_landmarks.exists():
            raise click.BadParameter(f"no landmark file {neutral_landmarks} (nor "
                                     f"{picked_points_file(neutral_scan).name}): give it",
                                     param_hint="--neutral-landmarks")
    scale = UNITS_TO_MM[units]
    columns, rows = grid_size
    named = unique_names(expressions, "--expression")
    neutral_points, neutral_marks = read_scan(neutral_scan, scale), read_points(neutral_landmarks, scale)
    files = {name: split_scan_spec(spec) for name, spec in named.items()}
    for name, (scan_path, landmark_path) in files.items():  # before the neutral's preparation, not after it
        for path, what in ((scan_path, "scan"), (landmark_path, "landmark file")):
            if not path.exists():
                defaulted = what != "scan" and path == scan_path.with_suffix(".landmarks.csv")
                also = f" (nor {picked_points_file(scan_path).name}; or give SCAN:LANDMARKS)" if defaulted else ""
                raise click.BadParameter(f"{name}: no {what} {path}{also}", param_hint="--expression")
    reference_marks = reference_landmarks(reference, 1.0)
    shared = [name for name in reference_marks if name in neutral_marks]
    if len(shared) >= 4:  # fewer: the normalisation names the missing ones
        check_size(np.array([reference_marks[n] for n in shared]), np.array([neutral_marks[n] for n in shared]),
                   "the reference face's", neutral_landmarks, units)
    click.echo(f"preparing {neutral_scan.name} and {len(files)} expression scan{'s' * (len(files) > 1)}")
    neutral = prepare_neutral(neutral_points, neutral_marks, reference_marks, method, (rows, columns), crop_radius,
                              neutral_landmarks, scan_source=neutral_scan, mesh_spacing=mesh_spacing,
                              remove_shading={"auto": None, "remove": True, "keep": False}[lighting],
                              leave_out_eyeballs=not keep_eyeballs)
    if neutral.shading is not None:
        click.echo(lighting_said(neutral.shading, neutral.shading_removed))
    said = facing_said(neutral.facing, neutral_scan.name)
    if said:
        click.echo(said)
    if neutral.eyeball_points:
        click.echo(f"eyes: {neutral.eyeball_points} points of {neutral_scan.name} are eyeballs seen between the lids, "
                   "left out of it and of the expression scans (--keep-eyeballs keeps them)")
    faces, uncoloured = {}, []
    jobs = [(name, scan_path, landmark_path, scale, mesh_spacing) for name, (scan_path, landmark_path) in files.items()]
    for name, face in prepared_expressions(neutral, jobs, worker_count(workers, [path for _, path, *_ in jobs])):
        faces[name] = face
        scan_path = files[name][0]
        if not (neutral.coloured and faces[name].coloured):
            uncoloured.append(name)
        said = facing_said(faces[name].facing, scan_path.name)
        if said and faces[name].facing.orientation != "outward":
            click.echo(said)
        why = another_face(faces[name].gap_mm, faces[name].noise_mm)
        if why is not None:
            click.echo(f"warning: {name} ({scan_path.name}): {why}")
        if faces[name].off_face_share >= OFF_FACE_NOTE:
            click.echo(f"note: {name} ({scan_path.name}): {faces[name].off_face_share:.1%} of its points lie over "
                       f"{OFF_FACE_MM:g} mm from the neutral's face once registered (something between the scanner and "
                       "the face: a hand, glasses, a microphone?) and are left out")
    off_neutral = off_expressions(neutral_off_expressions(neutral.vertices, [face.vertices for face in faces.values()],
                                                          OFF_FACE_MM), neutral.vertices, OFF_FACE_MM, len(faces))
    if off_neutral is not None:
        click.echo(f"warning: {neutral_scan.name}: {off_neutral}")
    click.echo("building the elements")
    basis = basis_from_scans(neutral, faces, kernel, log=click.echo)
    filled = ()
    if template is not None:
        from livebridge.retarget.fill import fill_basis

        click.echo(f"retargeting the muscles no scan shows from {template_spec}")
        template_basis, template_landmarks, template_landmarks_spec = template
        completed = fill_basis(basis, neutral.landmark_set(neutral_landmarks), template_basis, template_landmarks,
                               kernel, template_landmarks_spec)
        basis, filled = completed.basis, completed.filled
    saved = in_scan_frame(basis, neutral) if frame == "scan" else basis
    saved.save(out)
    if grid_obj is not None:
        neutral.mesh_grid.write_obj(grid_obj, saved.neutral)
    if landmarks_out is not None:
        neutral.landmark_set(neutral_landmarks).save(landmarks_out)
    largest = np.linalg.norm(saved.elements, axis=2).max(axis=1)
    click.echo(f"wrote {out}: {basis.n_muscles} elements on {basis.n_vertices} grid vertices "
               f"({columns}x{rows}, normalise {method}, kernel {kernel}, {frame} frame)")
    for muscle, size in zip(basis.muscles, largest):
        how = (f"retargeted from {template_spec}" if muscle.name in filled else
               "shape only" if muscle.name in uncoloured else "skin tracked")
        click.echo(f"  {muscle.name:24s} {muscle.region:5s} largest motion {size:6.2f} mm  ({how})")
    for muscle, element in zip(basis.muscles, basis.elements):
        if muscle.name in filled:
            continue
        why = misplaced(muscle, element, neutral.vertices, neutral.landmarks)
        if why is not None:
            click.echo(f"warning: {muscle.name}: {why}")
    if uncoloured:
        which = "the neutral scan" if not neutral.coloured else ", ".join(uncoloured)
        click.echo(f"note: no colour in {which}: the motion along the skin (most of a brow raise or a smile) is "
                   "then known only at the landmarks (and a closing eyelid's from the eye opening); scans with "
                   "colour (per point, or a textured OBJ or PLY) let it be tracked everywhere")


def _template(spec, landmarks_spec):
    """(template basis, its landmarks, their spec) of ``--fill-from`` / ``--fill-landmarks``, or None; read
    before any scan."""
    if spec is None:
        if landmarks_spec is not None:
            raise click.BadParameter("it names landmarks on the --fill-from face: give --fill-from too",
                                     param_hint="--fill-landmarks")
        return None
    from livebridge.cli.markers import load_basis
    from livebridge.retarget.landmarks import load_landmark_set

    if landmarks_spec is None:
        if spec != "builtin":
            raise click.BadParameter(f"which landmarks on {spec}? give --fill-landmarks (e.g. ict-22, or a file "
                                     "from `livebridge landmarks place`)", param_hint="--fill-landmarks")
        landmarks_spec = "builtin-22"
    template = load_basis(spec)
    landmarks = load_landmark_set(landmarks_spec).checked_on(len(template.triangles), landmarks_spec)
    return template, landmarks, landmarks_spec


OFF_FACE_NOTE = 0.001
"""The build says so when at least this share of an expression scan's points were left out as off the face
(:data:`~livebridge.retarget.face_scan.OFF_FACE_MM`); fewer are stray points."""
POOL_MIN_BYTES = 8_000_000
"""Expression scans smaller than this in all are prepared in this process: a worker takes about 2 s to start
(its imports and the neutral face), a 60k-point scan (0.9 MB) about as long to prepare."""
WORKER_BYTES_PER_POINT = 1200
"""A worker's peak memory per point of its scan (1.2 GB for a million points; measured 2.1 GB for 1.7M)."""
FILE_BYTES_PER_POINT = 15
"""The fewest bytes a scan file spends on a point: binary PLY, float x y z and uchar colour (1.7M points in
26 MB); other layouts spend more, and are judged to hold more points than they do, on the safe side."""


def worker_count(workers: int | None, scan_paths: list[Path]) -> int:
    """``workers`` when given; else the cores, at most one per scan and as many as the free memory holds for
    the largest scan (its points judged by its file size: :data:`FILE_BYTES_PER_POINT`), and 1 when the
    scans are under :data:`POOL_MIN_BYTES` in all."""
    import os

    if workers is not None:
        return min(workers, max(1, len(scan_paths)))
    sizes = [path.stat().st_size for path in scan_paths]
    if len(sizes) < 2 or sum(sizes) < POOL_MIN_BYTES:
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    per_worker = WORKER_BYTES_PER_POINT * max(sizes) / FILE_BYTES_PER_POINT
    return max(1, min(cores, len(sizes), int(available_memory() // per_worker)))


def available_memory() -> float:
    """Bytes the system can give a new process: Linux's MemAvailable (free memory and the page cache it can
    drop), else the free pages, else infinity (not known: memory does not limit)."""
    import os

    try:
        with open("/proc/meminfo") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return float("inf")


def prepared_expressions(neutral, jobs: list[tuple], workers: int):
    """(name, FaceScan) per job (name, scan path, landmark path, scale, mesh spacing), in the jobs' order,
    prepared on the ``neutral`` FaceScan in ``workers`` processes (1: here). The first job in order that
    fails raises its error; the jobs after it are cancelled."""
    if workers <= 1:
        for job in jobs:
            yield job[0], _prepare_file(neutral, *job[1:])
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    from livebridge.errors import InputError

    # spawn, not fork: the neutral's preparation started OpenCV's and OpenBLAS's threads in this process
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, context, initializer=_keep_neutral, initargs=(neutral,)) as pool:
        futures = [pool.submit(_prepare_kept, *job[1:]) for job in jobs]
        try:
            for job, future in zip(jobs, futures):
                try:
                    face = future.result()
                except BrokenProcessPool:  # killed: most often by the system, out of memory
                    raise InputError(f"a worker process stopped while {workers} scans were being prepared at once "
                                     f"(out of memory?); give fewer --workers (1: one scan at a time)",
                                     job[1], "--workers") from None
                yield job[0], face
        finally:
            for future in futures:
                future.cancel()


_NEUTRAL: list = []
"""A worker's neutral FaceScan, sent once when it starts (:func:`_keep_neutral`)."""


def _keep_neutral(neutral) -> None:
    _NEUTRAL[:] = [neutral]


def _prepare_kept(*job):
    return _prepare_file(_NEUTRAL[0], *job)


def _prepare_file(neutral, scan_path: Path, landmark_path: Path, scale: float, mesh_spacing: float | None):
    """One expression scan read and prepared on ``neutral`` (errors name the scan and the landmark file)."""
    from livebridge.retarget.face_scan import prepare_expression
    from livebridge.retarget.point_files import read_points
    from livebridge.retarget.scan import read_scan

    return prepare_expression(read_scan(scan_path, scale), read_points(landmark_path, scale), neutral, scan_path,
                              landmark_path, mesh_spacing)
