"""Training a markerless model from a take of isolated gestures (and, optionally, combined ones).

The performer makes the gestures of a *gesture list* in order, resting at neutral between them; each
entry is a basis muscle (an isolated gesture) or a combination of muscles at given levels (a pseudo-muscle,
the paper's answer to co-articulation). Training:

1. normalises every frame (pose warp, crop); the canonical pose is the first frame's;
2. finds the bounded gestures from each frame's distance to neutral and, for where each ends, how much
   the face still moves there (:mod:`gestures`), one per list entry;
3. takes each gesture's region of influence from its peak frame (:mod:`regions`) and builds the CRs from
   the isolated gestures' ROIs; a pseudo-muscle joins every CR holding two or more of its muscles;
4. measures each bounded gesture frame's actuation level as the dense optical flow from neutral projected
   on the flow of the frame that moves most (the time index the paper uses is not linear in actuation when
   the performer accelerates), and keeps ``n_states`` states at evenly spaced levels (the frame nearest each);
5. per CR: the sample matrix of its gestures' state frames (Laplacian-filtered, masked), the signature basis
   (FastICA or PCA), ``M = V D^-1 U^T`` and each (pseudo-)muscle's signature set ``Phi_i``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from livebridge.errors import InputError
from livebridge.markerless.gestures import Gesture, GestureConfig, find_gestures
from livebridge.markerless.model import MarkerlessModel, RegionModel
from livebridge.markerless.normalise import Normalisation, PoseState, lighting_normalise, normalise
from livebridge.markerless.regions import RegionConfig, co_articulation_regions, regions_of_influence
from livebridge.markerless.signatures import back_substitution, signature_basis, signatures

ACTIVITY_SIGMA = 2.0
ACTIVITY_TOP = 0.01
"""The fraction of most changed pixels whose mean is the activity that finds gestures."""
BREADTH_TOP = 0.1
"""The fraction whose mean places each gesture's peak (:func:`~livebridge.markerless.gestures.find_gestures`'s
``breadth``): in `livebridge bench markerless` the jaw's top state went from 0.78 of its opening to its full
opening, its held-out error from 0.29 to 0.04 (0.05, 0.3 and all pixels gave the same within 0.0001 MAE)."""


@dataclass(frozen=True)
class GesturePrompt:
    """One entry of a gesture list: a name and the basis contractions of its full actuation."""

    name: str
    actuation: dict[str, float]

    @property
    def isolated(self) -> bool:
        return len(self.actuation) == 1


def isolated_prompts(muscle_names: Sequence[str]) -> tuple[GesturePrompt, ...]:
    """One full isolated gesture per muscle, in order (the simulated performer's training script)."""
    return tuple(GesturePrompt(name, {name: 1.0}) for name in muscle_names)


def combination_prompts(combinations: dict[str, dict[str, float]]) -> tuple[GesturePrompt, ...]:
    """Pseudo-muscle gestures: name -> {muscle: level at full actuation}."""
    return tuple(GesturePrompt(name, dict(levels)) for name, levels in combinations.items())


@dataclass(frozen=True)
class TrainConfig:
    """Training settings.

    Attributes
    ----------
    method : {"ica", "pca"}
    n_components : int
        Signature-basis size per CR (capped by the samples' rank).
    n_states : int
        States per (pseudo-)muscle beside neutral.
    seed : int
    clip_deviations : float or None
        Clip the filtered images at this many robust deviations of the neutral face's (None: no clip). It
        keeps the rig's frame edges and LEDs from dominating the eye regions, which under a turning head
        and drifting light otherwise read as a half-closed eye: `livebridge bench markerless` state accuracy
        1.000 clipped at 8, 0.884 unclipped (isolated MAE 0.0035 against 0.0146).
    regions, gestures : RegionConfig, GestureConfig
    """

    method: str = "ica"
    n_components: int = 24
    n_states: int = 12
    seed: int = 0
    clip_deviations: float | None = 8.0
    regions: RegionConfig = field(default_factory=RegionConfig)
    gestures: GestureConfig = field(default_factory=GestureConfig)


@dataclass(frozen=True, eq=False)
class TrainResult:
    """A trained model and what training found.

    Attributes
    ----------
    model : MarkerlessModel
    gestures : list of Gesture
        The bounded gestures, one per prompt.
    activity : ndarray, shape (n_frames,)
        Distance to neutral per frame (NaN where the LEDs were lost).
    rois : ndarray, shape (n_prompts, H, W), bool
    state_frames : dict of str -> ndarray of int
        Per prompt, the take's frame numbers of its states 1..n_states (level k / n_states).
    """

    model: MarkerlessModel
    gestures: list[Gesture]
    activity: np.ndarray
    rois: np.ndarray
    state_frames: dict


def canonical_frames(images: Iterable[np.ndarray], norm: Normalisation, face_mesh: tuple | None = None
                     ) -> tuple[Normalisation, np.ndarray, np.ndarray]:
    """Every frame of a take in the canonical pose (the first frame's; the warp follows ``face_mesh``,
    ``(vertices (n, 3), triangles (m, 3))`` in the rig's head frame, when given).

    Returns
    -------
    (Normalisation with the canonical pose set, frames (n, h, w) uint8, lost (n,) bool)
    """
    frames, lost = [], []
    state = PoseState()
    for image in images:
        if norm.head_rig is not None and norm.canonical_head2cam is None:
            state, frame = normalise(image, norm, state)
            if frame.head2cam is not None:
                norm = norm.with_canonical(frame.head2cam, *(face_mesh or (None, None)))
        state, frame = normalise(image, norm, state)
        frames.append(np.clip(np.rint(frame.image), 0, 255).astype(np.uint8))
        lost.append(frame.lost)
    if not frames:
        raise InputError("the take has no frames")
    return norm, np.array(frames), np.array(lost)


def change_curves(frames: np.ndarray, lost: np.ndarray, tops: tuple = (ACTIVITY_TOP, BREADTH_TOP),
                  motion_top: float = BREADTH_TOP) -> tuple[np.ndarray, np.ndarray]:
    """How each frame differs from neutral and from its neighbours, each frame blurred once.

    Returns
    -------
    activities : ndarray, shape (n, len(tops))
        Per frame and fraction ``top``, the mean of the largest ``top`` of the blurred differences to the first
        frames. The few most changed pixels (:data:`ACTIVITY_TOP`) find a weak muscle's gesture, which a mean
        over the whole image would drown in noise; they saturate before a large gesture is full, whose peak the
        broader :data:`BREADTH_TOP` finds. NaN for a lost frame.
    motion : ndarray, shape (n,)
        Per frame, the mean of the largest ``motion_top`` of the blurred differences between the frames before
        and after it (NaN at the take's ends and next to a lost frame). At a gesture's turning point or in a
        hold it falls to the frames' noise, where the activity's distance from neutral may have stopped growing
        frames earlier (see :mod:`~livebridge.markerless.gestures`).
    """
    seen = np.flatnonzero(~lost)
    if len(seen) == 0:
        raise InputError("the head rig's LEDs were never found in the take")
    reference = np.median([_blurred(frames[i]) for i in seen[:5]], axis=0)
    counts = [max(1, int(top * reference.size)) for top in tops]
    motion_count = max(1, int(motion_top * reference.size))
    activities = np.full((len(frames), len(tops)), np.nan)
    motion = np.full(len(frames), np.nan)
    before = [None, None]  # the two frames before this one, blurred (None: lost)
    for i, frame in enumerate(frames):
        now = None if lost[i] else _blurred(frame)
        if now is not None:
            activities[i] = _top_means(np.abs(now - reference), counts)
            if before[0] is not None:
                motion[i - 1] = _top_means(np.abs(now - before[0]), [motion_count])[0]
        before = [before[1], now]
    return activities, motion


def _blurred(frame: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(frame.astype(np.float32), (0, 0), ACTIVITY_SIGMA)


def _top_means(change: np.ndarray, counts: list[int]) -> list[float]:
    """The mean of the largest ``count`` values of ``change`` (any shape), for each of ``counts``."""
    change = np.partition(change.ravel(), [change.size - count for count in counts])
    return [change[-count:].mean() for count in counts]


def _neutral_frames(n_frames: int, gestures: list[Gesture], lost: np.ndarray) -> np.ndarray:
    neutral = ~lost.copy()
    for g in gestures:
        neutral[max(0, g.start - 3):g.end + 4] = False
    return np.flatnonzero(neutral)


def _flow_levels(frames: np.ndarray, neutral: np.ndarray, roi: np.ndarray) -> np.ndarray:
    """Actuation levels (0..1, non-decreasing) of a bounded gesture's frames from optical flow, shape (n,).

    The dense flow from neutral to each frame (inside ``roi``, on its box) is projected on the flow at the
    gesture's last frame (its maximum actuation).
    """
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    x, y, w, h = cv2.boundingRect(roi.astype(np.uint8))
    margin = 16  # the flow needs context around the region
    x0, y0 = max(0, x - margin), max(0, y - margin)
    x1, y1 = min(roi.shape[1], x + w + margin), min(roi.shape[0], y + h + margin)
    inside = roi[y0:y1, x0:x1]
    base = np.ascontiguousarray(neutral[y0:y1, x0:x1])
    fields = np.array([flow.calc(base, np.ascontiguousarray(frame[y0:y1, x0:x1]), None)[inside].ravel()
                       for frame in frames])  # (n, 2 n_roi)
    full = fields[-1]
    energy = float(full @ full)
    if len(frames) < 2 or energy <= 1e-6 * max(1, inside.sum()):
        return np.linspace(0.0, 1.0, len(frames)) if len(frames) > 1 else np.ones(1)
    levels = np.maximum.accumulate(np.clip(fields @ full / energy, 0.0, None))
    return np.clip(levels / max(levels.max(), 1e-9), 0.0, 1.0)


def _state_frames(levels: np.ndarray, n_states: int) -> np.ndarray:
    """Index of the gesture frame nearest each level k / n_states, k = 1..n_states, shape (n_states,)."""
    targets = np.arange(1, n_states + 1) / n_states
    return np.abs(levels[None, :] - targets[:, None]).argmin(axis=1)


def _filtered(frame: np.ndarray, norm: Normalisation) -> np.ndarray:
    image = frame.astype(np.float32)
    return lighting_normalise(image, norm.blur_sigma, norm.log, norm.clip) if norm.laplacian else image


def train(images: Iterable[np.ndarray], norm: Normalisation, prompts: Sequence[GesturePrompt],
          muscle_names: Sequence[str], config: TrainConfig = TrainConfig(),
          face_mesh: tuple[np.ndarray, np.ndarray] | None = None) -> TrainResult:
    """Train a markerless model from a take (see the module docstring).

    Parameters
    ----------
    images : iterable of ndarray, each shape (H, W) or (H, W, 3)
        The take's frames, ``(W, H) == norm.input_size``.
    norm : Normalisation
        How to normalise (head rig or crop, Laplacian); its canonical pose is set here.
    prompts : sequence of GesturePrompt
        The gesture list, in the order performed.
    muscle_names : sequence of str
        Basis muscles (every prompt's muscles must be among them).
    config : TrainConfig
    face_mesh : (ndarray (n, 3), ndarray (m, 3)), optional
        The performer's neutral face (vertices in mm in the head rig's frame, triangles), e.g. the basis's:
        the pose warp follows its relief instead of a plane.

    Returns
    -------
    TrainResult
    """
    muscle_names = tuple(muscle_names)
    for prompt in prompts:
        unknown = sorted(set(prompt.actuation) - set(muscle_names))
        if unknown:
            raise InputError(f"gesture {prompt.name!r} names muscles {unknown} not in the basis")
    norm, frames, lost = canonical_frames(images, norm, face_mesh)
    activities, motion = change_curves(frames, lost)
    gestures = find_gestures(activities[:, 0], config.gestures, breadth=activities[:, 1], motion=motion)
    if len(gestures) != len(prompts):
        raise InputError(f"found {len(gestures)} gestures in the take, the gesture list has {len(prompts)} "
                         "(each gesture must start and end at neutral)")
    neutral_index = _neutral_frames(len(frames), gestures, lost)
    if len(neutral_index) < 2:
        raise InputError("the take has no neutral frames between its gestures")
    neutral = frames[neutral_index].astype(np.float32).mean(axis=0)
    rois = regions_of_influence(frames[[g.peak for g in gestures]], neutral,
                                frames[neutral_index[len(neutral_index) // 2]], config.regions)
    isolated = [p for p, prompt in enumerate(prompts) if prompt.isolated]
    crs = co_articulation_regions(rois[isolated], config.regions)
    neutral_u8 = np.clip(np.rint(neutral), 0, 255).astype(np.uint8)
    if norm.laplacian and config.clip_deviations is not None:
        plain = lighting_normalise(frames[neutral_index[0]].astype(np.float32), norm.blur_sigma, norm.log)
        norm = replace(norm, clip=float(config.clip_deviations * 1.4826 * np.median(np.abs(plain))))
    states = {}
    for p, gesture in enumerate(gestures):
        roi = rois[p] if rois[p].any() else np.ones_like(rois[p])
        levels = _flow_levels(frames[gesture.frames], neutral_u8, roi)
        states[p] = gesture.frames[_state_frames(levels, config.n_states)]
    neutral_filtered = np.mean([_filtered(frames[i], norm) for i in neutral_index[:: max(1, len(neutral_index) // 16)]],
                               axis=0)
    regions, members = [], []
    for j, cr in enumerate(crs):
        governed = {prompts[isolated[i]].name for i in cr.muscles}
        chosen = [isolated[i] for i in cr.muscles]
        chosen += [p for p, prompt in enumerate(prompts)
                   if not prompt.isolated and len(governed & set(prompt.actuation)) >= 2]
        weights = np.zeros(len(muscle_names))
        for i in cr.muscles:
            roi = rois[isolated[i]]
            weights[muscle_names.index(prompts[isolated[i]].name)] = (roi & cr.mask).sum() / max(1, roi.sum())
        regions.append(_region(f"cr{j + 1}", cr.mask, chosen, prompts, states, frames, neutral_filtered, norm,
                               muscle_names, weights, config))
        members.append(chosen)
    gesture_frames = _gesture_crops(prompts, states, frames, crs, members)
    model = MarkerlessModel(muscle_names, regions, norm, neutral, gesture_frames, config.method)
    return TrainResult(model, gestures, activities[:, 0], rois, {prompts[p].name: states[p] for p in states})


def _region(name, mask, chosen, prompts, states, frames, neutral_filtered, norm, muscle_names, weights,
            config: TrainConfig) -> RegionModel:
    pixels = np.flatnonzero(mask)
    columns = {p: np.array([_filtered(frames[i], norm).ravel()[pixels] for i in states[p]]).T for p in chosen}
    neutral_column = neutral_filtered.ravel()[pixels][:, None]
    samples = np.concatenate([neutral_column] + [columns[p] for p in chosen], axis=1)
    basis = signature_basis(samples, config.n_components, config.method, config.seed)
    back = back_substitution(basis)
    phis = tuple(signatures(back, np.concatenate([neutral_column, columns[p]], axis=1)).astype(np.float32)
                 for p in chosen)
    actuations = np.array([[prompts[p].actuation.get(m, 0.0) for m in muscle_names] for p in chosen])
    sample_norm = float(np.median(np.linalg.norm(samples, axis=0)))
    return RegionModel(name, mask, tuple(prompts[p].name for p in chosen), tuple(len(phi) for phi in phis),
                       back.astype(np.float32), phis, actuations, weights, sample_norm)


def _gesture_crops(prompts, states, frames, crs, members) -> dict:
    """Per (pseudo-)muscle in some CR: its state frames cropped to the box of its CRs."""
    crops = {}
    for p, prompt in enumerate(prompts):
        masks = [cr.mask for cr, chosen in zip(crs, members) if p in chosen]
        if not masks:
            continue
        x, y, w, h = cv2.boundingRect(np.any(masks, axis=0).astype(np.uint8))
        crops[prompt.name] = (frames[states[p]][:, y:y + h, x:x + w].copy(), (x, y, w, h))
    return crops
