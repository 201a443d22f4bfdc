"""Random characters and the straightforward alpha blend the compositor is checked against."""

from __future__ import annotations

import numpy as np

from livebridge.character.alpha import crossfade_weight
from livebridge.character.composite import region_footprint, sample_alpha
from livebridge.character.definition import Character, CharacterRegion, Sample
from livebridge.character.states import NEUTRAL, CRStates


def random_character(rng: np.random.Generator, size=(160, 120), n_regions: int = 4, n_channels: int = 3,
                     feather_px: float = 4.0) -> Character:
    """Regions with elliptic masks that overlap their neighbours, 1-3 muscles of 1-4 random samples each
    (some with a drawn opacity of their own)."""
    width, height = size
    neutral = rng.uniform(0, 1, (height, width, n_channels)).astype(np.float32)
    yy, xx = np.mgrid[:height, :width]
    regions = []
    for r in range(n_regions):
        cx, cy = rng.uniform(0.25, 0.75) * width, rng.uniform(0.25, 0.75) * height
        ax, ay = rng.uniform(0.15, 0.3) * width, rng.uniform(0.15, 0.3) * height
        mask = np.square((xx - cx) / ax) + np.square((yy - cy) / ay) <= 1.0
        muscles, per_muscle = [], []
        for m in range(int(rng.integers(1, 4))):
            muscles.append(f"m{r}_{m}")
            samples = []
            for _ in range(int(rng.integers(1, 5))):
                w, h = int(rng.integers(20, width // 2)), int(rng.integers(20, height // 2))
                x0 = int(np.clip(cx - w / 2 + rng.integers(-8, 9), 0, width - w))
                y0 = int(np.clip(cy - h / 2 + rng.integers(-8, 9), 0, height - h))
                image = rng.uniform(0, 1, (h, w, n_channels)).astype(np.float32)
                opacity = np.ones((h, w), np.float32)
                if rng.uniform() < 0.3:
                    opacity = rng.uniform(0.2, 1.0, (h, w)).astype(np.float32)
                    opacity[: h // 4] = 0.0
                samples.append(Sample(image, opacity, (x0, y0), f"sample {r} {m}"))
            per_muscle.append(tuple(samples))
        regions.append(CharacterRegion(f"region{r}", tuple(muscles), tuple(per_muscle), mask))
    return Character("random", neutral, tuple(regions), feather_px)


def random_states(rng: np.random.Generator, character: Character) -> CRStates:
    """Each region neutral, at a sample's exact level, at 1, or anywhere between."""
    muscle, level = [], []
    for region in character.regions:
        kind = rng.integers(4)
        if kind == 0:
            muscle.append(NEUTRAL)
            level.append(0.0)
            continue
        m = int(rng.integers(len(region.muscles)))
        n = len(region.samples[m])
        muscle.append(m)
        level.append(float(rng.integers(1, n + 1) / n) if kind == 1 else 1.0 if kind == 2 else rng.uniform(0, 1))
    return CRStates(np.array(muscle), np.array(level))


def reference_blend(character: Character, states: CRStates) -> np.ndarray:
    """Each region in order, over the whole canvas: the two neighbouring states' composites cross-dissolved,
    their alphas cross-faded against every earlier active region they overlap. Shape (height, width, C)."""
    width, height = character.size
    out = character.neutral.astype(np.float64).copy()
    footprints = [region_footprint(region, character.size) for region in character.regions]
    active = [m >= 0 and lv > 0 for m, lv in zip(states.muscle, states.level)]
    for r, region in enumerate(character.regions):
        if not active[r]:
            continue
        m = int(states.muscle[r])
        n = len(region.samples[m])
        t = states.level[r] * n
        lower = min(int(np.floor(t)), n - 1)
        fraction = t - lower
        fade = np.ones((height, width))
        for q in range(r):
            if active[q] and (footprints[r] & footprints[q]).any():
                fade *= crossfade_weight(footprints[r], footprints[q])
        mixed_alpha = np.zeros((height, width))
        mixed_colour = np.zeros_like(out)
        for k, weight in ((lower, 1.0 - fraction), (lower + 1, fraction)):
            if k == 0:
                continue
            sample = region.samples[m][k - 1]
            x, y, w, h = sample.rect
            alpha = np.zeros((height, width))
            alpha[y:y + h, x:x + w] = sample_alpha(region, m, k, character.feather_px, character.size)
            colour = np.zeros_like(out)
            colour[y:y + h, x:x + w] = sample.image
            mixed_alpha += weight * alpha
            mixed_colour += weight * alpha[..., None] * colour
        out = out * (1.0 - fade * mixed_alpha)[..., None] + fade[..., None] * mixed_colour
    return out


# ------------------------------------------------------------------------------------------------ a tiny model
TOY_SIZE = (96, 72)
TOY_REGIONS = (("upper", ("a",), (5,), (slice(4, 30), slice(8, 88))),
               ("lower", ("b", "c", "mix"), (4, 3, 3), (slice(34, 68), slice(20, 76))))
TOY_ACTUATIONS = {"a": (1.0, 0.0, 0.0), "b": (0.0, 1.0, 0.0), "c": (0.0, 0.0, 1.0), "mix": (0.0, 1.0, 0.5)}
"""What each toy (pseudo-)muscle means in the basis muscles a, b, c: ``mix`` is b with half of c."""
"""(name, muscles, n_states per muscle (state 0 neutral), the region's rows and columns)."""


def toy_neutral() -> np.ndarray:
    """A textured canonical face, grey levels 0..255, shape (72, 96) float32."""
    yy, xx = np.mgrid[:TOY_SIZE[1], :TOY_SIZE[0]]
    return (120 + 40 * np.sin(xx / 5.0) * np.cos(yy / 7.0)).astype(np.float32)


def toy_appearance(levels: dict[str, float]) -> np.ndarray:
    """The toy face with muscles at ``levels`` (name -> [0, 1]), grey levels, shape (72, 96) float32.

    ``a`` lowers a dark bar through the upper region, ``b`` widens a bright band in the lower region, ``c``
    darkens the lower region's right half: each region's look is a smooth function of its muscles' levels.
    """
    image = toy_neutral()
    yy, xx = np.mgrid[:TOY_SIZE[1], :TOY_SIZE[0]]
    mix = levels.get("mix", 0.0)
    a, b, c = (levels.get(m, 0.0) + mix * TOY_ACTUATIONS["mix"][k] for k, m in enumerate("abc"))
    if a:
        bar = np.exp(-np.square((yy - (8 + 18 * a)) / 2.5)) * (xx > 12) * (xx < 84)
        image -= 70 * a * bar
    if b:
        band = np.abs(yy - 50) < 1 + 12 * b
        image[band & (xx > 24) & (xx < 72)] += 60 * b
    if c:
        image[(yy > 36) & (yy < 66) & (xx > 48) & (xx < 74)] -= 60 * c
    return np.clip(image, 0, 255).astype(np.float32)


def toy_model():
    """A MarkerlessModel of the toy face: its regions, masks, and each state's canonical frame."""
    from livebridge.markerless.model import MarkerlessModel, RegionModel
    from livebridge.markerless.normalise import Normalisation

    regions, gestures = [], {}
    for name, muscles, n_states, window in TOY_REGIONS:
        mask = np.zeros((TOY_SIZE[1], TOY_SIZE[0]), bool)
        mask[window] = True
        n_pixels = int(mask.sum())
        back = np.zeros((2, n_pixels), np.float32)
        signatures = tuple(np.tile(np.float32([1.0, 0.0]), (n, 1)) for n in n_states)
        actuations = np.array([TOY_ACTUATIONS[m] for m in muscles])
        regions.append(RegionModel(name, mask, muscles, n_states, back, signatures, actuations, np.ones(3, bool),
                                   1.0))
        rows, cols = window
        box = (cols.start, rows.start, cols.stop - cols.start, rows.stop - rows.start)
        for muscle, n in zip(muscles, n_states):
            crops = np.stack([toy_appearance({muscle: k / (n - 1)})[window] for k in range(1, n)])
            gestures[muscle] = (np.clip(np.rint(crops), 0, 255).astype(np.uint8), box)
    neutral = np.clip(np.rint(toy_neutral()), 0, 255).astype(np.float32)
    return MarkerlessModel(("a", "b", "c"), tuple(regions), Normalisation(TOY_SIZE), neutral, gestures)
