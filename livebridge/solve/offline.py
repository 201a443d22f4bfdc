"""Offline solve: a file of labelled marker trajectories in, contractions out.

The same steps as the live path after labelling, on a whole take at once:

1. the file's markers matched to the marker set by name (or placed automatically,
   :mod:`livebridge.face.placement`);
2. a neutral frame, given or chosen (:func:`choose_neutral_frame`);
3. the coordinate alignment on it (:func:`livebridge.reconstruct.align.align_to_model`: similarity, surface
   projection, repeat), whose neutral positions in the model frame are the displacements' origin;
4. the head pose of every frame from the head markers, or with fewer than three of them seen from all
   markers weighted by how little the face model moves them (:meth:`livebridge.reconstruct.track.Tracker.pose`);
5. displacements in the model frame and the live path's :class:`~livebridge.solve.solver.ContractionSolver`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.face.placement import Placement, correspondence_alignment, fill_unseen, place_markers, rough_alignment
from livebridge.geometry.transforms import apply, invert, transform_scale, umeyama
from livebridge.reconstruct.align import Alignment, MeshSurface, align_to_model
from livebridge.reconstruct.track import TrackConfig, Tracker
from livebridge.solve.solver import ContractionSolver, SolverConfig, TakeSolution
from livebridge.take.trajectories import Trajectories

MAX_CANDIDATES = 300
"""Frames examined by the automatic neutral-frame choice (evenly spread over the take)."""


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

    Raises
    ------
    InputError
        Naming the markers the file lacks and those the set does not know.
    """
    missing = [name for name in markers.names if name not in trajectories.names]
    extra = [name for name in trajectories.names if name not in markers.names]
    if missing or extra:
        parts = ([f"missing from the file: {', '.join(missing)}"] if missing else []) + \
                ([f"not in the marker set: {', '.join(extra)}"] if extra else [])
        raise InputError("the file's markers do not match the marker set (" + "; ".join(parts) + ")",
                         trajectories.source, "markers")
    index = [trajectories.names.index(name) for name in markers.names]
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


def surface_deformation(points: np.ndarray, basis: Basis, reference: np.ndarray,
                        capture2model: np.ndarray) -> np.ndarray:
    """Per frame, RMS distance (model mm) of the markers from the neutral surface after the coordinate alignment,
    started from ``capture2model`` (found on the frame ``reference (n_markers, 3)``) composed with the frame's
    rigid motion to that reference.

    Returns
    -------
    ndarray, shape (n_frames,); inf with fewer than 3 markers seen.
    """
    surface = MeshSurface(basis.neutral, basis.triangles)
    out = np.full(len(points), np.inf)
    for f, frame in enumerate(points):
        seen = np.isfinite(frame).all(axis=1)
        common = seen & np.isfinite(reference).all(axis=1)
        if common.sum() < 3:
            continue
        transform = capture2model @ umeyama(frame[common], reference[common], with_scale=False)
        for _ in range(10):  # similarity to the closest surface points until the error stops falling
            moved = apply(transform, frame[seen])
            _, _, target = surface.closest(moved)
            error = float(np.sqrt(np.mean(((moved - target) ** 2).sum(-1))))
            if error >= out[f] - 1e-6:
                break
            out[f] = error
            transform = umeyama(frame[seen], target, with_scale=True)
    return out


def choose_neutral_frame(points: np.ndarray, basis: Basis, markers: MarkerSet | None = None,
                         capture2model: np.ndarray | None = None,
                         reference: np.ndarray | None = None) -> NeutralChoice:
    """The frame closest to rest.

    With a marker set: the least RMS distance of the markers from their positions on the model's neutral face
    after a similarity fit (:func:`model_deformation`). Without one (a layout being placed): the least RMS
    distance from the neutral surface after the coordinate alignment, started from ``capture2model`` found on
    the frame ``reference`` (:func:`surface_deformation`).

    Parameters
    ----------
    points : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, NaN unseen.
    """
    frames = _candidates(points)
    if markers is not None:
        scores = model_deformation(points[frames], markers.neutral_positions(basis))
        measure = "distance of the markers from their places on the model's neutral face after a similarity fit"
    elif capture2model is not None and reference is not None:
        scores = surface_deformation(points[frames], basis, reference, capture2model)
        measure = "distance of the markers from the neutral face surface after the coordinate alignment"
    else:
        raise ValueError("choose_neutral_frame needs a marker set, or a capture2model and its reference frame")
    best = int(np.argmin(scores))
    reason = (f"neutral frame {int(frames[best])} chosen automatically: least RMS {measure} "
              f"({scores[best]:.2f} mm; median {float(np.median(scores)):.2f} mm over {len(frames)} frames examined)")
    return NeutralChoice(int(frames[best]), reason)


def head_poses(tracker: Tracker, neutral_model: np.ndarray, capture2model: np.ndarray,
               positions: np.ndarray) -> np.ndarray:
    """``head2world`` per frame, shape (n_frames, 4, 4), by the live tracker's pose (head markers, else all
    markers weighted by steadiness) against the neutral frame's model-frame positions; NaN where < 3 are seen."""
    seen = np.isfinite(neutral_model).all(axis=1)
    state = tracker.start(0.0, neutral_model, seen, invert(capture2model))
    return np.stack([tracker.pose(state, frame) for frame in positions]) if len(positions) else np.zeros((0, 4, 4))


def solve_positions(t: np.ndarray, positions: np.ndarray, basis: Basis, markers: MarkerSet, neutral: NeutralChoice,
                    config: SolverConfig | None = None, progress: bool = False) -> OfflineSolution:
    """Solve a take of labelled positions (module docstring, steps 3 to 5).

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
    captured = positions[neutral.frame]
    if np.isfinite(captured).all(axis=1)[markers.face_mask].sum() < 3:
        raise InputError(f"the neutral frame {neutral.frame} shows fewer than 3 face markers", field="neutral-frame")
    alignment = align_to_model(captured, markers, basis)
    measured = apply(alignment.capture2model, captured)
    seen = np.isfinite(measured).all(axis=1)
    neutral_model = np.where(seen[:, None], measured, alignment.markers.neutral_positions(basis))
    displacement = alignment.markers.displacement_matrix(basis)
    tracker = Tracker(markers.head_mask, neutral_model, transform_scale(invert(alignment.capture2model)),
                      TrackConfig(), displacement)
    head2world = head_poses(tracker, neutral_model, alignment.capture2model, positions)
    # as the live tracker: positions_model = world2head @ world, displacement from the captured neutral
    displacements = np.stack([_to_model(pose, frame) for pose, frame in zip(head2world, positions)]) \
        - neutral_model[None] if len(positions) else np.zeros((0, len(markers), 3))
    solver = ContractionSolver(basis, alignment.markers, config)
    solution = solver.solve_take(displacements, progress=progress)
    return OfflineSolution(np.asarray(t, dtype=np.float64), basis.names, alignment.markers, positions, displacements,
                           head2world, alignment, neutral, solution)



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
    chosen: the rough alignment on the frame that shows the most markers, then the frame nearest the neutral
    surface from there.

    Parameters
    ----------
    positions : ndarray, shape (n_frames, n_markers, 3)
    names : tuple of str
    frame : int or None
        None: choose.
    correspond : dict of name -> vertex index, optional
    """
    if frame is None:
        candidates = _candidates(positions)
        first = int(candidates[np.argmax(np.isfinite(positions[candidates]).all(axis=2).sum(axis=1))])
        reference = fill_unseen(positions, first)
        seen = np.isfinite(reference).all(axis=1)
        if correspond:
            rough, _ = correspondence_alignment(reference, names, correspond, basis)
        else:
            rough, _ = rough_alignment(reference[seen], basis, MeshSurface(basis.neutral, basis.triangles))
        choice = choose_neutral_frame(positions, basis, capture2model=rough, reference=reference)
    else:
        choice = NeutralChoice(frame, f"neutral frame {frame} (given)")
    return place_markers(positions, names, basis, choice.frame, correspond), choice
