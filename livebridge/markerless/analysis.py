"""Per-frame analysis: each co-articulation region's muscle state, then muscle contractions.

Per CR ``j`` and frame (the paper's equations 2-4): ``c = M_j x`` (one matrix product over the region's
pixels of the normalised image), ``sigma = c / |c|``; per muscle ``i`` of the CR the best state
``omega_i = argmax_n sigma . Phi_i(n)`` and its score ``alpha_i``; the active muscle is the one of best
score (one active muscle per CR), the others are at rest.

Beyond the paper:

- the level is interpolated between the best state and its better neighbour (``sigma`` projected on the
  chord between their signatures), so contractions are not quantised to the training states;
- each region reports a confidence in [0, 1]: the best score, lowered when the sample's norm is far from
  the training samples' (not a face like the trained one);
- a region whose confidence falls below ``min_confidence``, or every region when the head rig's LEDs are
  lost, holds its last state (flagged ``held``);
- contractions come from the regions: a (pseudo-)muscle active at level ``l`` gives ``l`` times its
  actuation vector to the basis muscles the region reports; a muscle reported by several regions takes their
  weighted median, weighted by the share of its region of influence in each (a region that sees little of a
  muscle says little about it; one region misreading it, a leak from a neighbour's gesture or a partial view,
  does not move it), over the regions that see the face now: a held region's stale state counts only where
  every region reporting the muscle is held; the result is finite and in [0, 1] whatever the input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.markerless.model import MarkerlessModel, RegionModel
from livebridge.markerless.normalise import NormalisedFrame


@dataclass(frozen=True)
class RegionState:
    """The state of one CR in one frame.

    Attributes
    ----------
    region : str
    muscle : int
        Index into ``RegionModel.muscles`` of the active muscle; -1: neutral.
    level : float
        Fraction of full actuation in [0, 1] (state / (n_states - 1), interpolated between states).
    confidence : float
        In [0, 1].
    held : bool
        The state is the last trusted one, held (low confidence or lost LEDs).
    """

    region: str
    muscle: int
    level: float
    confidence: float
    held: bool = False


@dataclass(frozen=True, eq=False)
class MarkerlessResult:
    """One analysed frame.

    Attributes
    ----------
    regions : tuple of RegionState
    contractions : ndarray, shape (n_muscles,)
        Finite, in [0, 1].
    held : ndarray, shape (n_muscles,), bool
        Muscles whose value comes from a held region.
    lost : bool
        The LEDs (the face) were lost in this frame.
    """

    regions: tuple[RegionState, ...]
    contractions: np.ndarray
    held: np.ndarray
    lost: bool

    @property
    def quality(self) -> tuple[tuple[str, float], ...]:
        """(region, confidence) per region."""
        return tuple((state.region, state.confidence) for state in self.regions)

    @property
    def mean_confidence(self) -> float:
        return float(np.mean([s.confidence for s in self.regions])) if self.regions else 0.0


@dataclass(frozen=True, eq=False)
class AnalysisState:
    """Between frames: the last trusted state of each region (None before the first)."""

    last: tuple[RegionState, ...] | None = None


class _RegionTables:
    """One region's arrays laid out for the per-frame path (float32, signatures padded per muscle)."""

    def __init__(self, region: RegionModel):
        self.name = region.name
        self.pixels = region.pixels
        self.back = np.ascontiguousarray(region.back, dtype=np.float32)
        n_muscles, max_states = len(region.muscles), max(region.n_states)
        k = self.back.shape[0]
        self.phi = np.zeros((n_muscles, max_states, k), dtype=np.float32)
        self.pad = np.full((n_muscles, max_states), -np.inf, dtype=np.float32)
        for i, signature in enumerate(region.signatures):
            self.phi[i, :len(signature)] = signature
            self.pad[i, :len(signature)] = 0.0
        self.n_states = np.array(region.n_states)
        self.actuations = np.asarray(region.actuations, dtype=np.float64)
        self.weights = np.asarray(region.weights, dtype=np.float64)
        self.reports = self.weights > 0
        self.sample_norm = float(region.sample_norm)


def _interpolated_level(phi: np.ndarray, scores: np.ndarray, sigma: np.ndarray, best: int, n_states: int) -> float:
    """Level of state ``best`` moved towards its better-scoring neighbour by ``sigma``'s projection."""
    if n_states <= 1:
        return 0.0
    neighbours = [n for n in (best - 1, best + 1) if 0 <= n < n_states]
    other = max(neighbours, key=lambda n: scores[n])
    chord = phi[other] - phi[best]
    length2 = float(chord @ chord)
    step = float((sigma - phi[best]) @ chord) / length2 if length2 > 0 else 0.0
    position = best + (other - best) * min(max(step, 0.0), 1.0)
    return position / (n_states - 1)


def classify_region(tables: _RegionTables, sample: np.ndarray) -> RegionState:
    """The state of one region from its pixels.

    Parameters
    ----------
    tables : _RegionTables
    sample : ndarray, shape (n_pixels,), float32
        The region's pixels of the normalised image.
    """
    coords = tables.back @ sample
    norm = float(np.sqrt(coords @ coords))
    if not np.isfinite(norm) or norm == 0.0:
        return RegionState(tables.name, -1, 0.0, 0.0)
    sigma = coords / np.float32(norm)
    scores = tables.phi @ sigma + tables.pad  # (n_muscles, max_states)
    states = np.argmax(scores, axis=1)
    alphas = scores[np.arange(len(states)), states]
    active = int(np.argmax(alphas))
    best = int(states[active])
    alpha = float(alphas[active])
    sample_norm = float(np.sqrt(sample @ sample))
    ratio = min(sample_norm, tables.sample_norm) / max(sample_norm, tables.sample_norm, 1e-12)
    confidence = min(max(alpha, 0.0), 1.0) * ratio
    if best == 0:
        return RegionState(tables.name, -1, 0.0, confidence)
    level = _interpolated_level(tables.phi[active], scores[active], sigma, best, int(tables.n_states[active]))
    return RegionState(tables.name, active, level, confidence)


class Analyser:
    """Turns normalised frames into region states and contractions with a trained model.

    Parameters
    ----------
    model : MarkerlessModel
    min_confidence : float
        Regions below it hold their last trusted state.
    """

    def __init__(self, model: MarkerlessModel, min_confidence: float = 0.3):
        self.model = model
        self.min_confidence = float(min_confidence)
        self.tables = [_RegionTables(region) for region in model.regions]

    def initial_state(self) -> AnalysisState:
        return AnalysisState()

    def step(self, state: AnalysisState, frame: NormalisedFrame) -> tuple[AnalysisState, MarkerlessResult]:
        """Analyse one normalised frame.

        Parameters
        ----------
        state : AnalysisState
        frame : NormalisedFrame
            ``frame.filtered`` of shape ``model.image_size[::-1]``.

        Returns
        -------
        (AnalysisState, MarkerlessResult)
        """
        flat = np.ascontiguousarray(frame.filtered, dtype=np.float32).ravel()
        if not np.isfinite(flat).all():
            flat = np.nan_to_num(flat, nan=0.0, posinf=0.0, neginf=0.0)
        last = state.last or tuple(RegionState(t.name, -1, 0.0, 0.0) for t in self.tables)
        current = []
        for tables, previous in zip(self.tables, last):
            if frame.lost:
                seen = RegionState(tables.name, -1, 0.0, 0.0)
            else:
                with np.errstate(over="ignore", invalid="ignore"):  # absurd pixels: confidence 0, held below
                    seen = classify_region(tables, flat[tables.pixels])
            if frame.lost or seen.confidence < self.min_confidence:
                seen = RegionState(tables.name, previous.muscle, previous.level, seen.confidence, held=True)
            current.append(seen)
        current = tuple(current)
        contractions, held = self.contractions(current)
        trusted = tuple(RegionState(s.region, s.muscle, s.level, s.confidence) for s in current)
        return AnalysisState(trusted), MarkerlessResult(current, contractions, held, frame.lost)

    def contractions(self, states: tuple[RegionState, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Basis contractions (n_muscles,) in [0, 1] and held flags (n_muscles,) from region states."""
        n, k = self.model.n_muscles, len(self.tables)
        readings, weights = np.zeros((k, n)), np.zeros((k, n))
        held = np.array([state.held for state in states], dtype=bool)
        for r, (tables, region_state) in enumerate(zip(self.tables, states)):
            weights[r] = tables.weights
            if region_state.muscle >= 0:
                level = min(max(region_state.level, 0.0), 1.0)
                readings[r] = level * tables.actuations[region_state.muscle]
        # a region held for long (one the head's turn took out of view) would otherwise keep adding its last
        # state: in `livebridge bench markerless` one held a cheek at 0.25 through every later gesture
        seen = (weights[~held] > 0).any(axis=0)
        weights = np.where(held[:, None] == ~seen[None, :], weights, 0.0)
        values = _weighted_median(np.nan_to_num(readings, nan=0.0, posinf=0.0, neginf=0.0), weights)
        return np.clip(values, 0.0, 1.0), ~seen & (weights > 0).any(axis=0)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per column of ``values`` (k, n), the value where the cumulative ``weights`` (k, n; >= 0) of the sorted
    values first reach half their total (midway to the next value where they reach exactly half, as two
    regions of equal weight do), shape (n,); 0 for a column without weight.

    In `livebridge bench markerless` (held-out takes) it took the isolated gestures' MAE from 0.0047 (the
    weighted mean) to 0.0035: the lip press, read 0.62-1.00 by its four regions, no longer came out at 0.83;
    the everyday expressions' went from 0.0189 to 0.0197."""
    if not len(values):
        return np.zeros(values.shape[1:])
    order = np.argsort(values, axis=0)
    cumulative = np.cumsum(np.take_along_axis(weights, order, axis=0), axis=0)
    total = cumulative[-1]
    half = 0.5 * total
    first = np.argmax(cumulative >= half - 1e-12 * total, axis=0)
    sorted_values = np.take_along_axis(values, order, axis=0)
    columns = np.arange(values.shape[1])
    median = sorted_values[first, columns]
    following = sorted_values[np.minimum(first + 1, len(values) - 1), columns]
    exactly = np.abs(cumulative[first, columns] - half) <= 1e-12 * total
    median = np.where(exactly, 0.5 * (median + following), median)
    return np.where(total > 0, median, 0.0)
