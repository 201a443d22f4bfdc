"""An actuation basis as a folder of OBJ meshes, for a modelling or game tool (a blendshape per muscle) and back.

``livebridge basis export BASIS --out DIR`` writes ``DIR/neutral.obj``, one ``DIR/MUSCLE.obj`` per muscle (the
neutral face moved by the muscle's full contraction: a blendshape target) and ``DIR/basis.toml``, the manifest
``livebridge basis import DIR/basis.toml`` reads them back with (every muscle's region, side and description
in it). With ``--like MESH.obj`` (the mesh the basis lives on, e.g. the target of ``livebridge retarget
basis``) every file is that OBJ with its vertices moved (:class:`~livebridge.face.obj_file.ObjLayout`): its
texture coordinates, polygons and materials kept, so the shapes drop into the character's rig; otherwise
triangles. Vertices are written in ``units``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.basis_import import MANIFEST_FORMAT, UNITS_TO_MM

NEUTRAL_NAME = "neutral"
MANIFEST_NAME = "basis.toml"


def export_files(basis: Basis, folder: str | Path) -> list[Path]:
    """The files :func:`export_basis` writes into ``folder``: the neutral, one per muscle, the manifest."""
    folder = Path(folder)
    return [folder / f"{name}.obj" for name in (NEUTRAL_NAME, *basis.names)] + [folder / MANIFEST_NAME]


def export_basis(basis: Basis, folder: str | Path, units: str = "mm", like: str | Path | None = None) -> list[Path]:
    """Write ``basis`` into ``folder`` (created if need be) as OBJ meshes in ``units`` and their manifest; returns
    the files written (:func:`export_files`). ``like``: an OBJ of the basis's mesh (its vertices and faces, in
    ``units``) whose layout every file keeps."""
    from livebridge.atomic import write_bytes_atomically
    from livebridge.face.obj_file import mesh_obj
    from livebridge.tomlio import save_toml

    if units not in UNITS_TO_MM:
        raise InputError(f"unknown unit {units!r}; use one of {', '.join(UNITS_TO_MM)}", field="units")
    if NEUTRAL_NAME in basis.names:
        raise InputError(f"a muscle is named {NEUTRAL_NAME!r}, the neutral's file name", field="muscles")
    layout = None if like is None else _checked_like(Path(like), basis, units)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    scale = 1.0 / UNITS_TO_MM[units]
    files = export_files(basis, folder)
    shapes = [basis.neutral, *(basis.neutral + element for element in basis.elements)]
    for path, shape in zip(files, shapes):
        data = mesh_obj(shape * scale, basis.triangles, f"livebridge basis export: {path.stem}, {units}") \
            if layout is None else layout.moved(shape * scale)
        write_bytes_atomically(path, data, "OBJ file")
    save_toml(files[-1], _manifest(basis, units))
    return files


def _checked_like(path: Path, basis: Basis, units: str):
    """The :class:`~livebridge.face.obj_file.ObjLayout` of the OBJ ``path``, refused (naming it) unless it is the
    basis's mesh: its vertices and faces."""
    from livebridge.face.meshio import read_obj
    from livebridge.face.obj_file import ObjLayout

    mesh = read_obj(path)
    if len(mesh.vertices) != basis.n_vertices or not np.array_equal(mesh.triangles, basis.triangles):
        raise InputError(f"not the basis's mesh: {len(mesh.vertices)} vertices and {len(mesh.triangles)} triangles "
                         f"(polygons fanned), the basis {basis.n_vertices} and {len(basis.triangles)}", path)
    off = float(np.abs(mesh.vertices * UNITS_TO_MM[units] - basis.neutral).max())
    if off > 1e-3 * max(float(np.ptp(basis.neutral, axis=0).max()), 1.0):
        raise InputError(f"its vertices lie up to {off:.3g} mm from the basis's neutral read in {units}: another "
                         "mesh, pose or unit (give its unit with --units)", path)
    return ObjLayout.of(path.read_bytes())


def _manifest(basis: Basis, units: str) -> dict:
    """The ``livebridge-basis-manifest`` that imports the exported files: each muscle its own shape."""
    info = {}
    for muscle in basis.muscles:
        entry = {"region": muscle.region, "description": muscle.description}
        if muscle.side is not None:
            entry["side"] = muscle.side
        info[muscle.name] = entry
    return {"format": MANIFEST_FORMAT, "version": 1, "neutral": NEUTRAL_NAME, "suffix": ".obj", "units": units,
            "muscles": {name: {name: 1.0} for name in basis.names}, "info": info}
