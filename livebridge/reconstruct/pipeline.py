"""The marker reconstructor: 2D centroids of a frame set in, labelled markers in the model frame out.

``Reconstructor.step(state, points_2d, t) -> (state, LabelledFrame)`` is the per-frame call the
runtime makes. On the first frame, which must be the neutral face: multi-view correspondence and
triangulation, first labelling and coordinate alignment. On every later frame: the markers followed
into the last frame are found at their predicted projections
(:class:`~livebridge.reconstruct.predicted.PredictedMatcher`), the detections left over go through the
multi-view correspondence, the tracker assigns those points and stabilises the head. When the tracker
is lost (nothing labelled for several frames: the face left every camera) the markers are labelled
from scratch against their last known positions. ``Reconstructor.run`` is the batch form for a take.

Frames: *world* is the capture frame of the calibrated rig; the *model* frame is the face model's
(mm, +y up, +z out of the face), which is also the head frame: ``head2world`` maps model
coordinates to the world, so ``positions = world2head @ positions_world``. ``head2world`` is
rigid when capture and model agree in scale and otherwise carries the alignment's fixed scale.
Displacements are measured from the captured neutral frame, in the model frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from livebridge.calibration.cameras import CameraGroup
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.geometry.transforms import apply, transform_scale
from livebridge.reconstruct.align import Alignment, align_to_model
from livebridge.reconstruct.correspond import Correspondence, Correspondence3D
from livebridge.reconstruct.detect import DetectConfig, detect_markers
from livebridge.reconstruct.label import guided_first_labelling
from livebridge.reconstruct.predicted import PredictedMatcher
from livebridge.reconstruct.track import TrackConfig, Tracker, TrackState
from livebridge.reconstruct.triangulate import Triangulator
from livebridge.take.npz import Take


@dataclass(frozen=True)
class ReconstructConfig:
    """Reconstruction parameters.

    Attributes
    ----------
    tolerance_px : float
        Epipolar gate and largest reprojection residual of a used view (undistorted px).
    refine_iterations : int
        Gauss-Newton steps after the DLT (0: DLT only).
    label_gate_mm : float
        First labelling: largest distance of a point from its marker after the similarity fit.
    max_head_turn_deg : float
        First labelling: rotation hypotheses cover this much about each axis.
    align_surface : bool
        Refine the alignment by projecting markers onto the face surface (needs the basis mesh).
    track : TrackConfig
    detect : DetectConfig
    """

    tolerance_px: float = 1.5
    refine_iterations: int = 0
    label_gate_mm: float = 6.0
    max_head_turn_deg: float = 30.0
    align_surface: bool = True
    track: TrackConfig = field(default_factory=TrackConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)


@dataclass(frozen=True, eq=False)
class LabelledFrame:
    """Labelled markers of one frame (read-only arrays).

    Attributes
    ----------
    t : float
        Seconds.
    positions : ndarray, shape (n_markers, 3)
        Marker positions in the model (head) frame, mm; NaN where not labelled.
    displacements : ndarray, shape (n_markers, 3)
        Displacement from the neutral frame in the model frame, mm; NaN where not labelled.
        This is what the contraction solver takes.
    positions_world : ndarray, shape (n_markers, 3)
        The labelled positions in the capture (world) frame.
    head2world : ndarray, shape (4, 4)
        Head pose (model frame to world); NaN before the first labelling.
    n_stray : int
        Triangulated points that took no label (reflections, ghosts).
    labelled_fraction : float
        Fraction of the markers labelled in this frame.
    """

    t: float
    positions: np.ndarray
    displacements: np.ndarray
    positions_world: np.ndarray
    head2world: np.ndarray
    n_stray: int
    labelled_fraction: float

    def __post_init__(self):
        # made read-only, so they must not be the tracker's own arrays (compiled code is specialised, and
        # warmed up, for writable ones)
        for name in ("positions", "displacements", "positions_world", "head2world"):
            getattr(self, name).setflags(write=False)


@dataclass(frozen=True, eq=False)
class ReconstructorState:
    """State between frames: nothing until the first labelling succeeds.

    Attributes
    ----------
    track : TrackState or None
    tracker : Tracker or None
        Built at the first labelling (it holds the head reference and model scale).
    alignment : Alignment or None
    neutral : ndarray, shape (n_markers, 3) or None
        Neutral marker positions in the model frame.
    frames : int
        Frames seen.
    """

    track: TrackState | None = None
    tracker: Tracker | None = None
    alignment: Alignment | None = None
    neutral: np.ndarray | None = None
    frames: int = 0

    @property
    def labelled(self) -> bool:
        return self.track is not None


class Reconstructor:
    """Marker reconstruction for one rig and one marker set.

    Parameters
    ----------
    cameras : CameraGroup
    markers : MarkerSet
        Face and head-rig markers.
    basis : Basis
        The face model (neutral mesh for labelling and alignment).
    config : ReconstructConfig
    """

    def __init__(self, cameras: CameraGroup, markers: MarkerSet, basis: Basis,
                 config: ReconstructConfig = ReconstructConfig()):
        self.cameras = cameras
        self.markers = markers
        self.basis = basis
        self.config = config
        self.triangulator = Triangulator(cameras)
        self.correspond = Correspondence3D(self.triangulator, config.tolerance_px)
        self.matcher = PredictedMatcher(self.triangulator, config.tolerance_px, config.track.ratio)
        self.model_points = markers.neutral_positions(basis)

    @property
    def n_markers(self) -> int:
        return len(self.markers)

    def initial_state(self) -> ReconstructorState:
        return ReconstructorState()

    def warm_up(self) -> None:
        """Run the compiled per-frame kernels once (numba compiles or loads them on first use): the matcher,
        the correspondence, the triangulation and a tracker step on the neutral markers."""
        from livebridge.reconstruct import correspond

        correspond.warm_up()
        n_cams, n = len(self.cameras), self.n_markers
        self.matcher([np.zeros((1, 2))] * n_cams, np.zeros((n, 3)), np.ones(n, bool), np.ones(n))
        self.triangulator.dlt(np.zeros((n_cams, 1, 2)))
        tracker = Tracker(self.markers.head_mask, self.model_points, 1.0, self.config.track,
                          self.markers.displacement_matrix(self.basis))
        state = tracker.start(0.0, self.model_points, np.ones(n, bool), np.eye(4))
        tracker.step(state, self.model_points, 1.0 / 60.0)

    def detect(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Undistorted marker centroids per camera (see :func:`livebridge.reconstruct.detect.detect_markers`)."""
        return detect_markers(images, self.cameras, self.config.detect)

    def points_3d(self, points_2d: Sequence[np.ndarray], predicted: np.ndarray | None = None) -> Correspondence:
        """Unlabelled 3D points of one frame set (correspondence + triangulation).

        ``predicted (n_markers, 3)``: the tracker's predicted world positions, which settle
        ambiguous two-view groups (see :class:`~livebridge.reconstruct.correspond.Correspondence3D`).
        """
        found = self.correspond(points_2d, predicted, self.config.track.gate_mm * 0.75)
        if self.config.refine_iterations and len(found.points_3d):
            gathered = self.correspond._gather([np.asarray(p).reshape(-1, 2) for p in points_2d], found.detections)
            refined = self.triangulator.refine(found.points_3d, gathered, self.config.refine_iterations)
            found = Correspondence(refined, found.detections, found.residual_px, found.n_unused)
        return found

    def step(self, state: ReconstructorState, points_2d: Sequence[np.ndarray],
             t: float) -> tuple[ReconstructorState, LabelledFrame]:
        """Reconstruct one frame set.

        Parameters
        ----------
        state : ReconstructorState
        points_2d : sequence of ndarray, one per camera, each shape (n_detections_i, 2)
            Undistorted pixel centroids (as :meth:`detect` returns them).
        t : float
            Seconds.

        Returns
        -------
        (ReconstructorState, LabelledFrame)
        """
        if state.track is None:
            return self._first(state, points_2d, t)
        if state.tracker.lost(state.track):
            return self._reacquire(state, points_2d, t)
        tracker = state.tracker
        prediction = tracker.predict(state.track, t)
        predicted = prediction[1]
        # markers followed into the last frame are found around their predicted projections; the
        # detections they leave go through the general correspondence and the tracker's assignment
        found = self.matcher(points_2d, predicted, state.track.unseen == 0, tracker.gates(state.track))
        points = self.points_3d(found.remaining, predicted).points_3d
        track, out = tracker.step(state.track, points, t, found.positions_world, prediction)
        seen = np.isfinite(out.positions_model).all(axis=1)
        frame = LabelledFrame(float(t), out.positions_model, out.positions_model - state.neutral, out.positions_world,
                              out.head2world.copy(), out.n_stray, float(seen.mean()))
        return ReconstructorState(track, state.tracker, state.alignment, state.neutral, state.frames + 1), frame

    def _first(self, state: ReconstructorState, points_2d: Sequence[np.ndarray], t: float):
        config = self.config
        # blind correspondence, then again guided by the model markers the first alignment places
        points, labelling = guided_first_labelling(lambda predicted: self.points_3d(points_2d, predicted).points_3d,
                                                   self.model_points, gate_mm=config.label_gate_mm,
                                                   max_angle_deg=config.max_head_turn_deg)
        n = self.n_markers
        if not self._labelled_enough(labelling.n_matched, np.isin(np.flatnonzero(self.markers.head_mask),
                                                                   labelling.labels).sum()):
            nothing = np.full((n, 3), np.nan)
            frame = LabelledFrame(float(t), nothing, nothing.copy(), nothing.copy(), np.full((4, 4), np.nan),
                                  int(np.isfinite(points).all(axis=1).sum()), 0.0)
            return ReconstructorState(frames=state.frames + 1), frame
        captured = labelling.marker_points(points, n)
        if config.align_surface:
            alignment = align_to_model(captured, self.markers, self.basis)
        else:
            alignment = Alignment(labelling.capture2model, self.markers, labelling.rms_mm, 0)
        capture2model = alignment.capture2model
        measured = apply(capture2model, captured)
        seen = np.isfinite(measured).all(axis=1)
        virtual = alignment.markers.neutral_positions(self.basis)
        neutral = np.where(seen[:, None], measured, virtual)
        head2world = np.linalg.inv(capture2model)
        displacement = alignment.markers.displacement_matrix(self.basis)
        tracker = Tracker(self.markers.head_mask, neutral, transform_scale(head2world), config.track, displacement)
        track = tracker.start(t, neutral, seen, head2world)
        positions = np.where(seen[:, None], measured, np.nan)
        frame = LabelledFrame(float(t), positions, positions - neutral, captured, head2world,
                              int(np.isfinite(points).all(axis=1).sum() - seen.sum()), float(seen.mean()))
        return ReconstructorState(track, tracker, alignment, neutral, state.frames + 1), frame

    def _labelled_enough(self, n_matched: int, head_seen: int) -> bool:
        """A labelling from scratch is trusted with half the markers and 3 head markers, or with three quarters
        of the markers (a rig whose cameras see few head markers twice: the head pose then comes from all)."""
        n = self.n_markers
        return n_matched >= max(4, n // 2) and (head_seen >= 3 or n_matched >= 3 * n // 4)

    def _reacquire(self, state: ReconstructorState, points_2d: Sequence[np.ndarray], t: float):
        """Label a frame from scratch after the tracker lost every marker (a dropout longer than it coasts).

        The same labelling as the first frame's (rotation hypotheses, assignment, similarity, then the
        model-guided correspondence), against the markers' last known positions in the head frame (the
        face as last seen); the tracker then restarts from the head pose this gives.
        """
        config, track = self.config, state.track
        points, labelling = guided_first_labelling(lambda predicted: self.points_3d(points_2d, predicted).points_3d,
                                                   track.positions_model, gate_mm=config.label_gate_mm,
                                                   max_angle_deg=config.max_head_turn_deg)
        world = labelling.marker_points(points, self.n_markers)
        if not self._labelled_enough(labelling.n_matched, np.isfinite(world[self.markers.head_mask]).all(axis=1).sum()):
            track = state.tracker.coast(track, t)
            nothing = np.full((self.n_markers, 3), np.nan)
            frame = LabelledFrame(float(t), nothing, nothing.copy(), nothing.copy(), track.head2world.copy(),
                                  int(np.isfinite(points).all(axis=1).sum()), 0.0)
            return replace(state, track=track, frames=state.frames + 1), frame
        track, out = state.tracker.restart(track, t, world)
        seen = np.isfinite(out.positions_model).all(axis=1)
        strays = out.n_stray + int(np.isfinite(points).all(axis=1).sum() - seen.sum())
        frame = LabelledFrame(float(t), out.positions_model, out.positions_model - state.neutral, out.positions_world,
                              out.head2world.copy(), strays, float(seen.mean()))
        return replace(state, track=track, frames=state.frames + 1), frame

    def run(self, frames_2d: Sequence[Sequence[np.ndarray]], t: np.ndarray) -> list[LabelledFrame]:
        """Batch form: reconstruct a whole take of frame sets (the first is the neutral face).

        Parameters
        ----------
        frames_2d : sequence (n_frames) of sequences (n_cams) of ndarray, shape (n_detections, 2)
            Undistorted pixel centroids per frame and camera.
        t : ndarray, shape (n_frames,)

        Returns
        -------
        list of LabelledFrame
        """
        state = self.initial_state()
        frames = []
        for points_2d, time in zip(frames_2d, np.asarray(t, dtype=np.float64)):
            state, frame = self.step(state, points_2d, float(time))
            frames.append(frame)
        return frames

    def to_take(self, frames: Sequence[LabelledFrame], fps: float | None = None) -> Take:
        """Frames as a :class:`livebridge.take.npz.Take` (displacements, world positions, head poses)."""
        return Take(t=np.array([f.t for f in frames]), marker_names=self.markers.names,
                    displacements=np.stack([f.displacements for f in frames]),
                    positions=np.stack([f.positions_world for f in frames]),
                    head2world=np.stack([f.head2world for f in frames]), fps=fps)
