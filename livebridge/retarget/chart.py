"""A chart of the face for its skin images: coordinates in which the face's sides are not compressed.

A face scan resampled on x-y grid lines (the face looking along +z) is an x-y projection of the skin: where
the skin turns away from the scanner (the cheeks' and jaw's sides, the chin's underside, |normal z| 0.2-0.45
within 6 mm of a face grid's outline) its pattern is compressed by |normal z| (3-5x), fine detail is lost to
the resampling, and an error of the x-y flow there becomes ``1 / |normal z|`` times larger along the slope.
A chart that follows the face's roundness keeps the pattern near its true size all over: here the azimuthal
equidistant projection about a sphere fitted to the face (its centre behind it): a point's ``u, v`` are its
angle from the sphere's forward axis times the sphere's radius, in the direction of the point about that
axis (so near the front they are mm of skin and match x, y), and its height ``h`` is its distance from the
centre less the radius (the face's sphere at 0; the skin's "height" in the chart, growing towards the
scanner like z). Skin images built on regular ``u, v`` grid lines (:mod:`~livebridge.retarget.scans`) then
see the sides at their true scale. The planar chart (``u, v, h = x, y, z``) is the x-y projection itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_DISTANCE_FRACTION = 0.6
"""No point of the face may be nearer the chart's centre (axis) than this times the face's median distance
from it: the fitted centre is moved back along the view until none is. Near the centre the chart stretches
without bound (a small angle is many mm of u): the skin under the chin, 15-30 mm from the fitted axis of the
bench's face, took 2-4 mm errors (zygomatic_major_R 0.110 instead of 0.064 relative RMS, 60k points)."""
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
