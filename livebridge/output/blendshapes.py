"""The muscle -> blendshape map every blendshape output shares (VMC/OSC, Live Link Face): one map, two transports.

Muscles become blendshapes through a linear map: each muscle drives one or more blendshapes with weights,
and a blendshape's value is the weighted sum, clipped to [0, 1]. The default map sends the 16 Choe-Ko
muscles to Apple ARKit blendshape names (the names Perfect-Sync avatars, VSeeFace and Unreal's Live Link
Face use); receivers differ in case, so the names can be written ``camel`` (``browInnerUp``, ARKit's own
spelling), ``pascal`` (``BrowInnerUp``), ``lower`` (``browinnerup``) or ``snake`` (``brow_inner_up``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np

from livebridge.errors import InputError

CASES = ("camel", "pascal", "lower", "snake")

# Choe-Ko muscle -> ARKit blendshapes (from the ICT-FaceKit shapes the reference basis is built from).
ARKIT_MAPPING: dict[str, dict[str, float]] = {
    "frontalis_L": {"browInnerUp": 0.5, "browOuterUpLeft": 1.0},
    "frontalis_R": {"browInnerUp": 0.5, "browOuterUpRight": 1.0},
    "corrugator_L": {"browDownLeft": 1.0},
    "corrugator_R": {"browDownRight": 1.0},
    "orbicularis_oculi_L": {"eyeBlinkLeft": 1.0},
    "orbicularis_oculi_R": {"eyeBlinkRight": 1.0},
    "levator_labii_L": {"noseSneerLeft": 1.0},
    "levator_labii_R": {"noseSneerRight": 1.0},
    "zygomatic_major_L": {"mouthSmileLeft": 1.0},
    "zygomatic_major_R": {"mouthSmileRight": 1.0},
    "risorius_L": {"mouthStretchLeft": 1.0},
    "risorius_R": {"mouthStretchRight": 1.0},
    "depressor_anguli_oris": {"mouthFrownLeft": 1.0, "mouthFrownRight": 1.0},
    "orbicularis_oris": {"mouthPucker": 1.0},
    "lips_pressor": {"mouthPressLeft": 1.0, "mouthPressRight": 1.0},
    "jaw": {"jawOpen": 1.0},
}


def convert_case(name: str, case: str) -> str:
    """Spell a camelCase blendshape name in ``case`` (one of :data:`CASES`)."""
    if case == "camel":
        return name[:1].lower() + name[1:]
    if case == "pascal":
        return name[:1].upper() + name[1:]
    if case == "lower":
        return name.lower()
    if case == "snake":
        return re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", name).lower()
    raise InputError(f"case must be one of {CASES}, got {case!r}", field="case")


class BlendshapeMap:
    """Linear map from contractions to blendshape values.

    Parameters
    ----------
    muscle_names : sequence of str, length n_muscles
        The basis's muscles, in order.
    mapping : mapping of str to mapping of str to float, optional
        ``{muscle: {blendshape: weight}}``; default :data:`ARKIT_MAPPING`.
        ``"identity"`` sends each muscle under its own name. Muscles the
        mapping does not name drive nothing; a mapping entry for a muscle the
        basis lacks is an error.
    case : str
        Spelling of the blendshape names, one of :data:`CASES`.

    Attributes
    ----------
    names : tuple of str, length n_blendshapes
    matrix : ndarray, shape (n_blendshapes, n_muscles)
    """

    def __init__(self, muscle_names: Sequence[str], mapping: Mapping | str | None = None, case: str = "camel"):
        muscle_names = tuple(muscle_names)
        if mapping is None:
            mapping = ARKIT_MAPPING
        if mapping == "identity":
            mapping = {name: {name: 1.0} for name in muscle_names}
            case_of = {name: name for name in muscle_names}
        else:
            case_of = None
        if not isinstance(mapping, Mapping):
            raise InputError("mapping must be a table of {muscle = {blendshape = weight}} or 'identity'",
                             field="mapping")
        columns: dict[str, dict[int, float]] = {}
        for muscle, targets in mapping.items():
            if muscle not in muscle_names:
                if mapping is ARKIT_MAPPING:
                    continue  # the default map covers the Choe-Ko muscles a basis may not have
                raise InputError(f"unknown muscle {muscle!r}; the basis has {', '.join(muscle_names)}",
                                 field=f"mapping.{muscle}")
            if not isinstance(targets, Mapping):
                raise InputError("expected a table {blendshape = weight}", field=f"mapping.{muscle}")
            for shape, weight in targets.items():
                if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not np.isfinite(weight):
                    raise InputError(f"weight must be a finite number, got {weight!r}",
                                     field=f"mapping.{muscle}.{shape}")
                name = case_of[shape] if case_of else convert_case(shape, case)
                columns.setdefault(name, {})[muscle_names.index(muscle)] = float(weight)
        self.names = tuple(columns)
        self.matrix = np.zeros((len(self.names), len(muscle_names)))
        for row, weights in enumerate(columns.values()):
            for column, weight in weights.items():
                self.matrix[row, column] += weight

    def __call__(self, contractions: np.ndarray) -> np.ndarray:
        """Blendshape values in [0, 1], shape (n_blendshapes,), from contractions (n_muscles,); NaN -> 0."""
        values = self.matrix @ np.nan_to_num(np.asarray(contractions, dtype=np.float64), nan=0.0)
        return np.clip(values, 0.0, 1.0)

    def rows_for(self, names: Sequence[str]) -> np.ndarray:
        """The map's rows in the order of ``names`` (zero rows for names it does not drive).

        Parameters
        ----------
        names : sequence of str, length n_names
            Blendshape names as this map spells them.

        Returns
        -------
        ndarray, shape (n_names, n_muscles)

        Raises
        ------
        InputError
            When the map drives a blendshape that ``names`` lacks (its value would be lost).
        """
        index = {name: k for k, name in enumerate(names)}
        unknown = [name for name in self.names if name not in index]
        if unknown:
            raise InputError(f"the map drives {unknown[0]!r}, which is not one of the receiver's blendshapes",
                             field="mapping")
        rows = np.zeros((len(index), self.matrix.shape[1]))
        for row, name in enumerate(self.names):
            rows[index[name]] += self.matrix[row]
        return rows
