"""CR states of a frame for a character: per region the one active muscle and its level.

A character's regions list their muscles: basis muscles (``jaw``) and pseudo-muscles, co-articulated
combinations trained as one (``frontalis_L+corrugator_L``). Its state per frame comes from the markerless
analysis directly (a character filled from the same model has the model's regions), or from contractions,
the one signal every input produces, so any performer and any capture method drives any character: per
region the muscle (or pseudo-muscle) ``S`` whose uniform level ``l`` best explains the region's
contractions in least squares (``l`` = the mean contraction over ``S``; the residual is
``sum_R x^2 - |S| l^2``, so the winner maximises ``|S| l^2``), neutral when every contraction is zero.
"""

from __future__ import annotations

from collections.abc import Sequence
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


class ContractionStates:
    """Maps contractions of a basis to a character's CR states (rule in the module docstring).

    Parameters
    ----------
    region_muscles : sequence of sequence of str
        Per region of the character, its muscles (pseudo-muscles as ``"a+b"``).
    muscle_names : sequence of str
        The basis muscles, in the order of the contraction vectors.

    Raises
    ------
    InputError
        A region's muscle has a component the basis does not have.
    """

    def __init__(self, region_muscles: Sequence[Sequence[str]], muscle_names: Sequence[str]):
        index = {name: i for i, name in enumerate(muscle_names)}
        self.n_regions = len(region_muscles)
        self.n_candidates = max((len(m) for m in region_muscles), default=0)
        n = len(muscle_names)
        # membership (n_regions, n_candidates, n_muscles): 1 where muscle i is a component of candidate j
        self._members = np.zeros((self.n_regions, max(self.n_candidates, 1), n))
        for r, muscles in enumerate(region_muscles):
            for j, muscle in enumerate(muscles):
                for part in components(muscle):
                    if part not in index:
                        raise InputError(f"region {r} muscle {muscle!r}: {part!r} is no muscle of the basis "
                                         f"({', '.join(muscle_names)})", field="muscles")
                    self._members[r, j, index[part]] = 1.0
        self._sizes = self._members.sum(axis=2)  # (n_regions, n_candidates), 0 for padding

    def __call__(self, contractions: np.ndarray) -> CRStates:
        """CR states for ``contractions (n_muscles,)`` (non-finite values count as 0)."""
        x = np.nan_to_num(np.asarray(contractions, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        sums = self._members @ x  # (n_regions, n_candidates)
        levels = np.divide(sums, self._sizes, out=np.zeros_like(sums), where=self._sizes > 0)
        scores = self._sizes * np.square(np.clip(levels, 0.0, None))
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
