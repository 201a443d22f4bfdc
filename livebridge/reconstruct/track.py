"""Per-frame marker tracking: labels kept over time, in the head frame.

Each marker's last known position and velocity are kept in the head (model) frame, and the head
pose is extrapolated at constant velocity; the prediction for a marker is its head-frame position
advanced by its velocity, carried into the world by the predicted head pose. Detections are
assigned by gated optimal assignment (Hungarian); the gate widens while a marker is unseen, so a
marker is picked up again after an occlusion of several frames (its head-frame position does not
drift with head motion). Markers returning from a gap are predicted from the face model when a
displacement matrix is given: contractions are fitted (non-negative least squares) to the markers
tracked continuously, and the returning marker is placed where the model puts it, plus the offset
it had from the model when last seen - neighbouring markers can move in opposite directions
(upper and lower lip), so plain neighbour interpolation would not do. An assignment is refused when
the detection is not clearly nearer its own marker's prediction than any other marker's
(``ratio``) - the situation in which two labels could swap - and the refusals are counted.
Detections that take no label are strays (reflections), ignored and counted. With a face model, a
labelled marker that sits far from where the model puts it (contractions fitted to the frame's other
markers) loses its label: that is how a swap between neighbours after a gap in fast motion shows.
After the assignment the head pose is solved from the rigid head markers (Kabsch, scale fixed),
or, when fewer than three are seen, from all labelled markers.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from livebridge.geometry.transforms import apply, invert, rotation_matrix, rotation_vector
from livebridge.qp import nonnegative_least_squares
from livebridge.reconstruct.label import gated_assignment
from livebridge.reconstruct.stabilize import head_pose


@dataclass(frozen=True)
class TrackConfig:
    """Tracking parameters (mm, frames).

    Attributes
    ----------
    gate_mm : float
        Gate for a marker seen in the previous frame.
    gate_growth_mm : float
        Extra gate per frame the marker has been unseen.
    max_gate_mm : float
        The gate never grows beyond this.
    velocity_frames : int
        A marker unseen for longer than this is predicted without velocity.
    ratio : float
        A point is labelled only if its distance to its marker's prediction is below ``ratio`` times
        its distance to every other marker's prediction.
    lost_frames : int
        After this many frames in a row with fewer than 3 markers labelled (no head pose), the tracker
        is lost: its predictions are no longer trusted and the markers are labelled from scratch
        (:meth:`Tracker.lost`).
    consistency_mm : float or None
        With a face model (``displacement_matrix``): a labelled face marker farther than this (model mm)
        from where the model puts it -- contractions fitted to the frame's labelled markers, plus the
        marker's offset from the model when last seen -- loses its label (see :meth:`Tracker.step`).
        None: no check.
    """

    gate_mm: float = 4.0
    gate_growth_mm: float = 0.75
    max_gate_mm: float = 7.0
    velocity_frames: int = 3
    ratio: float = 0.6
    lost_frames: int = 6
    consistency_mm: float | None = 3.0


@dataclass(frozen=True, eq=False)
class TrackState:
    """Tracker state between frames.

    Attributes
    ----------
    t : float
        Time of the last frame (s).
    positions_model : ndarray, shape (n_markers, 3)
        Last known position of every marker in the model (head) frame.
    velocities_model : ndarray, shape (n_markers, 3)
        Their velocity in the model frame (mm/s).
    unseen : ndarray of int, shape (n_markers,)
        Frames since each marker was last labelled (0: labelled in the last frame).
    head2world : ndarray, shape (4, 4)
        Head pose in the last frame.
    head_motion : ndarray, shape (6,)
        Head velocity, rotation vector (rad/s) then translation (mm/s), of ``head2world`` over time.
    model_offsets : ndarray, shape (n_markers, 3)
        Each marker's offset from the face model's prediction when last seen (model frame).
    starved : int
        Frames in a row with fewer than 3 markers labelled.
    """

    t: float
    positions_model: np.ndarray
    velocities_model: np.ndarray
    unseen: np.ndarray
    head2world: np.ndarray
    head_motion: np.ndarray
    model_offsets: np.ndarray
    starved: int = 0


@dataclass(frozen=True, eq=False)
class TrackFrame:
    """Tracking output of one frame.

    Attributes
    ----------
    labels : ndarray of int, shape (n_points,)
        Marker index of each input point, -1 for strays.
    positions_world : ndarray, shape (n_markers, 3)
        Labelled positions in the world, NaN where unlabelled.
    positions_model : ndarray, shape (n_markers, 3)
        The same in the model (head) frame.
    head2world : ndarray, shape (4, 4)
    n_stray : int
        Input points that took no label.
    n_refused : int
        Assignments refused as possible swaps (swap guard) or dropped by the face-model check.
    """

    labels: np.ndarray
    positions_world: np.ndarray
    positions_model: np.ndarray
    head2world: np.ndarray
    n_stray: int
    n_refused: int


@njit(cache=True, nogil=True)
def _pose_step(head2world: np.ndarray, motion: np.ndarray, dt: float) -> np.ndarray:
    """``head2world`` advanced by ``dt`` seconds of constant motion (rotation about the pose's origin)."""
    out = head2world.copy()
    out[:3, :3] = rotation_matrix(motion[:3] * dt) @ np.ascontiguousarray(head2world[:3, :3])
    out[:3, 3] = head2world[:3, 3] + motion[3:] * dt
    return out


@njit(cache=True, nogil=True)
def _pose_motion(before: np.ndarray, after: np.ndarray, dt: float) -> np.ndarray:
    """Constant motion (6,) taking ``before`` to ``after`` in ``dt`` seconds (inverse of :func:`_pose_step`)."""
    # both carry the same scale s (the alignment's): A B^-1 = (s R_a)(R_b^T / s) = A B^T / s^2
    scale_squared = np.cbrt(np.linalg.det(before[:3, :3])) ** 2
    out = np.empty(6)
    relative = np.ascontiguousarray(after[:3, :3]) @ np.ascontiguousarray(before[:3, :3].T)
    out[:3] = rotation_vector(relative / scale_squared) / dt
    out[3:] = (after[:3, 3] - before[:3, 3]) / dt
    return out


class Tracker:
    """Label tracker for one marker set.

    Parameters
    ----------
    head_mask : ndarray of bool, shape (n_markers,)
        The rigid head-rig markers.
    head_reference_model : ndarray, shape (n_markers, 3)
        Reference positions in the model frame (head rows are used for the head pose).
    model_scale : float
        World mm per model mm (from the coordinate alignment).
    config : TrackConfig
    displacement_matrix : ndarray, shape (n_markers, n_muscles, 3), optional
        The face model's per-marker displacements (``MarkerSet.displacement_matrix``); predicts
        markers returning from a gap. Without it they are predicted at their last position.
    """

    def __init__(self, head_mask: np.ndarray, head_reference_model: np.ndarray, model_scale: float = 1.0,
                 config: TrackConfig = TrackConfig(), displacement_matrix: np.ndarray | None = None):
        self.head_mask = np.asarray(head_mask, dtype=bool)
        self.reference = np.asarray(head_reference_model, dtype=np.float64)
        self.model_scale = float(model_scale)
        self.config = config
        self.displacement = None if displacement_matrix is None else np.asarray(displacement_matrix, dtype=np.float64)
        self._head_reference = np.ascontiguousarray(self.reference[self.head_mask])
        if self.displacement is not None:  # each marker's share of D^T D, for the contraction fits
            self._marker_gram = np.einsum("nmk,nlk->nml", self.displacement, self.displacement)
        # how much each marker stays put on the skull (head markers and those no element moves far), for the
        # pose when fewer than 3 head markers are seen: weight 1 / (1 + (largest element motion / 1 mm)^2)
        reach = np.zeros(len(self.reference)) if self.displacement is None else \
            np.linalg.norm(self.displacement, axis=2).max(axis=1, initial=0.0)
        self._steadiness = np.where(self.head_mask, 1.0, 1.0 / (1.0 + reach**2))

    def pose(self, state: TrackState, world: np.ndarray) -> np.ndarray:
        """``head2world`` from the head markers in ``world (n_markers, 3)``, or with fewer than 3 of them from a
        rigid fit of every labelled marker to its last model-frame position, weighted by how little the face
        model moves it; all NaN with fewer than 3."""
        pose = self.head_pose(world)
        if np.isfinite(pose).all():
            return pose
        # the face moves with the expression: the markers that stay put carry the fit
        return head_pose(state.positions_model, world, self.model_scale, weights=self._steadiness)

    def head_pose(self, world: np.ndarray) -> np.ndarray:
        """``head2world`` ``(4, 4)`` from the head markers' world positions in ``world (n_markers, 3)`` (NaN: unseen);
        all NaN with fewer than 3 of them (:func:`~livebridge.reconstruct.stabilize.head_pose`)."""
        return head_pose(self._head_reference, np.ascontiguousarray(world[self.head_mask]), self.model_scale)

    def start(self, t: float, positions_model: np.ndarray, seen: np.ndarray, head2world: np.ndarray) -> TrackState:
        """Initial state from a labelled first frame.

        Parameters
        ----------
        t : float
        positions_model : ndarray, shape (n_markers, 3)
            Every marker's position in the model frame (labelled ones measured, the rest from the model).
        seen : ndarray of bool, shape (n_markers,)
        head2world : ndarray, shape (4, 4)
        """
        unseen = np.where(seen, 0, self.config.velocity_frames + 1).astype(np.int64)
        positions = np.array(positions_model, dtype=np.float64)
        return TrackState(float(t), positions, np.zeros_like(positions), unseen, np.array(head2world, dtype=np.float64),
                          np.zeros(6), positions - self.reference)

    def lost(self, state: TrackState) -> bool:
        """True when too few markers were labelled for too long to trust the predictions (``lost_frames``)."""
        return state.starved > self.config.lost_frames

    def coast(self, state: TrackState, t: float) -> TrackState:
        """The state at ``t`` after a frame in which nothing was labelled while lost: the head held still."""
        return replace(state, t=float(t), unseen=state.unseen + 1, head_motion=np.zeros(6), starved=state.starved + 1)

    def restart(self, state: TrackState, t: float, found_world: np.ndarray) -> tuple[TrackState, TrackFrame]:
        """Continue from markers labelled from scratch (after :meth:`lost`), ``found_world (n_markers, 3)``.

        The head pose comes from the labelled markers (:meth:`pose`, at least 3 needed); velocities start at
        zero.
        """
        pose = self.pose(state, found_world)
        if not np.isfinite(pose).all():
            raise ValueError("restart needs at least 3 labelled markers")
        fresh = replace(state, head2world=pose, head_motion=np.zeros(6),
                        velocities_model=np.zeros_like(state.velocities_model))
        return self.step(fresh, np.zeros((0, 3)), t, found_world)

    def predict(self, state: TrackState, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted head pose ``(4, 4)`` and world marker positions ``(n_markers, 3)`` at time ``t``."""
        dt = t - state.t
        head2world = _pose_step(state.head2world, state.head_motion, dt)
        moving = (state.unseen <= self.config.velocity_frames)[:, None]
        ahead = dt * (state.unseen[:, None] + 1)
        positions = state.positions_model + np.where(moving, state.velocities_model * ahead, 0.0)
        return head2world, apply(head2world, positions)

    def gates(self, state: TrackState) -> np.ndarray:
        """Each marker's assignment gate this frame (world mm), shape (n_markers,)."""
        config = self.config
        gate = np.minimum(config.gate_mm + config.gate_growth_mm * state.unseen, config.max_gate_mm)
        return gate * self.model_scale

    def step(self, state: TrackState, points_3d: np.ndarray, t: float, found_world: np.ndarray | None = None,
             prediction: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[TrackState, TrackFrame]:
        """Label one frame's unlabelled points.

        Parameters
        ----------
        state : TrackState
        points_3d : ndarray, shape (n_points, 3)
            Unlabelled world points of this frame.
        t : float
            Seconds.
        found_world : ndarray, shape (n_markers, 3), optional
            Markers already labelled this frame (world positions; NaN for the others), e.g. by
            :class:`~livebridge.reconstruct.predicted.PredictedMatcher`; ``points_3d`` are assigned to
            the rest.
        prediction : (ndarray (4, 4), ndarray (n_markers, 3)), optional
            ``self.predict(state, t)`` when the caller already has it.

        Returns
        -------
        (TrackState, TrackFrame)
        """
        config = self.config
        points_3d = np.asarray(points_3d, dtype=np.float64).reshape(-1, 3)
        n_markers = len(state.positions_model)
        dt = max(t - state.t, 1e-6)
        predicted_pose, predicted = self.predict(state, t) if prediction is None else prediction
        world = np.full((n_markers, 3), np.nan) if found_world is None else np.array(found_world, dtype=np.float64)
        found = np.isfinite(world).all(axis=1)
        gate = self.gates(state)
        cost = np.linalg.norm(predicted[:, None] - points_3d[None], axis=-1)  # (n_markers, n_points)
        contractions = None
        returning = (state.unseen > 0) & ~found
        if self.displacement is not None and returning.any() and len(points_3d):
            contractions, predicted = self._model_prediction(state, points_3d, cost, gate, predicted_pose, predicted,
                                                             world)
            cost = np.linalg.norm(predicted[:, None] - points_3d[None], axis=-1)
        rows, cols = gated_assignment(np.where(found[:, None], np.inf, cost), gate)
        # refuse an assignment unless the point is clearly nearer its own prediction than any other (swap guard)
        if len(rows):
            others = cost[:, cols].copy()
            others[rows, np.arange(len(rows))] = np.inf
            keep = cost[rows, cols] < config.ratio * others.min(axis=0)
        else:
            keep = np.zeros(0, dtype=bool)
        n_refused = int((~keep).sum())
        rows, cols = rows[keep], cols[keep]
        labels = np.full(len(points_3d), -1, dtype=np.int64)
        labels[cols] = rows
        world[rows] = points_3d[cols]
        head2world = self.pose(state, world)
        if not np.isfinite(head2world).all():
            head2world = predicted_pose
        world2head = invert(head2world)
        model = apply(world2head, world)
        seen = np.isfinite(model).all(axis=1)
        if self.displacement is not None and config.consistency_mm is not None:
            kept, contractions = self._consistent(model, seen, state.model_offsets, contractions)
            dropped = np.flatnonzero(seen & ~kept)
            if len(dropped):
                labels[np.isin(labels, dropped)] = -1
                world[dropped] = model[dropped] = np.nan
                n_refused += len(dropped)
                seen = kept
        continuing = seen & (state.unseen == 0)
        velocities = state.velocities_model.copy()
        velocities[continuing] = (model[continuing] - state.positions_model[continuing]) / dt
        velocities[seen & ~continuing] = 0.0
        positions = state.positions_model.copy()
        positions[seen] = model[seen]
        unseen = np.where(seen, 0, state.unseen + 1)
        offsets = state.model_offsets
        if self.displacement is not None:
            if contractions is None:
                contractions = self._contractions(model, seen & ~self.head_mask)
            if contractions is not None:
                offsets = offsets.copy()
                fitted = np.einsum("nmd,m->nd", self.displacement[seen], contractions)
                offsets[seen] = model[seen] - self.reference[seen] - fitted
        new_state = replace(state, t=float(t), positions_model=positions, velocities_model=velocities, unseen=unseen,
                            head2world=head2world, head_motion=_pose_motion(state.head2world, head2world, dt),
                            model_offsets=offsets, starved=0 if seen.sum() >= 3 else state.starved + 1)
        frame = TrackFrame(labels, world, model, head2world, int((labels < 0).sum()), n_refused)
        return new_state, frame

    def _contractions(self, model: np.ndarray, use: np.ndarray) -> np.ndarray | None:
        """Non-negative contractions ``(n_muscles,)`` fitting the model-frame positions of the markers in ``use``.

        The markers' offsets are not subtracted: an offset is the misfit left by this fit, and fitting
        to positions less their offsets would add each frame's misfit to the next (a random walk)."""
        if use.sum() < 3:
            return None
        gram = self._marker_gram[use].sum(axis=0)  # (M, M): D^T D of the markers used
        rhs = np.einsum("nmk,nk->m", self.displacement[use], model[use] - self.reference[use])
        return nonnegative_least_squares(gram, rhs)

    def _consistent(self, model, seen, offsets, contractions) -> tuple[np.ndarray, np.ndarray | None]:
        """The labels the face model explains, shape (n_markers,) bool, and the contractions fitted to them.

        Why: after a gap in fast motion (a lip opening while a frame set was lost) every marker's
        prediction can be off by about the spacing of its neighbours, and the assignment then gives
        each the next one's point -- a shifted comb that no distance test tells from the truth. The
        face model does: those markers sit ``~spacing`` from where contractions fitted to the rest of
        the face put them. Labels farther than ``consistency_mm`` are dropped (the fit is repeated
        without them once); the markers come back in a later frame, predicted by the model.
        """
        face = seen & ~self.head_mask
        if contractions is None:
            contractions = self._contractions(model, face)
        if contractions is None:
            return seen, None
        limit = self.config.consistency_mm

        def off(x):
            expected = self.reference + np.einsum("nmd,m->nd", self.displacement, x) + offsets
            return face & (np.linalg.norm(model - expected, axis=1) > limit)

        bad = off(contractions)
        if bad.any():
            refit = self._contractions(model, face & ~bad)
            if refit is not None:
                contractions = refit
                bad |= off(contractions)
        return seen & ~bad, contractions

    def _model_prediction(self, state, points_3d, cost, gate, predicted_pose, predicted, found_world):
        """Predictions of markers returning from a gap from the face model, fitted to the continuing markers."""
        continuing = state.unseen == 0
        found = np.isfinite(found_world).all(axis=1)
        rows, cols = gated_assignment(np.where((continuing & ~found)[:, None], cost, np.inf), gate)
        world = found_world.copy()
        world[rows] = points_3d[cols]
        if np.isfinite(world).all(axis=1).sum() < 3:
            return None, predicted
        pose = self.head_pose(world)
        if not np.isfinite(pose).all():
            pose = predicted_pose
        model = apply(invert(pose), world)
        seen = np.isfinite(model).all(axis=1)
        contractions = self._contractions(model, seen & ~self.head_mask)
        if contractions is None:
            return None, predicted
        returning = ~continuing
        expected = self.reference + np.einsum("nmd,m->nd", self.displacement, contractions) + state.model_offsets
        predicted = predicted.copy()
        predicted[returning] = apply(pose, expected[returning])
        return contractions, predicted
