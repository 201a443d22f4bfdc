"""Offline solve: a file of labelled marker trajectories in, contractions out.

The same steps as the live path after labelling, on a whole take at once:

1. the file's markers matched to the marker set by name (or placed automatically,
   :mod:`livebridge.face.placement`);
2. a neutral frame, given or chosen (:func:`choose_neutral_frame` with a marker set, :func:`choose_rest_frame`
   for a layout being placed);
3. the coordinate alignment on it (:func:`livebridge.reconstruct.align.align_to_model`: similarity, surface
   projection, repeat), whose neutral positions in the model frame are the displacements' origin;
4. the head pose of every frame from the head markers, or with fewer than three of them seen from all
   markers weighted by how little the face model moves them (:meth:`livebridge.reconstruct.track.Tracker.pose`);
5. displacements in the model frame and the live path's :class:`~livebridge.solve.solver.ContractionSolver`;
6. for frames posed from the face markers, the pose refitted to the positions the solved contractions predict
   and the frame solved again, until the contractions settle (:func:`refit_poses`): offline, unlike live, the
   take can be solved more than once.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.face.markers import match_markers as match_names
from livebridge.face.placement import Placement, fill_unseen, place_markers
from livebridge.geometry.transforms import apply, invert, transform_scale, umeyama
from livebridge.reconstruct.align import Alignment, align_to_model
from livebridge.reconstruct.stabilize import head_pose
from livebridge.reconstruct.track import TrackConfig, Tracker
from livebridge.solve.solver import ContractionSolver, SolverConfig, TakeSolution
from livebridge.take.trajectories import Trajectories

MAX_CANDIDATES = 300
"""Frames examined by the automatic neutral-frame choice (evenly spread over the take)."""
MAX_POSE_ROUNDS = 30
"""Most refits of the head pose of frames posed from the face markers (:func:`refit_poses`)..."""
POSE_TOLERANCE = 1e-4
"""...stopping once the contractions change by less than this (RMS over the take)."""
REST_PERCENTILE = 1.0
"""Percentile of each muscle's contraction relative to a reference frame taken as its rest (:func:`rest_distance`)."""


@dataclass(frozen=True, eq=False)
class NeutralChoice:
    """The neutral frame and why.

    Attributes
    ----------
    frame : int
    reason : str
        One line for the user.
    """

    frame: int
    reason: str


@dataclass(frozen=True, eq=False)
class OfflineSolution:
    """An offline solve.

    Attributes
    ----------
    t : ndarray, shape (n_frames,)
    muscle_names : tuple of str
    markers : MarkerSet
        As solved with: the file's marker order, placed on the surface by the alignment.
    positions : ndarray, shape (n_frames, n_markers, 3)
        Capture frame (mm), in ``markers`` order.
    displacements : ndarray, shape (n_frames, n_markers, 3)
        Model frame (mm), NaN where unseen.
    head2world : ndarray, shape (n_frames, 4, 4)
        Model to capture frame per frame (NaN where the pose could not be found).
    alignment : Alignment
    neutral : NeutralChoice
    solution : TakeSolution
    """

    t: np.ndarray
    muscle_names: tuple[str, ...]
    markers: MarkerSet
    positions: np.ndarray
    displacements: np.ndarray
    head2world: np.ndarray
    alignment: Alignment
    neutral: NeutralChoice
    solution: TakeSolution


def match_markers(trajectories: Trajectories, markers: MarkerSet) -> np.ndarray:
    """The file's marker positions in the marker set's order, shape (n_frames, n_markers, 3).

    Names match exactly, then by landmark number (OpenFace's numbered columns against a 68-point set):
    :func:`livebridge.face.markers.match_markers`.

    Raises
    ------
    InputError
        Naming the markers the file lacks and those the set does not know.
    """
    index = match_names(trajectories.names, markers, source=trajectories.source)
    return trajectories.points[:, index]


def _candidates(points: np.ndarray) -> np.ndarray:
    """Frames worth examining: those showing nearly the most markers any frame shows, at most MAX_CANDIDATES."""
    counts = np.isfinite(points).all(axis=2).sum(axis=1)
    frames = np.flatnonzero(counts >= max(3, 0.9 * counts.max(initial=0)))
    if not len(frames):
        raise InputError("no frame shows 3 markers or more", field="neutral-frame")
    step = max(1, int(np.ceil(len(frames) / MAX_CANDIDATES)))
    return frames[::step]


def model_deformation(points: np.ndarray, virtual: np.ndarray) -> np.ndarray:
    """Per frame, RMS distance (model mm) of the markers from their model neutral positions after a similarity fit.

    Parameters
    ----------
    points : ndarray, shape (n_frames, n_markers, 3)
    virtual : ndarray, shape (n_markers, 3)

    Returns
    -------
    ndarray, shape (n_frames,); inf with fewer than 3 markers seen.
    """
    out = np.full(len(points), np.inf)
    for f, frame in enumerate(points):
        seen = np.isfinite(frame).all(axis=1)
        if seen.sum() >= 3:
            fit = umeyama(frame[seen], virtual[seen], with_scale=True)
            out[f] = np.sqrt(np.mean(((apply(fit, frame[seen]) - virtual[seen]) ** 2).sum(-1)))
    return out


def rest_distance(displacements: np.ndarray, basis: Basis, markers: MarkerSet,
                  percentile: float = REST_PERCENTILE) -> np.ndarray:
    """Per frame, how far (model mm, RMS over the face markers) the basis puts the face from rest.

    The displacements are from a reference frame that need not be at rest. Unconstrained least squares gives
    each frame's contractions relative to the reference, ``u_f = c_f - c_ref``. Contractions are never
    negative and each muscle relaxes somewhere in a take, so the reference's own contractions are
    ``c_ref = max(0, -P(u))`` with ``P`` a low percentile over the frames (not the minimum: one noisy frame
    would set it); the distance is the RMS of ``B (u_f + c_ref)``. Unlike a distance between shapes, which
    skin sliding along the face hides, this measures the deformation the expression muscles make.

    Parameters
    ----------
    displacements : ndarray, shape (n_frames, n_markers, 3)
        Model frame, from the reference frame, NaN unseen.
    basis : Basis
    markers : MarkerSet
    percentile : float

    Returns
    -------
    ndarray, shape (n_frames,); inf where fewer than 3 face markers are seen.
    """
    matrix = markers.displacement_matrix(basis)  # (n, M, 3)
    relative = np.full((len(displacements), matrix.shape[1]), np.nan)
    for f, frame in enumerate(displacements):
        seen = markers.face_mask & np.isfinite(frame).all(axis=1)
        if seen.sum() >= 3:
            rows = matrix[seen].transpose(0, 2, 1).reshape(-1, matrix.shape[1])
            relative[f] = np.linalg.lstsq(rows, frame[seen].reshape(-1), rcond=None)[0]
    solved = np.isfinite(relative).all(axis=1)
    if not solved.any():
        return np.full(len(displacements), np.inf)
    reference = np.maximum(0.0, -np.percentile(relative[solved], percentile, axis=0))
    predicted = np.einsum("nmk,fm->fnk", matrix[markers.face_mask], relative + reference)
    out = np.sqrt(np.mean((predicted ** 2).sum(-1), axis=1))
    return np.where(solved, out, np.inf)


def choose_neutral_frame(points: np.ndarray, basis: Basis, markers: MarkerSet) -> NeutralChoice:
    """The frame closest to rest by the marker set: the least RMS distance of the markers from their positions
    on the model's neutral face after a similarity fit (:func:`model_deformation`).

    Parameters
    ----------
    points : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, NaN unseen.
    """
    frames = _candidates(points)
    scores = model_deformation(points[frames], markers.neutral_positions(basis))
    best = int(np.argmin(scores))
    reason = (f"neutral frame {int(frames[best])} chosen automatically: least RMS distance of the markers from "
              f"their places on the model's neutral face after a similarity fit ({scores[best]:.2f} mm; median "
              f"{float(np.median(scores)):.2f} mm over {len(frames)} frames examined)")
    return NeutralChoice(int(frames[best]), reason)


def choose_rest_frame(points: np.ndarray, basis: Basis, markers: MarkerSet, reference: int) -> NeutralChoice:
    """The frame closest to rest by the basis (:func:`rest_distance`), from displacements measured against
    ``reference`` (the frame ``markers`` were placed on), among the frames showing nearly all markers.

    Parameters
    ----------
    points : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, NaN unseen, in ``markers`` order.
    """
    frames = _candidates(points)
    take = model_displacements(points, basis, markers, reference)
    scores = rest_distance(take.displacements, basis, take.alignment.markers)[frames]
    best = int(np.argmin(scores))
    reason = (f"neutral frame {int(frames[best])} chosen automatically: least deformation from rest the basis "
              f"explains ({scores[best]:.2f} mm RMS; median {float(np.median(scores)):.2f} mm over {len(frames)} "
              f"frames examined; displacements from frame {reference})")
    return NeutralChoice(int(frames[best]), reason)


def head_poses(tracker: Tracker, neutral_model: np.ndarray, capture2model: np.ndarray,
               positions: np.ndarray) -> np.ndarray:
    """``head2world`` per frame, shape (n_frames, 4, 4), by the live tracker's pose (head markers, else all
    markers weighted by steadiness) against the neutral frame's model-frame positions; NaN where < 3 are seen."""
    seen = np.isfinite(neutral_model).all(axis=1)
    state = tracker.start(0.0, neutral_model, seen, invert(capture2model))
    return np.stack([tracker.pose(state, frame) for frame in positions]) if len(positions) else np.zeros((0, 4, 4))


@dataclass(frozen=True, eq=False)
class ModelTake:
    """A take in the model frame, from its neutral frame.

    Attributes
    ----------
    alignment : Alignment
        The coordinate alignment on the neutral frame.
    neutral_model : ndarray, shape (n_markers, 3)
        The neutral frame's markers in the model frame (the model's place for those it misses).
    head2world : ndarray, shape (n_frames, 4, 4)
        NaN where fewer than 3 markers were seen.
    head_posed : ndarray of bool, shape (n_frames,)
        Frames whose pose came from 3 or more head markers (the others: from the face markers).
    displacements : ndarray, shape (n_frames, n_markers, 3)
        Model frame, from ``neutral_model``, NaN unseen.
    """

    alignment: Alignment
    neutral_model: np.ndarray
    head2world: np.ndarray
    head_posed: np.ndarray
    displacements: np.ndarray


def model_displacements(positions: np.ndarray, basis: Basis, markers: MarkerSet, frame: int) -> ModelTake:
    """The coordinate alignment on the neutral ``frame``, the head pose of every frame and the model-frame
    displacements from that frame (module docstring, steps 3 and 4).

    Parameters
    ----------
    positions : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, in ``markers`` order, NaN unseen.
    """
    captured = positions[frame]
    if np.isfinite(captured).all(axis=1)[markers.face_mask].sum() < 3:
        raise InputError(f"the neutral frame {frame} shows fewer than 3 face markers", field="neutral-frame")
    alignment = align_to_model(captured, markers, basis)
    measured = apply(alignment.capture2model, captured)
    seen = np.isfinite(measured).all(axis=1)
    neutral_model = np.where(seen[:, None], measured, alignment.markers.neutral_positions(basis))
    displacement = alignment.markers.displacement_matrix(basis)
    tracker = Tracker(markers.head_mask, neutral_model, transform_scale(invert(alignment.capture2model)),
                      TrackConfig(), displacement)
    head2world = head_poses(tracker, neutral_model, alignment.capture2model, positions)
    head_posed = (np.isfinite(positions).all(axis=2) & markers.head_mask).sum(axis=1) >= 3
    return ModelTake(alignment, neutral_model, head2world, head_posed, _displacements(head2world, positions,
                                                                                       neutral_model))


def _displacements(head2world: np.ndarray, positions: np.ndarray, neutral_model: np.ndarray) -> np.ndarray:
    """Model-frame displacements (n_frames, n_markers, 3) as the live tracker: world2head @ world - neutral."""
    if not len(positions):
        return np.zeros((0, *neutral_model.shape))
    return np.stack([_to_model(pose, frame) for pose, frame in zip(head2world, positions)]) - neutral_model[None]


def refit_poses(take: ModelTake, positions: np.ndarray, matrix: np.ndarray, contractions: np.ndarray) -> np.ndarray:
    """``head2world`` (n_frames, 4, 4) with each face-posed frame refitted rigidly to the model-frame positions
    the solved contractions predict (neutral + displacement matrix @ contractions) rather than to the neutral:
    the expression no longer drags the head pose along.

    Parameters
    ----------
    take : ModelTake
    positions : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, NaN unseen.
    matrix : ndarray, shape (n_markers, n_muscles, 3)
    contractions : ndarray, shape (n_frames, n_muscles)
    """
    scale = transform_scale(invert(take.alignment.capture2model))
    head2world = take.head2world.copy()
    for f in np.flatnonzero(~take.head_posed & np.isfinite(contractions).all(axis=1)):
        predicted = take.neutral_model + np.einsum("nmk,m->nk", matrix, contractions[f])
        head2world[f] = head_pose(predicted, positions[f], scale)
    return head2world


def solve_positions(t: np.ndarray, positions: np.ndarray, basis: Basis, markers: MarkerSet, neutral: NeutralChoice,
                    config: SolverConfig | None = None, progress: bool = False) -> OfflineSolution:
    """Solve a take of labelled positions (module docstring, steps 3 to 6).

    Parameters
    ----------
    t : ndarray, shape (n_frames,)
    positions : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, in ``markers`` order, NaN unseen.
    basis : Basis
    markers : MarkerSet
    neutral : NeutralChoice
    config : SolverConfig, optional
    progress : bool
        A tqdm bar on stderr while solving.
    """
    positions = np.asarray(positions, dtype=np.float64)
    take = model_displacements(positions, basis, markers, neutral.frame)
    solver = ContractionSolver(basis, take.alignment.markers, config)
    solution = solver.solve_take(take.displacements, progress=progress)
    matrix = take.alignment.markers.displacement_matrix(basis)
    for _ in range(MAX_POSE_ROUNDS if not take.head_posed.all() else 0):
        # face-posed frames: the pose from what the contractions predict, the contractions from that pose, ...
        head2world = refit_poses(take, positions, matrix, solution.contractions)
        take = replace(take, head2world=head2world,
                       displacements=_displacements(head2world, positions, take.neutral_model))
        previous, solution = solution, solver.solve_take(take.displacements)
        if np.sqrt(np.mean((solution.contractions - previous.contractions) ** 2)) < POSE_TOLERANCE:
            break
    return OfflineSolution(np.asarray(t, dtype=np.float64), basis.names, take.alignment.markers, positions,
                           take.displacements, take.head2world, take.alignment, neutral, solution)


def _to_model(head2world: np.ndarray, world: np.ndarray) -> np.ndarray:
    """``world (n, 3)`` in the head (model) frame; all NaN where the pose is unknown."""
    if not np.isfinite(head2world).all():
        return np.full_like(world, np.nan)
    return apply(invert(head2world), world)


def parse_neutral(option: str | int, n_frames: int) -> int | None:
    """``--neutral-frame``: a frame number in range, or None for ``auto``."""
    if option == "auto":
        return None
    try:
        frame = int(option)
    except (TypeError, ValueError):
        raise InputError(f"expected 'auto' or a frame number, got {option!r}", field="--neutral-frame") from None
    if not 0 <= frame < n_frames:
        raise InputError(f"frame {frame} is outside the take (frames 0..{n_frames - 1})", field="--neutral-frame")
    return frame


def neutral_for_set(positions: np.ndarray, basis: Basis, markers: MarkerSet, frame: int | None) -> NeutralChoice:
    """The given neutral frame, or (None) the one :func:`choose_neutral_frame` picks against the marker set."""
    if frame is not None:
        return NeutralChoice(frame, f"neutral frame {frame} (given)")
    return choose_neutral_frame(positions, basis, markers)


def place_from_positions(positions: np.ndarray, names: tuple[str, ...], basis: Basis, frame: int | None,
                         correspond: dict[str, int] | None = None) -> tuple[Placement, NeutralChoice]:
    """Automatic placement (:func:`livebridge.face.placement.place_markers`) with the neutral frame given or
    chosen.

    To choose, the layout is placed on the frame that shows the most markers, the frame closest to rest found
    from there (:func:`choose_rest_frame`), and the layout placed again on that frame, starting from the first
    placement's similarity carried over by the head's rigid motion between the two frames.

    Parameters
    ----------
    positions : ndarray, shape (n_frames, n_markers, 3)
    names : tuple of str
    frame : int or None
        None: choose.
    correspond : dict of name -> vertex index, optional
    """
    if frame is not None:
        given = NeutralChoice(frame, f"neutral frame {frame} (given)")
        return place_markers(positions, names, basis, frame, correspond), given
    candidates = _candidates(positions)
    first = int(candidates[np.argmax(np.isfinite(positions[candidates]).all(axis=2).sum(axis=1))])
    placement = place_markers(positions, names, basis, first, correspond)
    choice = choose_rest_frame(positions, basis, placement.markers, first)
    if choice.frame == first:
        return placement, choice
    head = placement.markers.head_mask if placement.markers.head_mask.sum() >= 3 else np.ones(len(names), bool)
    start, end = fill_unseen(positions, first), fill_unseen(positions, choice.frame)
    common = head & np.isfinite(start).all(axis=1) & np.isfinite(end).all(axis=1)
    rough = placement.capture2model @ umeyama(end[common], start[common], with_scale=False)
    again = place_markers(positions, names, basis, choice.frame, correspond, rough=rough)
    return replace(again, how=f"{placement.how} on frame {first}, carried over to frame {choice.frame}"), choice
