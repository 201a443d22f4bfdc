"""ARKit-named shape sets: the 52 ARKit expression shapes as displacement fields on a basis's mesh.

A shape set turns ARKit weights into a face: ``E = E0 + sum_k w_k s_k``; sampled at markers it gives the
marker displacements the contraction solver explains with muscles (:mod:`livebridge.arkit.solve`). Two
sources:

- an artist's ARKit-named shapes (:func:`arkit_shapes_from_deltas`, :func:`load_arkit_shapes`): for
  example the ICT-FaceKit face region, whose 53 expression shapes follow ARKit with ``_L``/``_R`` sides
  (``mouthSmile_L`` is ``mouthSmileLeft``) and split two of ARKit's shapes in halves (``browInnerUp_L`` +
  ``browInnerUp_R`` is ``browInnerUp``, likewise ``cheekPuff``); a name that is neither is refused;
- a basis's own muscles (:func:`arkit_shapes_from_muscles`), for a face without ARKit shapes (the built-in
  face): the shapes with the least total displacement that reproduce every muscle through the shared
  muscle -> blendshape map (``A^T S = E`` for the map ``A (52, n_muscles)`` and the elements ``E``), so
  weights the map makes from contractions ``x`` synthesise exactly ``sum_i x_i e_i``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.arkit.names import ARKIT_INDEX, ARKIT_NAMES
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.npzio import read_npz
from livebridge.output.blendshapes import BlendshapeMap

UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_SIDES = {"L": "Left", "R": "Right"}
_HALVES = ("browInnerUp", "cheekPuff")  # ARKit shapes some rigs sculpt as two halves


@dataclass(frozen=True, eq=False)
class ArkitShapes:
    """The 52 ARKit shapes as displacement fields, in millimetres, in ARKit's order.

    Attributes
    ----------
    deltas : ndarray, shape (52, n_vertices, 3)
        Shape minus neutral; zero for a shape the set does not have.
    present : ndarray of bool, shape (52,)
        The shapes the set has.
    source : str
        Where the shapes came from (for messages).
    """

    deltas: np.ndarray
    present: np.ndarray
    source: str

    @property
    def n_vertices(self) -> int:
        return self.deltas.shape[1]

    @property
    def missing(self) -> tuple[str, ...]:
        """ARKit names the set has no shape for (their weights move nothing)."""
        return tuple(name for name, here in zip(ARKIT_NAMES, self.present) if not here)


def arkit_name(name: str) -> tuple[str, bool]:
    """``(ARKit name, is a half)`` of a shape name: ``mouthSmile_L`` -> ``mouthSmileLeft``, ``browInnerUp_L`` ->
    (``browInnerUp``, True); an ARKit name is itself. Raises InputError for any other name."""
    if name in ARKIT_INDEX:
        return name, False
    match = re.fullmatch(r"(\w+?)_([LR])", name)
    if match:
        base, side = match.groups()
        if base in _HALVES:
            return base, True
        if base + _SIDES[side] in ARKIT_INDEX:
            return base + _SIDES[side], False
    raise InputError(f"{name!r} is not an ARKit blendshape name (nor NAME_L / NAME_R of one)", field="names")


def arkit_shapes_from_deltas(names, deltas: np.ndarray, units: str = "mm", source: str = "") -> ArkitShapes:
    """An ARKit shape set from named displacement fields.

    Parameters
    ----------
    names : sequence of str, length n_shapes
        ARKit names, or ``NAME_L``/``NAME_R`` forms (see the module docstring).
    deltas : ndarray, shape (n_shapes, n_vertices, 3)
        Shape minus neutral, in ``units``.
    units : {"mm", "cm", "m"}
    """
    deltas = np.asarray(deltas, dtype=np.float64)
    names = [str(name) for name in names]
    if deltas.ndim != 3 or deltas.shape[0] != len(names) or deltas.shape[2] != 3:
        raise InputError(f"deltas must have shape ({len(names)}, n_vertices, 3), got {deltas.shape}", source,
                         "deltas")
    if units not in UNITS_TO_MM:
        raise InputError(f"unknown unit {units!r}; use one of {', '.join(UNITS_TO_MM)}", source, "units")
    if not np.isfinite(deltas).all():
        raise InputError("contains NaN or infinity", source, "deltas")
    out = np.zeros((len(ARKIT_NAMES),) + deltas.shape[1:])
    present = np.zeros(len(ARKIT_NAMES), dtype=bool)
    seen: set[str] = set()
    for name, delta in zip(names, deltas):
        if name in seen:
            raise InputError(f"shape {name!r} is given twice", source, "names")
        seen.add(name)
        try:
            target, _ = arkit_name(name)
        except InputError as error:
            raise InputError(error.message, source, "names") from None
        out[ARKIT_INDEX[target]] += delta * UNITS_TO_MM[units]
        present[ARKIT_INDEX[target]] = True
    return ArkitShapes(out, present, source)


def load_arkit_shapes(path: str | Path, units: str = "cm") -> ArkitShapes:
    """ARKit shapes from an ``.npz`` holding ``names (n,)`` and ``deltas (n, n_vertices, 3)`` (the layout of the
    ICT-FaceKit ``face_region.npz``, whose units are centimetres)."""
    path = Path(path)
    arrays = read_npz(path, "named shapes", ("names", "deltas"))
    return arkit_shapes_from_deltas(arrays["names"], arrays["deltas"], units, str(path))


def arkit_shapes_from_muscles(basis: Basis, blend_map: BlendshapeMap | None = None) -> ArkitShapes:
    """The least-displacement ARKit shapes that reproduce each muscle of ``basis`` through ``blend_map``.

    Parameters
    ----------
    basis : Basis
    blend_map : BlendshapeMap, optional
        Camel-case ARKit names; default the shared ARKit map for the basis's muscles.
    """
    blend_map = blend_map or BlendshapeMap(basis.names)
    rows = blend_map.rows_for(ARKIT_NAMES)  # A (52, M)
    elements = basis.elements.reshape(basis.n_muscles, -1)
    shapes = np.linalg.pinv(rows.T) @ elements  # least-norm S with A^T S = E where solvable
    present = np.abs(rows).sum(axis=1) > 0
    return ArkitShapes(shapes.reshape((len(ARKIT_NAMES),) + basis.neutral.shape), present,
                       "synthesised from the basis's muscles")
