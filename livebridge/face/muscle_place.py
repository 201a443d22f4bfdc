"""Where an element moves the face, against where its muscle is.

A basis from scans names each element by the muscle the user gave its scan for. A new name gets its region and
side from where the element moves the face (:func:`muscle_for`); a Choe-Ko name has them already, and a scan
given for the wrong muscle or the wrong side (a right smile as ``zygomatic_major_L``, a brow raise as ``jaw``)
would pass silently into a basis the solver then splits the face by. :func:`misplaced` says so. A basis imported
from an artist's shapes has no landmarks, but its sides can still be told (:func:`side_warnings`): a rig whose
``_L`` shapes are the viewer's left, or a mesh whose +x is the subject's right, would drive the animatronic
head's right brow with the performer's left.

The place of an element's motion is its centre weighted by the squared motion: the element's tracking noise
(0.1-0.2 mm over the whole face) weighs next to nothing there. Weighted by the motion itself (as new muscles
were placed before), the closing left eye built from `livebridge bench scans`' 60k-point scans (seed 7) had its
centre 19.0 mm left of the midline and 19.5 mm up, below the outer eye corners (30 mm): a blink scanned under a
new name became a lower-face muscle. Weighted by its square: 33.5 and 34.1 mm, the true element's 34.2 and 34.4;
every other element of those scans within 0.8 mm of its true centre.
"""

from __future__ import annotations

import numpy as np

from livebridge.face.basis import CHOE_KO_BY_NAME, Muscle

SIDE_EYE_DISTANCES = 0.1
"""A centre further than this many outer-eye-corner distances off the midline is on one side."""
SIDE_WIDTHS = 0.05
"""Without landmarks, a centre further than this share of the face's width (the neutral's 5th to 95th
percentile in x) off the midline (the median x) is on one side."""
ONE_SIDED_EYE_DISTANCES = 0.25
"""A two-sided muscle whose centre is further than this off the midline moves mostly one side (a real face's
symmetric expression is rarely exactly so)."""


def motion_centre(element: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The centre (3,) of ``vertices`` (n, 3) weighted by the squared length of ``element`` (n, 3)."""
    weight = np.sum(element ** 2, axis=1)
    return weight @ vertices / max(float(weight.sum()), np.finfo(float).tiny)


def muscle_for(name: str, element: np.ndarray, vertices: np.ndarray, landmarks: dict[str, np.ndarray]) -> Muscle:
    """The Choe-Ko muscle of that name, or a new one placed by where ``element`` (n, 3) moves ``vertices``.

    A new muscle's region is ``upper`` when its motion centre is above the outer eye corners, its side ``L`` /
    ``R`` (+x / -x) when that centre is off the midline by more than :data:`SIDE_EYE_DISTANCES` eye distances.
    """
    if name in CHOE_KO_BY_NAME:
        return CHOE_KO_BY_NAME[name]
    centre = motion_centre(element, vertices)
    eyes = _outer_eye_corners(landmarks)
    region = "upper" if centre[1] > eyes[:, 1].mean() else "lower"
    off = centre[0] - eyes[:, 0].mean()
    side = None if abs(off) <= SIDE_EYE_DISTANCES * _eye_distance(eyes) else ("L" if off > 0 else "R")
    return Muscle(name, region, side, "from a scan")


def misplaced(muscle: Muscle, element: np.ndarray, vertices: np.ndarray, landmarks: dict[str, np.ndarray]
              ) -> str | None:
    """Why ``element`` (n, 3) does not move ``vertices`` (n, 3; the face frame: +x the subject's left, +y up)
    where ``muscle`` is, or None when it does or cannot be told.

    Only clear contradictions count: a one-sided muscle whose motion centre is on the other side or on the
    midline; a two-sided one whose centre is well off it (:data:`ONE_SIDED_EYE_DISTANCES`); an upper-face muscle
    whose centre is below the nose tip, a lower-face one whose centre is above the outer eye corners (a closing
    eye lifts the cheek and a sneer the nose's sides: between the two lines is either face's).
    """
    centre = motion_centre(element, vertices)
    eyes = _outer_eye_corners(landmarks)
    distance = _eye_distance(eyes)
    off = float(centre[0] - eyes[:, 0].mean())
    moved = "left" if off > 0 else "right"
    where = f"its motion's centre is {abs(off):.1f} mm {moved} of the midline"
    if muscle.side is not None:
        sign = 1.0 if muscle.side == "L" else -1.0
        if sign * off < -SIDE_EYE_DISTANCES * distance:
            other = _other_side(muscle.name)
            return (f"it moves the subject's {moved} side ({where}), and the muscle is on the "
                    f"{'left' if sign > 0 else 'right'}" + (f": is its scan {other}'s?" if other else ""))
        if sign * off <= SIDE_EYE_DISTANCES * distance:
            return f"it moves both sides alike ({where}), and the muscle is on one side"
    elif abs(off) > ONE_SIDED_EYE_DISTANCES * distance:
        return f"it moves mostly the subject's {moved} side ({where}), and the muscle moves both sides"
    height, corners = float(centre[1]), float(eyes[:, 1].mean())
    if muscle.region == "upper" and "nose_tip" in landmarks and height < landmarks["nose_tip"][1]:
        return (f"its motion's centre is below the nose tip ({_mm(height)} mm up, the nose tip at "
                f"{_mm(landmarks['nose_tip'][1])}), and the muscle is in the upper face")
    if muscle.region == "lower" and height > corners:
        return (f"its motion's centre is above the outer eye corners ({_mm(height)} mm up, the corners at "
                f"{_mm(corners)}), and the muscle is in the lower face")
    return None


def _mm(value: float) -> str:
    return f"{value:.1f}" if abs(value) >= 0.05 else "0.0"


def side_warnings(muscles, elements: np.ndarray, vertices: np.ndarray) -> list[str]:
    """Warnings for the one-sided muscles whose elements (n_muscles, n, 3) move the other side of ``vertices``
    (n, 3; +x the subject's left), without landmarks: the midline is the median x, the margin
    :data:`SIDE_WIDTHS` of the width. When every one-sided element does (two or more), one warning: the mesh's
    x axis or the shapes' side names are the other way round."""
    x = vertices[:, 0]
    midline, width = float(np.median(x)), float(np.subtract(*np.percentile(x, [95, 5])))
    sided = [(muscle, element) for muscle, element in zip(muscles, elements) if muscle.side is not None]
    swapped = []
    for muscle, element in sided:
        off = float(motion_centre(element, vertices)[0] - midline)
        if (1.0 if muscle.side == "L" else -1.0) * off < -SIDE_WIDTHS * width:
            swapped.append((muscle, off))
    if len(swapped) == len(sided) > 1:
        return [f"every one-sided element ({len(sided)}) moves the other side of the face: livebridge's +x is the "
                "subject's left, and _L the subject's left; mirror the meshes (x -> -x) or give each muscle the "
                "other side's shapes"]
    return [f"{muscle.name}: it moves the subject's {'left' if off > 0 else 'right'} side (its motion's centre is "
            f"{abs(off):.1f} mm from the neutral's midline), and the muscle is on the "
            f"{'left' if muscle.side == 'L' else 'right'}: are its shapes the other side's?" for muscle, off in swapped]


def _outer_eye_corners(landmarks: dict[str, np.ndarray]) -> np.ndarray:
    return np.array([landmarks["eye_outer_L"], landmarks["eye_outer_R"]], dtype=np.float64)


def _eye_distance(eyes: np.ndarray) -> float:
    return float(np.linalg.norm(eyes[0] - eyes[1]))


def _other_side(name: str) -> str | None:
    for this, that in (("_L", "_R"), ("_R", "_L")):
        if name.endswith(this) and name[:-2] + that in CHOE_KO_BY_NAME:
            return name[:-2] + that
    return None
