"""First labelling: assign unlabelled 3D points of the neutral frame to the model's markers.

The capture frame and the model frame differ by an unknown similarity (the performer's head can be
turned, moved and scaled relative to the model). Rotation hypotheses on a grid (every
``step_deg`` up to ``max_angle_deg`` about each axis) are scored by truncated nearest-neighbour
distances after centring and scaling; the best few are refined by alternating Hungarian
assignment (:func:`scipy.optimize.linear_sum_assignment`, gated) and an Umeyama similarity fit
until the assignment stops changing. The best refined hypothesis wins.

Without a prior, a marker seen by only two cameras is ambiguous: when two such markers lie near one
epipolar plane their detections can pair crosswise into two ghost points, and the marker is never
triangulated. :func:`guided_first_labelling` therefore runs the correspondence twice: once blind,
then - after the similarity alignment from the confident assignments - again with the aligned
model markers as predictions, so their own detections pair up. :func:`complete_labelling` then
assigns the remaining points to the remaining markers by gated Hungarian assignment in the aligned
frame, with a gate scaled to the residual of the fit and a uniqueness check (no other marker near
the point, no other point near the marker): a wrong first label is worse than a missing one, as
the tracker keeps labels.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from livebridge.geometry.transforms import apply, umeyama

UNMATCHED_COST = 1e6


@dataclass(frozen=True, eq=False)
class Labelling:
    """Result of the first labelling.

    Attributes
    ----------
    labels : ndarray of int, shape (n_points,)
        Marker index of each captured point, -1 for points left unlabelled (strays).
    capture2model : ndarray, shape (4, 4)
        Similarity transform from the capture (world) frame to the model frame.
    rms_mm : float
        RMS distance between matched points and their markers after alignment (model mm).
    n_matched : int
    """

    labels: np.ndarray
    capture2model: np.ndarray
    rms_mm: float
    n_matched: int

    def marker_points(self, points_3d: np.ndarray, n_markers: int) -> np.ndarray:
        """Captured positions per marker, shape (n_markers, 3); NaN for markers not matched."""
        out = np.full((n_markers, 3), np.nan)
        matched = self.labels >= 0
        out[self.labels[matched]] = np.asarray(points_3d)[matched]
        return out


def gated_assignment(cost: np.ndarray, gate: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optimal assignment of rows to columns, pairs above the gate forbidden.

    Parameters
    ----------
    cost : ndarray, shape (n_rows, n_cols)
    gate : float or ndarray, shape (n_rows,)
        Largest allowed cost per row.

    Returns
    -------
    rows, cols : ndarray of int, the accepted pairs.
    """
    if cost.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    gate = np.broadcast_to(np.asarray(gate, dtype=np.float64).reshape(-1, 1), (cost.shape[0], 1))
    allowed = cost <= gate
    rows_any = allowed.any(axis=1)
    cols_any = allowed.any(axis=0)
    r_index, c_index = np.flatnonzero(rows_any), np.flatnonzero(cols_any)
    if len(r_index) == 0 or len(c_index) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    sub = np.where(allowed[np.ix_(r_index, c_index)], cost[np.ix_(r_index, c_index)], UNMATCHED_COST)
    rows, cols = linear_sum_assignment(sub)
    ok = sub[rows, cols] < UNMATCHED_COST
    return r_index[rows[ok]], c_index[cols[ok]]


def _hypotheses(max_angle_deg: float, step_deg: float) -> np.ndarray:
    """Rotation matrices on an Euler grid, shape (n, 3, 3)."""
    angles = np.arange(-max_angle_deg, max_angle_deg + 1e-9, step_deg)
    grid = np.array(list(itertools.product(angles, angles, angles)))
    return Rotation.from_euler("xyz", grid, degrees=True).as_matrix()


def first_labelling(points_3d: np.ndarray, model_points: np.ndarray, gate_mm: float = 6.0,
                    max_angle_deg: float = 30.0, step_deg: float = 7.5, n_refine: int = 6,
                    max_iterations: int = 30) -> Labelling:
    """Label the captured neutral frame against the model's markers.

    Parameters
    ----------
    points_3d : ndarray, shape (n_points, 3)
        Unlabelled captured points (world frame, mm), strays included; NaN rows ignored.
    model_points : ndarray, shape (n_markers, 3)
        Marker positions on the neutral model (model frame, mm).
    gate_mm : float
        Largest distance (model mm, after alignment) at which a point may take a marker's label.
    max_angle_deg, step_deg : float
        Rotation hypotheses: every ``step_deg`` within ``±max_angle_deg`` about x, y and z.
    n_refine : int
        How many of the best hypotheses are refined by assignment + similarity.
    max_iterations : int

    Returns
    -------
    Labelling
    """
    points_3d = np.asarray(points_3d, dtype=np.float64)
    model_points = np.asarray(model_points, dtype=np.float64)
    labels = np.full(len(points_3d), -1, dtype=np.int64)
    finite = np.flatnonzero(np.isfinite(points_3d).all(axis=1))
    if len(finite) < 3:
        return Labelling(labels, np.full((4, 4), np.nan), np.inf, 0)
    capture = points_3d[finite]
    model_center = np.median(model_points, axis=0)
    capture_center = np.median(capture, axis=0)
    scale = np.median(np.linalg.norm(model_points - model_center, axis=1)) / max(
        np.median(np.linalg.norm(capture - capture_center, axis=1)), 1e-9)
    tree = cKDTree(model_points)
    rotations = _hypotheses(max_angle_deg, step_deg)
    # capture -> model under each hypothesis: R (s (p - c_capture)) + c_model
    moved = np.einsum("hij,nj->hni", rotations, scale * (capture - capture_center)) + model_center
    distance, _ = tree.query(moved.reshape(-1, 3))
    score = (np.minimum(distance.reshape(len(rotations), -1), 2 * gate_mm) ** 2).sum(axis=1)
    best = None
    for h in np.argsort(score)[:n_refine]:
        transform = np.eye(4)
        transform[:3, :3] = scale * rotations[h]
        transform[:3, 3] = model_center - scale * rotations[h] @ capture_center
        result = _refine(capture, model_points, transform, gate_mm, max_iterations)
        if best is None or (result[2], -result[3]) > (best[2], -best[3]):
            best = result
    transform, pairs, n_matched, rms = best
    labels[finite[pairs[0]]] = pairs[1]
    return Labelling(labels, transform, rms, n_matched)


def _refine(capture, model_points, transform, gate_mm, max_iterations):
    """Alternate gated Hungarian assignment and similarity fit from a starting ``capture2model``."""
    previous = None
    gate = 3 * gate_mm
    for iteration in range(max_iterations):
        moved = apply(transform, capture)
        cost = np.linalg.norm(moved[:, None] - model_points[None], axis=-1)
        rows, cols = gated_assignment(cost, gate)
        if len(rows) < 3:
            return transform, (rows, cols), 0, np.inf
        key = (tuple(rows), tuple(cols))
        if key == previous and gate == gate_mm:
            break
        previous = key
        transform = umeyama(capture[rows], model_points[cols], with_scale=True)
        if iteration >= 2:
            gate = gate_mm  # coarse gate for the first steps, then the real one
    moved = apply(transform, capture)
    cost = np.linalg.norm(moved[:, None] - model_points[None], axis=-1)
    rows, cols = gated_assignment(cost, gate_mm)
    rms = float(np.sqrt(np.mean(cost[rows, cols] ** 2))) if len(rows) else np.inf
    return transform, (rows, cols), len(rows), rms


CHI2_3_MEDIAN = 2.365974  # median of the chi-squared distribution with 3 degrees of freedom


def robust_rms(residual: np.ndarray) -> float:
    """RMS of 3D residual lengths estimated from their median (isotropic Gaussian errors), robust to outliers.

    ``residual (n,)`` distances; ``sqrt(3 median(r²) / χ²₃ median)``, NaN when empty.
    """
    residual = np.asarray(residual, dtype=np.float64)
    if not len(residual):
        return float("nan")
    return float(np.sqrt(3.0 * np.median(residual**2) / CHI2_3_MEDIAN))


def complete_labelling(points_3d: np.ndarray, model_points: np.ndarray, confident: Labelling,
                       gate_mm: float = 6.0, residual_factor: float = 8.0, min_gate_mm: float = 0.5,
                       ratio: float = 3.0, max_iterations: int = 5) -> Labelling:
    """Labels for a (new) point set of the same frame, starting from a confident labelling's alignment.

    In the aligned frame every marker takes a point only within the *residual gate*
    ``g = clip(residual_factor * r, min_gate_mm, gate_mm)``, where ``r`` is the robust RMS
    (:func:`robust_rms`) of the current assignment's residuals (at first: the confident labelling's
    markers, each matched within ``gate_mm``), so an outlier (a ghost point near a marker seen by
    one camera) neither widens the gate nor keeps its label. A pair ``(point, marker)`` at distance
    ``d`` must also be unique: every other marker farther than ``max(g, ratio * d)`` from the point
    and every other point farther than that from the marker. One gated Hungarian assignment
    (:func:`gated_assignment`) picks the pairs; the similarity is refitted on them and the
    assignment repeated until it stops changing.

    Parameters
    ----------
    points_3d : ndarray, shape (n_points, 3)
        Captured points of the frame (world, mm), strays included; NaN rows ignored.
    model_points : ndarray, shape (n_markers, 3)
    confident : Labelling
        A labelling of the same frame (possibly of another point set of it): its ``capture2model``
        and the set of markers it matched are used.
    gate_mm : float
        Largest gate (model mm).
    residual_factor, min_gate_mm, ratio : float
    max_iterations : int

    Returns
    -------
    Labelling
        Of ``points_3d``; ``rms_mm`` over its pairs.
    """
    points_3d = np.asarray(points_3d, dtype=np.float64)
    model_points = np.asarray(model_points, dtype=np.float64)
    labels = np.full(len(points_3d), -1, dtype=np.int64)
    finite = np.flatnonzero(np.isfinite(points_3d).all(axis=1))
    transform = confident.capture2model
    if len(finite) < 3 or not np.isfinite(transform).all():
        return Labelling(labels, transform, np.inf, 0)
    capture = points_3d[finite]
    known = np.zeros(len(model_points), dtype=bool)
    known[confident.labels[confident.labels >= 0]] = True
    cost = np.linalg.norm(apply(transform, capture)[:, None] - model_points[None], axis=-1)  # (p, m)
    rows, cols = gated_assignment(np.where(known[None], cost, np.inf), gate_mm)
    previous = None
    for _ in range(max_iterations):
        if len(rows) < 3:
            break
        gate = float(np.clip(residual_factor * robust_rms(cost[rows, cols]), min_gate_mm, gate_mm))
        # uniqueness: within max(gate, ratio * d) of a pair, neither another marker nor another point
        d = np.where(cost <= gate, cost, np.inf)
        radius = np.maximum(gate, ratio * d)
        sorted_rows = np.sort(cost, axis=1)
        sorted_cols = np.sort(cost, axis=0)
        second_marker = np.where(cost <= sorted_rows[:, :1], sorted_rows[:, 1:2] if cost.shape[1] > 1 else np.inf,
                                 sorted_rows[:, :1])  # nearest other marker to each point, per pair
        second_point = np.where(cost <= sorted_cols[:1], sorted_cols[1:2] if cost.shape[0] > 1 else np.inf,
                                sorted_cols[:1])  # nearest other point to each marker, per pair
        allowed = np.isfinite(d) & (second_marker > radius) & (second_point > radius)
        rows_new, cols_new = gated_assignment(np.where(allowed, cost, np.inf), np.finfo(np.float64).max)
        key = (tuple(rows_new), tuple(cols_new))
        rows, cols = rows_new, cols_new
        if key == previous or len(rows) < 3:
            break
        previous = key
        refit = umeyama(capture[rows], model_points[cols], with_scale=True)
        if not np.isfinite(refit).all():
            break
        transform = refit
        cost = np.linalg.norm(apply(transform, capture)[:, None] - model_points[None], axis=-1)
    if len(rows) < 3:
        return Labelling(labels, transform, np.inf, 0)
    labels[finite[rows]] = cols
    residual = np.linalg.norm(apply(transform, capture[rows]) - model_points[cols], axis=-1)
    return Labelling(labels, transform, float(np.sqrt(np.mean(residual**2))), len(rows))


def guided_first_labelling(find_points: Callable[[np.ndarray | None], np.ndarray], model_points: np.ndarray,
                           gate_mm: float = 6.0, max_angle_deg: float = 30.0, step_deg: float = 7.5,
                           residual_factor: float = 8.0, min_gate_mm: float = 0.5,
                           ratio: float = 3.0) -> tuple[np.ndarray, Labelling]:
    """First labelling of a neutral frame set, with a model-guided second correspondence.

    ``find_points(None)`` gives the blind correspondence's points, labelled by
    :func:`first_labelling`; ``find_points(predicted)``, with the model markers carried into the
    capture frame by that alignment (``predicted (n_markers, 3)``, world mm), gives the guided
    points, which :func:`complete_labelling` labels. The blind labelling is returned instead only
    when the guided one matches fewer than 3 markers or fewer than half as many.

    Parameters
    ----------
    find_points : callable
        ``find_points(predicted (n_markers, 3) or None) -> points_3d (n_points, 3)`` (world mm):
        correspondence + triangulation of the frame set, with tracker-style predictions.
    model_points : ndarray, shape (n_markers, 3)
    gate_mm, max_angle_deg, step_deg : float
        As in :func:`first_labelling`.
    residual_factor, min_gate_mm, ratio : float
        As in :func:`complete_labelling`.

    Returns
    -------
    (points_3d (n_points, 3), Labelling)
        The points the labels index and their labelling.
    """
    model_points = np.asarray(model_points, dtype=np.float64)
    points = np.asarray(find_points(None), dtype=np.float64).reshape(-1, 3)
    first = first_labelling(points, model_points, gate_mm=gate_mm, max_angle_deg=max_angle_deg, step_deg=step_deg)
    if first.n_matched < 3 or not np.isfinite(first.capture2model).all():
        return points, first
    predicted = apply(np.linalg.inv(first.capture2model), model_points)
    guided = np.asarray(find_points(predicted), dtype=np.float64).reshape(-1, 3)
    labelling = complete_labelling(guided, model_points, first, gate_mm=gate_mm, residual_factor=residual_factor,
                                   min_gate_mm=min_gate_mm, ratio=ratio)
    if labelling.n_matched < max(3, (first.n_matched + 1) // 2):
        return points, first
    return guided, labelling
