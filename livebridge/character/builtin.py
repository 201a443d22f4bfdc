"""The built-in character: a cartoon face drawn procedurally with OpenCV, so no data is needed.

:func:`draw_cartoon` draws the face for any contractions of the 16 Choe-Ko muscles of the built-in basis
(brows raised by the frontalis and knitted by the corrugator, eyelids closed by the orbicularis oculi, the
nose wrinkled by the levator labii, mouth corners pulled by the zygomatic major, risorius and depressor
anguli oris, lips pursed by the orbicularis oris and pressed by the lips pressor, the mouth opened and the
chin lowered by the jaw). :func:`builtin_character` turns it into a flip-book character: the neutral face,
and per region of :data:`BUILTIN_LAYOUT` (the muscles grouped into nine regions like the paper's CRs) and
per state of each muscle, the face drawn with that muscle alone at that level, cut to the region's mask.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from livebridge.character.definition import Character, CharacterRegion, Sample
from livebridge.character.states import components

DESIGN_SIZE = (640, 480)
"""The canvas the drawing is designed on; other sizes scale it (keeping the aspect, centred)."""
SKIN = (245, 205, 170)
LINE = (80, 45, 30)
BACKGROUND = (70, 92, 124)
LIP = (200, 90, 95)
MOUTH_INSIDE = (70, 20, 25)
IRIS = (70, 120, 170)


@dataclass(frozen=True)
class RegionShape:
    """A region of the built-in layout: its muscles and its mask, an ellipse on the design canvas."""

    name: str
    muscles: tuple[str, ...]
    centre: tuple[float, float]
    axes: tuple[float, float]
    exclude: tuple[tuple[float, float], tuple[float, float]] | None = None  # (centre, axes) of a hole


BUILTIN_LAYOUT = (
    RegionShape("brow_L", ("frontalis_L", "corrugator_L", "frontalis_L+corrugator_L"), (395, 120), (115, 70)),
    RegionShape("brow_R", ("frontalis_R", "corrugator_R", "frontalis_R+corrugator_R"), (245, 120), (115, 70)),
    RegionShape("eye_L", ("orbicularis_oculi_L",), (395, 205), (62, 45)),
    RegionShape("eye_R", ("orbicularis_oculi_R",), (245, 205), (62, 45)),
    RegionShape("nose", ("levator_labii_L", "levator_labii_R", "levator_labii_L+levator_labii_R"), (320, 275),
                (60, 48)),
    RegionShape("cheek_L", ("zygomatic_major_L", "risorius_L"), (425, 318), (42, 46)),
    RegionShape("cheek_R", ("zygomatic_major_R", "risorius_R"), (215, 318), (42, 46)),
    RegionShape("mouth", ("jaw", "zygomatic_major_L+zygomatic_major_R", "jaw+zygomatic_major_L+zygomatic_major_R",
                          "zygomatic_major_L", "zygomatic_major_R", "risorius_L+risorius_R", "orbicularis_oris",
                          "lips_pressor", "depressor_anguli_oris"), (320, 355), (112, 52)),
    RegionShape("chin", ("jaw",), (320, 420), (200, 95), exclude=((320, 352), (100, 40))),
)
"""The nine regions of the built-in character, in compositing order (the performer's left is drawn on the
viewer's right). The mouth is one region whose candidates include the combinations the face makes (a smile,
an open smile), so its one active state per frame is a whole mouth shape."""


def _transform(size: tuple[int, int]) -> tuple[float, float, float]:
    """``(scale, dx, dy)`` from the design canvas to a canvas of ``size``."""
    width, height = size
    scale = min(width / DESIGN_SIZE[0], height / DESIGN_SIZE[1])
    return scale, (width - scale * DESIGN_SIZE[0]) / 2, (height - scale * DESIGN_SIZE[1]) / 2


class _Pen:
    """Draws on a canvas in design coordinates (anti-aliased, sub-pixel)."""

    SHIFT = 4

    def __init__(self, image: np.ndarray, size: tuple[int, int]):
        self.image = image
        self.scale, self.dx, self.dy = _transform(size)

    def _pts(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        p = p * self.scale + [self.dx, self.dy]
        return np.rint(p * (1 << self.SHIFT)).astype(np.int32)

    def polygon(self, points, colour) -> None:
        cv2.fillPoly(self.image, [self._pts(points)], colour, cv2.LINE_AA, self.SHIFT)

    def line(self, points, colour, width: float) -> None:
        thickness = max(1, int(round(width * self.scale)))
        cv2.polylines(self.image, [self._pts(points)], False, colour, thickness, cv2.LINE_AA, self.SHIFT)

    def ellipse(self, centre, axes, colour, width: float = -1) -> None:
        thickness = -1 if width < 0 else max(1, int(round(width * self.scale)))
        c = self._pts([centre])[0]
        a = np.rint(np.asarray(axes) * self.scale * (1 << self.SHIFT)).astype(int)
        cv2.ellipse(self.image, (int(c[0]), int(c[1])), (int(a[0]), int(a[1])), 0, 0, 360, colour, thickness,
                    cv2.LINE_AA, self.SHIFT)


def _mix(a, b, t: float) -> tuple[int, int, int]:
    t = float(np.clip(t, 0.0, 1.0))
    return tuple(int(round((1 - t) * u + t * v)) for u, v in zip(a, b))


def _curve(a, b, bulge: float, n: int = 24, power: float = 1.0) -> np.ndarray:
    """Points from ``a`` to ``b`` bowed by ``bulge`` (design px, +: down) in the middle, shape (n, 2)."""
    u = np.linspace(0.0, 1.0, n)[:, None]
    base = (1 - u) * np.asarray(a, float) + u * np.asarray(b, float)
    return base + np.hstack([np.zeros_like(u), bulge * np.sin(np.pi * u) ** power])


def draw_cartoon(contractions: dict[str, float], size: tuple[int, int] = DESIGN_SIZE) -> np.ndarray:
    """The cartoon face for ``contractions`` (muscle name -> level in [0, 1]; missing: 0).

    Returns
    -------
    ndarray of float32, shape (height, width, 3)
        RGB in [0, 1].
    """
    x = {name: float(np.clip(value, 0.0, 1.0)) for name, value in contractions.items()}
    width, height = size
    image = np.empty((height, width, 3), np.uint8)
    image[:] = BACKGROUND
    pen = _Pen(image, size)
    jaw = x.get("jaw", 0.0)
    _draw_head(pen, jaw)
    for side, s in (("L", 1.0), ("R", -1.0)):
        _draw_brow(pen, s, x.get(f"frontalis_{side}", 0.0), x.get(f"corrugator_{side}", 0.0))
        _draw_eye(pen, s, x.get(f"orbicularis_oculi_{side}", 0.0))
    _draw_nose(pen, x.get("levator_labii_L", 0.0), x.get("levator_labii_R", 0.0))
    _draw_mouth(pen, x, jaw)
    return image.astype(np.float32) / 255.0


def _draw_head(pen: _Pen, jaw: float) -> None:
    t = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    px, py = 320 + 175 * np.cos(t), 240 + 215 * np.sin(t)
    below = py > 345
    py = np.where(below, py + 38 * jaw * (py - 345) / (455 - 345), py)  # the chin follows the jaw
    pen.polygon(np.stack([px, py], 1), SKIN)
    pen.line(np.stack([px, py], 1)[below], LINE, 2)
    pen.polygon([[150, 150], [170, 60], [260, 22], [380, 22], [470, 60], [490, 150], [440, 80], [320, 60],
                 [200, 80]], (90, 60, 40))  # hair


def _draw_brow(pen: _Pen, s: float, frontalis: float, corrugator: float) -> None:
    inner = np.array([320 + s * 30, 150.0])
    middle = np.array([320 + s * 75, 138.0])
    outer = np.array([320 + s * 118, 150.0])
    raise_by = 24 * frontalis
    inner = inner + [-s * 10 * corrugator, 16 * corrugator - raise_by * 1.1]
    middle = middle + [0.0, 6 * corrugator - raise_by]
    outer = outer + [0.0, -0.6 * raise_by]
    pen.line([outer, middle, inner], LINE, 9)
    for k in range(3):  # forehead wrinkles come with the frontalis
        y = 100 - 14 * k - 0.4 * raise_by
        pen.line(_curve([320 + s * 15, y], [320 + s * 95, y + 4], -5), _mix(SKIN, LINE, 0.7 * frontalis), 2)
    pen.line([[320 + s * 12, 150 - 14 * corrugator], [320 + s * 8, 180]], _mix(SKIN, LINE, corrugator), 3)


def _draw_eye(pen: _Pen, s: float, closure: float) -> None:
    centre = np.array([320 + s * 75, 205.0])
    half_w, half_h = 38.0, 22.0
    eye = np.zeros(pen.image.shape[:2], np.uint8)
    _Pen(eye, (eye.shape[1], eye.shape[0])).ellipse(centre, (half_w, half_h), 255)
    pen.ellipse(centre, (half_w, half_h), (250, 250, 250))
    pen.ellipse(centre + [0, 2], (14, 14), IRIS)
    pen.ellipse(centre + [0, 2], (6, 6), (15, 15, 20))
    # the upper lid: skin over the eye above a curve that drops as the orbicularis oculi closes it
    bulge = -1.1 * half_h + closure * 1.95 * half_h  # from above the eye's top to near its bottom
    lid = _curve(centre + [-half_w - 2, 0.0], centre + [half_w + 2, 0.0], bulge)
    cover = np.zeros_like(eye)
    top = np.vstack([lid, [centre + [half_w + 4, -half_h - 8], centre + [-half_w - 4, -half_h - 8]]])
    _Pen(cover, (eye.shape[1], eye.shape[0])).polygon(top, 255)
    region = (eye.astype(np.float32) / 255) * (cover.astype(np.float32) / 255)
    pen.image[:] = np.rint(pen.image * (1 - region[..., None]) + np.array(SKIN) * region[..., None]).astype(np.uint8)
    pen.ellipse(centre, (half_w, half_h), LINE, 2)
    inside = np.abs(lid[:, 0] - centre[0]) < half_w - 2
    pen.line(lid[inside], LINE, 3)
    # the sphincter lifts the cheek below the eye
    pen.line(_curve(centre + [-30, 34 - 8 * closure], centre + [30, 34 - 8 * closure], 6 - 4 * closure),
             _mix(SKIN, LINE, 0.8 * closure), 2)


def _draw_nose(pen: _Pen, levator_l: float, levator_r: float) -> None:
    pen.line(_curve([316, 225], [306, 288], 4), _mix(SKIN, LINE, 0.5), 2)
    for s, lift in ((1.0, levator_l), (-1.0, levator_r)):
        wing = np.array([320 + s * 20, 292 - 8 * lift])
        pen.line(_curve(wing + [-s * 2, -14], wing + [-s * 14, 6], s * 4), LINE, 3)
        pen.ellipse(wing + [-s * 9, 0], (5, 3), _mix(SKIN, LINE, 0.7))
        for k in range(2):  # wrinkles on the side of the nose
            y = 250 + 9 * k - 4 * lift
            pen.line([[320 + s * 8, y], [320 + s * 20, y + 4]], _mix(SKIN, LINE, 0.8 * lift), 2)
        pen.line(_curve(wing + [s * 8, -4], [320 + s * 66, 350 - 6 * lift], s * 6), _mix(SKIN, LINE, 0.25 + 0.5 * lift),
                 2)  # the nasolabial fold deepens


def _draw_mouth(pen: _Pen, x: dict[str, float], jaw: float) -> None:
    pucker, press = x.get("orbicularis_oris", 0.0), x.get("lips_pressor", 0.0)
    depressor = x.get("depressor_anguli_oris", 0.0)
    corners = []
    for s, side in ((-1.0, "R"), (1.0, "L")):
        smile, wide = x.get(f"zygomatic_major_{side}", 0.0), x.get(f"risorius_{side}", 0.0)
        cx = 320 + s * (58 + 12 * smile + 20 * wide - 30 * pucker)
        cy = 345 - 24 * smile + 18 * depressor + 3 * wide + 10 * jaw
        corners.append(np.array([cx, cy]))
    right, left = corners
    opening = 44 * jaw + 12 * pucker * (1 - press)
    upper_thick = (9 + 6 * pucker) * (1 - 0.75 * press)
    lower_thick = (11 + 6 * pucker) * (1 - 0.75 * press)
    # how far the middle of the mouth sags below the line between its corners: a smile, or a frown (< 0)
    curvature = 2 + 14 * min(x.get("zygomatic_major_L", 0.0) + x.get("zygomatic_major_R", 0.0), 1.5) \
        - 12 * depressor
    inner_top = _curve(right, left, curvature - 0.35 * opening, power=0.7)
    inner_bottom = _curve(right, left, curvature + 0.65 * opening, power=0.7)
    outer_top = _curve(right, left, curvature - 0.35 * opening - upper_thick, power=0.5)
    outer_bottom = _curve(right, left, curvature + 0.65 * opening + lower_thick, power=0.5)
    pen.polygon(np.vstack([outer_top, inner_top[::-1]]), LIP)
    pen.polygon(np.vstack([inner_bottom, outer_bottom[::-1]]), _mix(LIP, (255, 255, 255), 0.1))
    if opening > 0.5:
        pen.polygon(np.vstack([inner_top, inner_bottom[::-1]]), MOUTH_INSIDE)
        teeth = _curve(right + [6, 0], left + [-6, 0], curvature - 0.35 * opening + 3, power=0.7)
        pen.line(teeth, (240, 240, 235), max(1.0, min(6.0, 0.25 * opening)))
    pen.line(inner_top, LINE, 2)
    pen.line(inner_bottom, LINE, 2 if opening > 0.5 else 1)
    for corner, s in ((right, -1.0), (left, 1.0)):  # dimples when the corners pull
        pull = x.get(f"zygomatic_major_{'L' if s > 0 else 'R'}", 0.0)
        pen.line(_curve(corner + [s * 6, -8], corner + [s * 9, 8], s * 3), _mix(SKIN, LINE, 0.8 * pull), 2)


def region_mask(shape: RegionShape, size: tuple[int, int]) -> np.ndarray:
    """The region's mask on a canvas of ``size``, shape (height, width) bool."""
    mask = np.zeros((size[1], size[0]), np.uint8)
    pen = _Pen(mask, size)
    pen.ellipse(shape.centre, shape.axes, 255)
    if shape.exclude is not None:
        pen.ellipse(*shape.exclude, 0)
    return mask >= 128


@lru_cache(maxsize=4)
def builtin_character(size: tuple[int, int] = DESIGN_SIZE, n_states: int = 3,
                      feather_px: float = 10.0) -> Character:
    """The cartoon as a character: ``n_states`` samples per muscle of every region (cached per arguments).

    Parameters
    ----------
    size : (int, int)
        ``(width, height)`` of the canvas.
    n_states : int
        Samples per muscle, at levels ``k / n_states``.
    feather_px : float
    """
    neutral = draw_cartoon({}, size)
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(feather_px) + 5, 2 * int(feather_px) + 5))
    regions = []
    for shape in BUILTIN_LAYOUT:
        drawn = {(muscle, k): draw_cartoon({part: k / n_states for part in components(muscle)}, size)
                 for muscle in shape.muscles for k in range(1, n_states + 1)}
        # like an artist, draw only what changes: the region's pixels that some state changes, grown so the
        # alpha ramp lies on unchanged skin (and the compositor touches no pixel it need not)
        changed = np.zeros(neutral.shape[:2], np.uint8)
        for image in drawn.values():
            changed |= (np.abs(image - neutral).max(axis=2) > 1.0 / 255).astype(np.uint8)
        mask = region_mask(shape, size) & (cv2.dilate(changed, grow) > 0)
        ys, xs = np.nonzero(mask)
        x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
        per_muscle = tuple(
            tuple(Sample(drawn[(muscle, k)][y0:y1, x0:x1].copy(), np.ones((y1 - y0, x1 - x0), np.float32),
                         (int(x0), int(y0)), f"builtin {shape.name} {muscle} {k}/{n_states}")
                  for k in range(1, n_states + 1))
            for muscle in shape.muscles)
        regions.append(CharacterRegion(shape.name, shape.muscles, per_muscle, mask))
    return Character("builtin", neutral, tuple(regions), feather_px)
