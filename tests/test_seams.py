"""The lips' seam: sides from the landmarks, warps and smoothing that do not reach across it."""

import numpy as np
import pytest

from livebridge.geometry.transforms import rotation_matrix
from livebridge.retarget.seams import LipSeam
from livebridge.retarget.tps import fit_tps

MOUTH = {"mouth_corner_R": np.array([-25.0, -38.0, -28.0]), "mouth_corner_L": np.array([25.0, -38.0, -28.0]),
         "lip_upper_inner": np.array([0.0, -35.0, -17.0]), "lip_lower_inner": np.array([0.0, -35.6, -17.5])}
"""A mouth whose closed lips meet on a line bowed 2.7 mm up in the middle."""


def _turned(landmarks: dict, degrees: float) -> dict:
    """The landmarks rotated about the z axis (a head tilted in the picture plane)."""
    rotation = rotation_matrix(np.array([0.0, 0.0, np.radians(degrees)]))
    return {name: rotation @ p for name, p in landmarks.items()}


def _on_seam(landmarks: dict, u: np.ndarray, offset: float) -> np.ndarray:
    """Points (n, 2) at fractions ``u`` from the right corner to the left, ``offset`` mm above the parabola
    through the corners and the inner lips' middle (perpendicular to the corner line)."""
    right, left = landmarks["mouth_corner_R"][:2], landmarks["mouth_corner_L"][:2]
    middle = 0.5 * (landmarks["lip_upper_inner"][:2] + landmarks["lip_lower_inner"][:2])
    along = (left - right) / np.linalg.norm(left - right)
    up = np.array([-along[1], along[0]])
    height = (middle - right) @ up
    width = np.linalg.norm(left - right)
    u_mid = (middle - right) @ along / width
    bow = height * u * (1 - u) / (u_mid * (1 - u_mid))
    return right + u[:, None] * width * along + (bow + offset)[:, None] * up


def test_no_seam_without_the_mouth_landmarks():
    assert LipSeam.from_landmarks({k: v for k, v in MOUTH.items() if k != "lip_lower_inner"}) is None


@pytest.mark.parametrize("degrees", [0.0, 25.0, -40.0])
def test_sides_follow_the_bowed_seam_of_a_turned_mouth(degrees):
    landmarks = _turned(MOUTH, degrees)
    seam = LipSeam.from_landmarks(landmarks, taper_mm=6.0)
    u = np.linspace(0.02, 0.98, 30)
    above, strength = seam.sides(_on_seam(landmarks, u, 0.3))
    below, _ = seam.sides(_on_seam(landmarks, u, -0.3))
    assert above.all() and not below.any()
    np.testing.assert_allclose(strength, 1.0)
    # past a corner the sides count less and less: half at 3 mm, nothing from 6 mm on
    _, past = seam.sides(_on_seam(landmarks, np.array([-3.0, -6.0, -20.0]) / 50.0, 5.0))
    np.testing.assert_allclose(past, [0.5, 0.0, 0.0], atol=0.02)


def _lower_lip_drop(points: np.ndarray) -> np.ndarray:
    """A jaw opening's motion (n, 3): the skin below the seam of :data:`MOUTH` 20 mm down, above it still;
    the drop fades to nothing 10 mm past the corners."""
    seam = LipSeam.from_landmarks(MOUTH)
    above, _ = seam.sides(points[:, :2])
    fade = np.clip(1.0 - (np.abs(points[:, 0]) - 25.0) / 10.0, 0.0, 1.0)
    return np.where(above, 0.0, fade)[:, None] * np.array([0.0, -20.0, -8.0])


def _face(xy: np.ndarray) -> np.ndarray:
    """Points (n, 3) on a rounded face-like surface over ``xy`` (n, 2)."""
    return np.column_stack([xy, -xy[:, 0] ** 2 / 100.0 - (xy[:, 1] + 40.0) ** 2 / 200.0])


def test_a_split_warp_keeps_the_lips_apart():
    xx, yy = np.meshgrid(np.arange(-50.0, 51.0, 4.0), np.arange(-80.0, 1.0, 4.0))
    start = _face(np.column_stack([xx.ravel() + 0.5, yy.ravel() + 0.7]))
    end = start + _lower_lip_drop(start)

    def fit(a, b):
        return fit_tps(a, b, "r", 0.1)

    near = _on_seam(MOUTH, np.linspace(0.1, 0.9, 40), 0.0)
    probes = _face(np.concatenate([near + [0.0, dy] for dy in (-1.0, 1.0)]))
    truth = _lower_lip_drop(probes)
    whole = np.linalg.norm(fit(start, end)(probes) - probes - truth, axis=1)
    split = np.linalg.norm(LipSeam.from_landmarks(MOUTH).split_fit(start, end, fit)(probes) - probes - truth, axis=1)
    assert np.median(whole) > 3.0  # one spline over the face drags each lip half way to the other
    assert np.median(split) < 0.2 * np.median(whole)


def test_smoothing_does_not_reach_across_the_seam():
    x = np.arange(-50.0, 50.01, 0.5)
    y = np.arange(-70.0, -5.01, 0.5)
    xx, yy = np.meshgrid(x, y)
    points = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    drop = _lower_lip_drop(points)[:, 1].reshape(xx.shape)
    weight = np.ones_like(drop)
    weight[:, :10] = 0.0  # no skin at the image's left edge
    seam = LipSeam.from_landmarks(MOUTH)
    (smoothed,), cover = seam.smoother(x, y)([drop], weight, 6.0)
    above, strength = seam.sides(points[:, :2])
    between = (strength == 1.0).reshape(xx.shape) & (np.abs(xx) < 12)
    np.testing.assert_allclose(smoothed[between], drop[between], atol=0.05)
    np.testing.assert_allclose(cover[between], 1.0, atol=1e-3)  # its own side's skin is all there
    # far past the corners it is the plain weighted blur; at the skin's edge the cover falls
    import cv2
    plain = cv2.GaussianBlur((drop * weight).astype(np.float32), (0, 0), 6.0) / cv2.GaussianBlur(
        weight.astype(np.float32), (0, 0), 6.0)
    far = (np.abs(xx) > 40) & (xx > -44)
    np.testing.assert_allclose(smoothed[far], plain[far], atol=1e-3)
    assert cover[:, 10].max() < 0.6


@pytest.mark.parametrize("degrees", [0.0, 20.0])
def test_the_seam_moves_onto_the_groove_between_the_lips(degrees):
    """Landmarks 1 mm off the lips' line: the seam follows the deepest crease of the surface instead (sides
    right at 0.3 mm from it), and the middle of the gap where the lips are apart."""
    from livebridge.retarget.grid import FaceGrid

    landmarks = _turned(MOUTH, degrees)
    true_line = LipSeam.from_landmarks(landmarks)
    x = np.arange(-60.0, 60.01, 0.5)
    y = np.arange(-80.0, 0.01, 0.5)
    xx, yy = np.meshgrid(x, y)
    xy = np.column_stack([xx.ravel(), yy.ravel()])
    width, along, up = true_line._frame()
    u = np.clip((xy - true_line.right) @ along / width, 0.0, 1.0)
    across = (xy - true_line.right) @ up - true_line._seam_v(u)  # mm above the true line
    heights = (-np.abs(xy[:, 0]) / 10.0 - 3.0 * np.exp(-across ** 2 / (2 * 0.8 ** 2))).reshape(xx.shape)
    lifted = {name: p + np.r_[1.0 * up, 0.0] for name, p in landmarks.items()}  # the landmarks 1 mm too high
    seam = LipSeam.from_landmarks(lifted)
    for apart in (False, True):
        grid = FaceGrid(x, y, np.where((np.abs(across) < 1.0).reshape(xx.shape), np.nan, heights) if apart
                        else heights)
        refined = seam.along_groove(grid)
        probe_u = np.linspace(0.15, 0.85, 25)
        for offset, expected in ((0.3, True), (-0.3, False)):
            points = _on_seam(landmarks, probe_u, offset)
            assert (refined.sides(points)[0] == expected).all(), (apart, offset)
        assert not seam.sides(_on_seam(landmarks, probe_u, 0.3))[0].any()  # the landmarks alone: 1 mm off


@pytest.mark.parametrize("upper_steeper", [True, False])
def test_the_grooves_bottom_is_on_the_lip_of_the_gentler_flank(upper_steeper):
    """Closed lips meeting on a straight line at a row of the skin image, one lip overhanging the other (its
    flank rising 4 mm per mm, the other's 1.5): the points at the groove's bottom go with the lip whose flank
    the frontal scanner sees face-on, the points a pixel off it with their own lip."""
    from livebridge.retarget.grid import FaceGrid

    straight = {"mouth_corner_R": np.array([-25.0, -38.0, -28.0]), "mouth_corner_L": np.array([25.0, -38.0, -28.0]),
                "lip_upper_inner": np.array([0.0, -38.0, -17.0]), "lip_lower_inner": np.array([0.0, -38.0, -17.0])}
    x = np.arange(-60.0, 60.01, 0.5)
    y = np.arange(-80.0, 0.01, 0.5)
    xx, yy = np.meshgrid(x, y)
    above = yy + 38.0
    steep, gentle = (4.0, 1.5) if upper_steeper else (1.5, 4.0)
    heights = -np.abs(xx) / 10.0 - 3.0 + np.minimum(np.where(above > 0, steep * above, -gentle * above), 3.0)
    seam = LipSeam.from_landmarks(straight).along_groove(FaceGrid(x, y, heights))
    u = np.linspace(-15.0, 15.0, 31)
    for dy, expected in ((0.0, not upper_steeper), (0.5, True), (-0.5, False)):
        upper, _ = seam.sides(np.column_stack([u, np.full_like(u, -38.0 + dy)]))
        assert (upper == expected).all(), dy
