"""A chart of the face for its skin images: coordinates in which the face's sides are not compressed.

A face scan resampled on x-y grid lines (the face looking along +z) is an x-y projection of the skin: where
the skin turns away from the scanner (the cheeks' and jaw's sides, |normal z| 0.2-0.45 within 6 mm of the
face grid's outline) its pattern is compressed by |normal z| (3-5x) and an error of the x-y flow there
becomes ``1 / |normal z|`` times larger along the slope. A chart that follows the face's roundness keeps the
pattern near its true size: the skin images (:mod:`~livebridge.retarget.scans`) are built on regular
``(u, v)`` grid lines with the chart's height ``h`` as their heights, the skin tracked there
(:mod:`~livebridge.retarget.skin_flow`), and each output vertex's motion read back at its own ``(u, v)``
and mapped back to the face frame.

:func:`face_chart` fits the chart to the neutral's own grid (least squares): a cylinder about a vertical
axis (``u`` the angle about the axis times the face's median distance from it, ``v = y``, ``h`` the distance
from the axis less that median) or a sphere (azimuthal equidistant about the forward axis). On the bench's
face (ICT, 150 x 150 grid) the cylinder fits better (RMS distance from it 6.8 mm, the sphere 12.4 mm: a face
is rounder across than up and down) and tracks better: `livebridge bench scans` (seed 7, 60k / 150k points a
scan) 10 / 13 of 16 elements within 0.10 relative RMS with the cylinder against 10 / 11 in x-y, mean 0.116 /
0.085 against 0.116 / 0.094; depressor_anguli_oris 0.123 / 0.081 (x-y 0.144 / 0.103), lips_pressor 0.123 /
0.085 (0.138 / 0.110), frontalis 0.078-0.082 / 0.056 (0.088 / 0.071-0.083), risorius 0.093-0.096 / 0.063-0.070
(0.100-0.107 / 0.080-0.087); worse: zygomatic_major_R at 60k 0.092 (0.059: a bad first guess at the crop's
corner the flow no longer recovers from), the eyelids at 60k 0.30 / 0.29 (0.29 / 0.24). With single elements
(no template, 60k; centres as fitted) the sphere measured jaw 0.225, lips_pressor 0.148, depressor 0.147
against the cylinder's 0.181, 0.143, 0.135 and x-y's 0.136, 0.153, 0.154. The planar chart (``u, v, h = x, y,
z``) is the x-y projection itself (its bench figures within 0.002 of the former x-y code for 13 of 16
elements; jaw 0.122 against 0.114 at 60k, the eyelids within 0.015).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_DISTANCE_FRACTION = 0.6
"""No point of the face may be nearer the chart's centre (axis) than this times the face's median distance
from it: the fitted centre is moved back along the view until none is. Near the centre the chart stretches
without bound (a small angle is many mm of u): the skin under the bench face's chin lies 15-30 mm from the
fitted axis, where the flow took 2-4 mm errors. `livebridge bench scans` (60k / 150k points) with the fitted
axis: zygomatic_major_R 0.116 / 0.091, mean of the 16 elements 0.120 / 0.088; moved back (80 -> 120 mm
behind the nose tip): 0.092 / 0.041, 0.116 / 0.082-0.085."""
MAX_RADIUS_FACTOR = 20.0
"""A fitted sphere this many times larger than the face's extent is taken as a flat face: the planar chart."""


@dataclass(frozen=True, eq=False)
class SkinChart:
    """Coordinates ``(u, v, h)`` of the face frame's points (x right, y up, the face looking along +z).

    Attributes
    ----------
    kind : str
        ``"planar"`` (``u, v, h = x, y, z``), ``"sphere"`` or ``"cylinder"`` (about a vertical axis).
    centre : ndarray, shape (3,)
        The sphere's centre or a point on the cylinder's axis (behind the face), mm.
    radius : float
        The face's median distance from the centre (axis), mm: ``u, v`` are angles times it (mm of skin at
        that distance; ``v = y`` on the cylinder), ``h`` a point's distance from the centre (axis) less it.
    """

    kind: str = "planar"
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.0

    @property
    def planar(self) -> bool:
        return self.kind == "planar"

    def to_chart(self, points: np.ndarray) -> np.ndarray:
        """Points (n, 3) in the face frame as ``(u, v, h)`` (n, 3)."""
        points = np.asarray(points, dtype=np.float64)
        if self.planar:
            return points.copy()
        d = points - self.centre
        if self.kind == "cylinder":
            distance = np.hypot(d[:, 0], d[:, 2])
            return np.column_stack([self.radius * np.arctan2(d[:, 0], d[:, 2]), points[:, 1], distance - self.radius])
        distance = np.linalg.norm(d, axis=1)
        sideways = np.hypot(d[:, 0], d[:, 1])
        angle = np.arctan2(sideways, d[:, 2])  # from the forward (+z) axis
        # angle / sideways, -> 1 / distance on the axis (no direction there)
        scale = self.radius * np.where(sideways > 1e-12 * distance, angle / np.maximum(sideways, 1e-300),
                                       1.0 / np.maximum(distance, 1e-300))
        return np.column_stack([scale * d[:, 0], scale * d[:, 1], distance - self.radius])

    def from_chart(self, chart: np.ndarray) -> np.ndarray:
        """``(u, v, h)`` (n, 3) back to points (n, 3) in the face frame."""
        chart = np.asarray(chart, dtype=np.float64)
        if self.planar:
            return chart.copy()
        distance = chart[:, 2] + self.radius
        if self.kind == "cylinder":
            angle = chart[:, 0] / self.radius
            return np.column_stack([self.centre[0] + distance * np.sin(angle), chart[:, 1],
                                    self.centre[2] + distance * np.cos(angle)])
        angle = np.hypot(chart[:, 0], chart[:, 1]) / self.radius
        scale = np.sinc(angle / np.pi) * distance / self.radius  # sin(angle) / angle, stable at 0
        return self.centre + np.column_stack([scale * chart[:, 0], scale * chart[:, 1], distance * np.cos(angle)])

    def motion_to_chart(self, points: np.ndarray, motion: np.ndarray) -> np.ndarray:
        """Motions (n, 3) of ``points`` (n, 3) as motions in the chart (n, 3)."""
        return self.to_chart(np.asarray(points) + motion) - self.to_chart(points)

    def motion_from_chart(self, points: np.ndarray, chart_motion: np.ndarray) -> np.ndarray:
        """Motions in the chart (n, 3) of ``points`` (n, 3, face frame) as motions in the face frame (n, 3)."""
        return self.from_chart(self.to_chart(points) + chart_motion) - np.asarray(points, dtype=np.float64)

    def view_directions(self, points: np.ndarray) -> np.ndarray:
        """Unit vectors (n, 3) along which the chart's height ``h`` grows at ``points`` (n, 3; face frame): the
        direction a skin image made in this chart looks at the skin from (``+z`` for the planar chart, away
        from the axis, level, for the cylinder, away from the centre for the sphere). Skin turned away from
        it is compressed in the skin image (see
        :func:`~livebridge.retarget.skin_smoothing.shrink_noise`)."""
        points = np.asarray(points, dtype=np.float64)
        if self.planar:
            return np.tile([0.0, 0.0, 1.0], (len(points), 1))
        d = points - self.centre
        if self.kind == "cylinder":
            d[:, 1] = 0.0
        size = np.linalg.norm(d, axis=1, keepdims=True)
        # the centre (axis) itself: looking along +z, as the planar chart (no face point is that near it)
        return np.where(size > 1e-12, d / np.maximum(size, 1e-300), [0.0, 0.0, 1.0])

    def landmarks(self, landmarks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Landmarks (name to (3,)) in the chart."""
        if not landmarks:
            return {}
        names = list(landmarks)
        chart = self.to_chart(np.array([landmarks[n] for n in names], dtype=np.float64))
        return dict(zip(names, chart))


PLANAR = SkinChart()
"""The x-y projection (``u, v, h = x, y, z``)."""


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The least-squares sphere (circle, for points (n, 2)) through points (n, 3): (centre, radius), the
    algebraic fit (``|p|^2 = 2 c . p + k`` solved linearly, ``radius^2 = k + |c|^2``)."""
    points = np.asarray(points, dtype=np.float64)
    mean = points.mean(axis=0)
    p = points - mean
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    solution, *_ = np.linalg.lstsq(a, (p ** 2).sum(axis=1), rcond=None)
    centre = solution[:-1]
    return centre + mean, float(np.sqrt(max(solution[-1] + centre @ centre, 0.0)))


def face_chart(points: np.ndarray, kind: str = "cylinder") -> SkinChart:
    """The ``kind`` chart of a face's points (n, 3; face frame, looking along +z), fitted to them; the
    planar chart when the face is (nearly) flat or the fitted centre is not behind most of it."""
    points = np.asarray(points, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if kind == "planar" or len(points) < 10:
        return PLANAR
    extent = float(np.ptp(points[:, :2], axis=0).max())
    if kind == "cylinder":
        (cx, cz), radius = fit_sphere(points[:, [0, 2]])
        centre = np.array([cx, 0.0, cz])
    else:
        centre, radius = fit_sphere(points)
    if not (np.isfinite(radius) and radius < MAX_RADIUS_FACTOR * extent) or centre[2] >= np.median(points[:, 2]):
        return PLANAR
    distance = _distances(points, centre, kind)
    step = 0.02 * float(np.median(distance))
    for _ in range(200):  # back along the view until no skin is near the centre (axis): there the chart tears
        if distance.min() >= MIN_DISTANCE_FRACTION * np.median(distance):
            break
        centre = centre - [0.0, 0.0, step]
        distance = _distances(points, centre, kind)
    radius = float(np.median(distance))  # the chart's u, v: mm of skin at the face's typical distance
    return SkinChart(kind, centre, radius)


def _distances(points: np.ndarray, centre: np.ndarray, kind: str) -> np.ndarray:
    """Distances (n,) of points (n, 3) from a sphere's centre or a vertical cylinder's axis through it."""
    d = points - centre
    return np.hypot(d[:, 0], d[:, 2]) if kind == "cylinder" else np.linalg.norm(d, axis=1)
