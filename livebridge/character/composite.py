"""Per-frame compositing of a character from its CR states.

Each region, in the character's order, is alpha-blended over the image so far (the neutral image first):
``out = out * (1 - a) + a * sample``. A level between two samples of the active muscle (``k / K`` and
``(k + 1) / K``; level 0 is the neutral image) cross-dissolves the two composites,
``(1 - f) * blend(out, lower) + f * blend(out, upper)``, which is one blend with both samples:
``out * (1 - (1 - f) a_lo - f a_hi) + (1 - f) a_lo s_lo + f a_hi s_hi`` (with the neutral image as the lower
state, its term is ``out`` itself). Alphas are the samples' feathered masks
(:func:`~livebridge.character.alpha.feathered_alpha`) times, where a region overlaps an earlier region that
is not neutral in this frame, the cross-fade weight (:func:`~livebridge.character.alpha.crossfade_weight`):
two active regions share their overlap, while a region whose neighbour rests shows in full.

Everything that does not change per frame (each region's rectangle on the canvas, every sample's alpha and
premultiplied colour padded to it) is prepared once, so a frame costs one copy of the neutral image and one
pass over the rectangle of each non-neutral region.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from livebridge.character.alpha import crossfade_weight, feathered_alpha
from livebridge.character.definition import Character, CharacterRegion
from livebridge.character.states import CRStates


def sample_alpha(region: CharacterRegion, muscle: int, state: int, feather_px: float,
                 canvas_size: tuple[int, int]) -> np.ndarray:
    """A sample's own alpha (before cross-fading), shape (h, w) of the sample: its drawn opacity inside the
    region's mask, feathered at the boundary (not at the edge of the ``(width, height)`` canvas). ``state``
    counts from 1."""
    sample = region.samples[muscle][state - 1]
    x, y, w, h = sample.rect
    shape = sample.opacity > 0
    if region.mask is not None:
        shape &= region.mask[y:y + h, x:x + w]
    open_edges = (y == 0, y + h == canvas_size[1], x == 0, x + w == canvas_size[0])
    return feathered_alpha(shape, feather_px, open_edges) * sample.opacity


def region_footprint(region: CharacterRegion, size: tuple[int, int]) -> np.ndarray:
    """Where a region draws, shape (height, width) bool: its mask, or the union of its samples' shapes."""
    if region.mask is not None:
        return region.mask
    footprint = np.zeros((size[1], size[0]), bool)
    for samples in region.samples:
        for sample in samples:
            x, y, w, h = sample.rect
            footprint[y:y + h, x:x + w] |= sample.opacity > 0
    return footprint


def overlaps(character: Character) -> list[list[tuple[int, np.ndarray]]]:
    """Per region, ``(earlier region, cross-fade weight (height, width))`` for each earlier region it overlaps."""
    footprints = [region_footprint(region, character.size) for region in character.regions]
    return [[(q, crossfade_weight(own, earlier)) for q, earlier in enumerate(footprints[:r]) if (own & earlier).any()]
            for r, own in enumerate(footprints)]


class _RegionTables:
    """One region's samples padded to its rectangle, ``layers (n_samples + 1, h, w, n_channels + 1)``: per
    sample its premultiplied colour and its alpha last (layer 0: the neutral state, all zero), and its
    cross-fade weights ``fades (n_overlaps, h, w)`` against the earlier regions it overlaps."""

    __slots__ = ("x", "y", "layers", "first", "counts", "fade_regions", "fades")

    def __init__(self, character: Character, region: CharacterRegion, overlapping: list[tuple[int, np.ndarray]]):
        rects = np.array([s.rect for samples in region.samples for s in samples])
        self.x, self.y = int(rects[:, 0].min()), int(rects[:, 1].min())
        width = int((rects[:, 0] + rects[:, 2]).max()) - self.x
        height = int((rects[:, 1] + rects[:, 3]).max()) - self.y
        n = len(rects)
        c = character.n_channels
        self.layers = np.zeros((n + 1, height, width, c + 1), np.float32)
        self.counts = tuple(len(samples) for samples in region.samples)
        self.first = tuple(1 + int(v) for v in np.concatenate([[0], np.cumsum(self.counts)[:-1]]))
        i = 1
        for m, samples in enumerate(region.samples):
            for k, sample in enumerate(samples, start=1):
                x, y, w, h = sample.rect
                alpha = sample_alpha(region, m, k, character.feather_px, character.size)
                window = (slice(y - self.y, y - self.y + h), slice(x - self.x, x - self.x + w))
                self.layers[i][window + (slice(0, c),)] = sample.image * alpha[..., None]
                self.layers[i][window + (c,)] = alpha
                i += 1
        self.fade_regions = np.array([q for q, _ in overlapping], dtype=np.int64)
        window = (slice(self.y, self.y + height), slice(self.x, self.x + width))
        self.fades = np.ascontiguousarray(np.stack([weight[window] for _, weight in overlapping])
                                          if overlapping else np.ones((0, height, width), np.float32))


def neighbours(level: float, n_samples: int) -> tuple[int, int, float]:
    """``(lower state, upper state, fraction of the upper)`` around ``level`` for samples at ``k / K``.

    States count from 1 (0: the neutral image); ``level`` 1 gives ``(K - 1, K, 1.0)``.
    """
    t = min(max(float(level), 0.0), 1.0) * n_samples
    lower = min(int(np.floor(t)), n_samples - 1)
    return lower, lower + 1, t - lower


class Compositor:
    """Composites frames of ``character`` from CR states (see the module docstring).

    Parameters
    ----------
    character : Character
    """

    def __init__(self, character: Character):
        self.character = character
        self.neutral = np.ascontiguousarray(character.neutral, dtype=np.float32)
        self.tables = tuple(_RegionTables(character, region, overlapping)
                            for region, overlapping in zip(character.regions, overlaps(character)))

    def composite(self, states: CRStates, out: np.ndarray | None = None) -> np.ndarray:
        """The frame for ``states``, shape (height, width, n_channels) float32 in [0, 1].

        ``out`` (same shape, float32), when given, is written and returned (no allocation per frame).
        """
        if out is None:
            out = self.neutral.copy()
        else:
            np.copyto(out, self.neutral)
        active = (np.asarray(states.muscle) >= 0) & (np.asarray(states.level) > 0.0)
        for r, table in enumerate(self.tables):
            if not active[r]:
                continue
            muscle = int(states.muscle[r])
            lower, upper, fraction = neighbours(states.level[r], table.counts[muscle])
            hi = table.first[muscle] + upper - 1
            lo = hi - 1 if lower > 0 else 0
            _blend(out, table.y, table.x, table.layers[lo], np.float32(1.0 - fraction), table.layers[hi],
                   np.float32(fraction), table.fades, active[table.fade_regions])
        return out


@njit(cache=True, nogil=True, fastmath=True)
def _blend(out, y0, x0, lower, w_lo, upper, w_hi, fades, fade_on):  # pragma: no cover - compiled
    """``out[window] = out * (1 - f (w_lo a_lo + w_hi a_hi)) + f (w_lo P_lo + w_hi P_hi)`` (P premultiplied),
    ``f`` the product of the cross-fade weights ``fades[p]`` of the active overlapping regions; ``lower``
    and ``upper`` are layers (h, w, n_channels + 1), alpha last."""
    height, width, n = upper.shape
    channels = n - 1
    one = np.float32(1.0)
    for i in range(height):
        row = out[y0 + i, x0:x0 + width]
        for j in range(width):
            covered = w_lo * lower[i, j, channels] + w_hi * upper[i, j, channels]
            if covered == 0:
                continue
            fade = one
            for p in range(fade_on.shape[0]):
                if fade_on[p]:
                    fade *= fades[p, i, j]
            keep = one - fade * covered
            lo, hi = fade * w_lo, fade * w_hi
            for c in range(channels):
                row[j, c] = row[j, c] * keep + lo * lower[i, j, c] + hi * upper[i, j, c]
