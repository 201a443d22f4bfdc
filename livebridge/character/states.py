"""CR states of a frame for a character: per region the one active muscle and its level.

A character's regions list their muscles: basis muscles (``jaw``) and pseudo-muscles, co-articulated
combinations trained as one. A pseudo-muscle's actuation (what it means in basis contractions at full level)
is given (a markerless model knows it: ``"zygomatic+risorius"`` -> both zygomatics at 1, both risorii at
0.5), or read from a name ``"a+b"`` (each component at 1). The state per frame comes from the markerless
analysis directly (a character filled from the same model has the model's regions), or from contractions,
the one signal every input produces, so any performer and any capture method drives any character: per
region the candidate whose actuation ``v``, scaled by a level ``l``, best explains the contractions ``x`` in
least squares (``l = x.v / v.v``; the squared residual falls by ``(x.v)^2 / v.v``, so the winner maximises
that), neutral when no candidate explains anything.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError

NEUTRAL = -1
"""The muscle index of a region in its neutral state."""


@dataclass(frozen=True, eq=False)
class CRStates:
    """One frame's state of every region of a character, in the character's region order.

    Attributes
    ----------
    muscle : ndarray of int, shape (n_regions,)
        Index into the region's muscles, :data:`NEUTRAL` (-1) for neutral.
    level : ndarray of float, shape (n_regions,)
        Fraction of full actuation in [0, 1] (0 where neutral).
    """

    muscle: np.ndarray
    level: np.ndarray

    @classmethod
    def neutral(cls, n_regions: int) -> CRStates:
        return cls(np.full(n_regions, NEUTRAL, np.int64), np.zeros(n_regions))


def components(muscle: str) -> tuple[str, ...]:
    """The basis muscles of a (pseudo-)muscle name: ``"a+b"`` -> ``("a", "b")``."""
    return tuple(part.strip() for part in muscle.split("+"))


def actuation_matrix(muscles: Sequence[str], muscle_names: Sequence[str],
                     actuations: Mapping[str, Mapping[str, float]] | None = None, where: str = "") -> np.ndarray:
    """Per candidate its actuation in basis contractions, shape (n_candidates, n_muscles).

    Parameters
    ----------
    muscles : sequence of str
        A region's muscles and pseudo-muscles.
    muscle_names : sequence of str
        The basis muscles.
    actuations : mapping, optional
        Pseudo-muscle -> {basis muscle: level at full actuation}; others are read from their names.
    where : str
        Names the region in errors.

    Raises
    ------
    InputError
        A candidate names a muscle the basis does not have.
    """
    index = {name: i for i, name in enumerate(muscle_names)}
    matrix = np.zeros((len(muscles), len(muscle_names)))
    for j, muscle in enumerate(muscles):
        parts = dict(actuations[muscle]) if actuations and muscle in actuations else \
            {part: 1.0 for part in components(muscle)}
        for part, value in parts.items():
            if part not in index:
                raise InputError(f"{where}muscle {muscle!r}: {part!r} is no muscle of the basis "
                                 f"({', '.join(muscle_names)})", field="muscles")
            matrix[j, index[part]] = float(value)
    return matrix


class ContractionStates:
    """Maps contractions of a basis to a character's CR states (rule in the module docstring).

    Parameters
    ----------
    region_muscles : sequence of sequence of str
        Per region of the character, its muscles (pseudo-muscles as ``"a+b"`` or named in ``actuations``).
    muscle_names : sequence of str
        The basis muscles, in the order of the contraction vectors.
    actuations : sequence of mapping, optional
        Per region, pseudo-muscle -> {basis muscle: level} (see :func:`actuation_matrix`).

    Raises
    ------
    InputError
        A region's muscle has a component the basis does not have.
    """

    def __init__(self, region_muscles: Sequence[Sequence[str]], muscle_names: Sequence[str],
                 actuations: Sequence[Mapping[str, Mapping[str, float]]] | None = None):
        self.n_regions = len(region_muscles)
        n_candidates = max((len(m) for m in region_muscles), default=1)
        # (n_regions, n_candidates, n_muscles); padding rows stay zero and never win
        self._vectors = np.zeros((self.n_regions, n_candidates, len(muscle_names)))
        for r, muscles in enumerate(region_muscles):
            given = actuations[r] if actuations is not None else None
            self._vectors[r, :len(muscles)] = actuation_matrix(muscles, muscle_names, given, f"region {r} ")
        norms = np.square(self._vectors).sum(axis=2)
        self._inverse_norms = np.divide(1.0, norms, out=np.zeros_like(norms), where=norms > 0)

    def __call__(self, contractions: np.ndarray) -> CRStates:
        """CR states for ``contractions (n_muscles,)`` (non-finite values count as 0)."""
        x = np.nan_to_num(np.asarray(contractions, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        along = self._vectors @ x  # (n_regions, n_candidates): x . v
        levels = along * self._inverse_norms
        scores = np.where(along > 0, along * levels, 0.0)
        best = np.argmax(scores, axis=1)
        rows = np.arange(self.n_regions)
        active = scores[rows, best] > 0.0
        muscle = np.where(active, best, NEUTRAL)
        level = np.where(active, np.clip(levels[rows, best], 0.0, 1.0), 0.0)
        return CRStates(muscle.astype(np.int64), level)


def states_from_regions(region_names: Sequence[str], region_states) -> CRStates | None:
    """CR states from the markerless analysis's per-region states, or None when its regions are not these.

    Parameters
    ----------
    region_names : sequence of str
        The character's regions, in order.
    region_states : sequence of RegionState
        Each with ``region`` (name), ``muscle`` (index into the region's muscles, -1 neutral) and ``level``.
    """
    by_name = {state.region: state for state in region_states}
    if set(by_name) != set(region_names):
        return None
    muscle = np.array([int(by_name[name].muscle) for name in region_names], dtype=np.int64)
    level = np.array([float(by_name[name].level) for name in region_names])
    level = np.where(np.isfinite(level), np.clip(level, 0.0, 1.0), 0.0)
    return CRStates(np.where(level > 0, muscle, NEUTRAL), np.where(muscle >= 0, level, 0.0))
