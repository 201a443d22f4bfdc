"""Video rewrite: a character filled from a markerless model's training frames, and how well it rebuilds video.

Filled from the training samples instead of drawings (the paper's §6), each region's sample for a state is
the region's pixels in the canonical frame that defines that state (``model.state_frame``), so a new
performance is rebuilt from the actor's own appearance. Each CR mask is grown by the feather width first:
the alpha ramp then lies on the pixels just outside the region, which the state barely changes, and
neighbouring regions overlap there (and cross-fade) instead of leaving a seam of the neutral face between them.

:func:`rewrite_scores` measures a rebuilt take against the true canonical frames: PSNR per region (over its
CR mask) and overall (over all the masks), next to the PSNR of the neutral image alone (the peer).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from livebridge.character.composite import Compositor
from livebridge.character.definition import Character, CharacterRegion, Sample
from livebridge.character.states import CRStates


def intensity_scale(model) -> float:
    """The white level of the model's canonical images: 255 for 8-bit grey values, else 1."""
    return 255.0 if float(np.max(model.neutral_image)) > 1.5 else 1.0


def character_from_model(model, feather_px: float = 10.0, name: str = "video rewrite") -> Character:
    """A grey character on the model's canonical image with one sample per training state of every CR.

    Parameters
    ----------
    model : MarkerlessModel
        Anything with ``neutral_image (H, W)``, ``regions`` (``name``, ``mask (H, W)``, ``muscles``,
        ``n_states`` with state 0 neutral) and ``state_frame(region, muscle, state) -> (H, W)``.
    feather_px : float
        Width of the samples' alpha ramp; also how far each CR mask is grown.
    name : str
    """
    scale = np.float32(intensity_scale(model))
    neutral = (np.asarray(model.neutral_image, np.float32) / scale)[..., None]
    grow = max(1, int(round(feather_px)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    regions = []
    for cr in model.regions:
        mask = cv2.dilate(np.asarray(cr.mask, np.uint8), kernel) > 0
        ys, xs = np.nonzero(mask)
        x0, y0, x1, y1 = int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1
        per_muscle = []
        for muscle, n_states in zip(cr.muscles, cr.n_states):
            # a muscle trained without any non-neutral state keeps one sample, the neutral face, so the
            # character's muscle indices stay the model's
            states = range(1, n_states) if n_states > 1 else (0,)
            per_muscle.append(tuple(
                Sample((model.state_frame(cr.name, muscle, k)[y0:y1, x0:x1] / scale)[..., None].astype(np.float32),
                       np.ones((y1 - y0, x1 - x0), np.float32), (x0, y0), f"{cr.name} {muscle} state {k}")
                for k in states))
        regions.append(CharacterRegion(cr.name, tuple(cr.muscles), tuple(per_muscle), mask,
                                       _pseudo_actuations(cr, model.muscle_names)))
    return Character(name, neutral, tuple(regions), feather_px)


def _pseudo_actuations(cr, muscle_names) -> dict[str, dict[str, float]]:
    """The model's actuation of each pseudo-muscle (the muscles that are not basis muscles) of a CR."""
    actuations = {}
    for j, muscle in enumerate(cr.muscles):
        if muscle not in muscle_names:
            row = np.asarray(cr.actuations)[j]
            actuations[muscle] = {muscle_names[i]: float(row[i]) for i in np.flatnonzero(row)}
    return actuations


def psnr_db(squared_error: float, count: int, peak: float = 1.0) -> float:
    """PSNR (dB) of a summed squared error over ``count`` values; inf when exact."""
    mse = squared_error / max(count, 1)
    return float("inf") if mse == 0 else float(10.0 * np.log10(peak * peak / mse))


@dataclass(frozen=True)
class RewriteScore:
    """PSNR of a rebuilt take against the truth, and of the neutral image alone, dB.

    Attributes
    ----------
    regions : tuple of str
    rewrite_db, neutral_db : tuple of float
        Per region, over its CR mask.
    overall_rewrite_db, overall_neutral_db : float
        Over the union of the CR masks.
    frames : int
    """

    regions: tuple[str, ...]
    rewrite_db: tuple[float, ...]
    neutral_db: tuple[float, ...]
    overall_rewrite_db: float
    overall_neutral_db: float
    frames: int


def rewrite_scores(compositor: Compositor, masks: Iterable[np.ndarray],
                   frames: Iterable[tuple[np.ndarray, CRStates]]) -> RewriteScore:
    """Score a rebuilt take.

    Parameters
    ----------
    compositor : Compositor
        Of a one-channel character (a video-rewrite character).
    masks : iterable of ndarray of bool, shape (H, W)
        Where each region is scored (the model's CR masks, in the character's region order).
    frames : iterable of (ndarray (H, W), CRStates)
        The true canonical frame (in [0, 1]) and the states the analysis found in it.
    """
    masks = [np.asarray(m, bool) for m in masks]
    union = np.logical_or.reduce(masks)
    neutral = compositor.neutral[..., 0].astype(np.float64)
    n = len(masks)
    rewrite_err, neutral_err = np.zeros(n + 1), np.zeros(n + 1)
    count = 0
    buffer = np.empty_like(compositor.neutral)
    for truth, states in frames:
        truth = np.asarray(truth, np.float64)
        rebuilt = compositor.composite(states, buffer)[..., 0].astype(np.float64)
        e_rewrite, e_neutral = np.square(rebuilt - truth), np.square(neutral - truth)
        for r, mask in enumerate(masks + [union]):
            rewrite_err[r] += e_rewrite[mask].sum()
            neutral_err[r] += e_neutral[mask].sum()
        count += 1
    sizes = [int(m.sum()) * count for m in masks + [union]]
    return RewriteScore(compositor.character.region_names,
                        tuple(psnr_db(e, s) for e, s in zip(rewrite_err[:n], sizes)),
                        tuple(psnr_db(e, s) for e, s in zip(neutral_err[:n], sizes)),
                        psnr_db(rewrite_err[n], sizes[n]), psnr_db(neutral_err[n], sizes[n]), count)
