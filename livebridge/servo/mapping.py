"""From muscle contractions to raw servo targets: mixing, curves, raw ranges.

Per servo ``s``: ``u_s = sum_i W[s, i] x_i`` (weights may be negative, a servo
may mix several muscles), then a curve ``y = f(u)`` and finally the raw range::

    raw = neutral + y * (max - neutral)     for y >= 0
    raw = neutral + (-y) * (min - neutral)  for y <  0

with ``y`` clipped to [-1, 1], so contraction 1 reaches ``max`` and -1 reaches
``min``; an inverted servo simply has ``max < min``. Curves:

- ``linear``: ``y = u``;
- ``gamma``: ``y = sign(u) |u|^gamma``;
- ``piecewise``: linear interpolation through ``points`` ``[(u, y), ...]``
  (sorted by ``u``; held constant beyond the ends).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

_CURVE_KINDS = ("linear", "gamma", "piecewise")


@dataclass(frozen=True)
class Curve:
    """A mapping curve: ``kind`` in {'linear', 'gamma', 'piecewise'}."""

    kind: str = "linear"
    gamma: float = 1.0
    points: tuple[tuple[float, float], ...] = ()

    def __post_init__(self):
        if self.kind not in _CURVE_KINDS:
            raise ValueError(f"unknown curve {self.kind!r} (linear, gamma, piecewise)")
        if self.kind == "gamma" and not (np.isfinite(self.gamma) and self.gamma > 0):
            raise ValueError(f"gamma must be a positive number, got {self.gamma}")
        if self.kind == "piecewise":
            pts = np.asarray(self.points, dtype=float)
            if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2 or not np.all(np.isfinite(pts)):
                raise ValueError("piecewise points must be at least two finite [u, y] pairs")
            if np.any(np.diff(pts[:, 0]) <= 0):
                raise ValueError("piecewise points must have strictly increasing u")

    def __call__(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        if self.kind == "linear":
            return u
        if self.kind == "gamma":
            return np.sign(u) * np.abs(u) ** self.gamma
        pts = np.asarray(self.points, dtype=float)
        return np.interp(u, pts[:, 0], pts[:, 1])


@dataclass(frozen=True, eq=False)
class Mapping:
    """Contractions -> raw targets for a set of servos.

    Attributes
    ----------
    weights : ndarray, shape (n_servos, n_muscles)
    curves : tuple of Curve, length n_servos
    neutral, minimum, maximum : ndarray, shape (n_servos,)
        Raw units; ``maximum`` is reached at y = 1 and may be below ``minimum``.
    """

    weights: np.ndarray
    curves: tuple[Curve, ...]
    neutral: np.ndarray
    minimum: np.ndarray
    maximum: np.ndarray

    @property
    def low(self) -> np.ndarray:
        """Lower raw limit per servo, shape (n_servos,)."""
        return np.minimum(self.minimum, self.maximum)

    @property
    def high(self) -> np.ndarray:
        """Upper raw limit per servo, shape (n_servos,)."""
        return np.maximum(self.minimum, self.maximum)

    @cached_property
    def compiled(self) -> tuple:
        """The mapping as arrays for :func:`raw_kernel` (weights, curve kinds, gammas, piecewise points
        padded to the longest curve with their counts, neutral, minimum, maximum)."""
        n_points = np.array([len(c.points) for c in self.curves], dtype=np.int64)
        curve_u = np.zeros((len(self.curves), max(int(n_points.max(initial=0)), 1)))
        curve_y = np.zeros_like(curve_u)
        for s, curve in enumerate(self.curves):
            if curve.points:
                curve_u[s, :n_points[s]], curve_y[s, :n_points[s]] = np.asarray(curve.points, dtype=float).T
        return (np.array(self.weights, dtype=np.float64),
                np.array([_CURVE_KINDS.index(c.kind) for c in self.curves], dtype=np.int64),
                np.array([c.gamma for c in self.curves], dtype=np.float64), curve_u, curve_y, n_points,
                *(np.array(a, dtype=np.float64) for a in (self.neutral, self.minimum, self.maximum)))

    def drive(self, contractions: np.ndarray) -> np.ndarray:
        """Mixed and curved drive ``y`` in [-1, 1], shape (n_servos,), from contractions (n_muscles,).

        Non-finite contractions give NaN for exactly the servos that use them.
        """
        weights, kinds, gammas, curve_u, curve_y, n_points = self.compiled[:6]
        return drive_kernel(np.array(contractions, dtype=np.float64), weights, kinds, gammas, curve_u, curve_y,
                            n_points)

    def raw(self, contractions: np.ndarray) -> np.ndarray:
        """Raw targets, shape (n_servos,), inside [low, high]; NaN where an input was non-finite."""
        return raw_kernel(np.array(contractions, dtype=np.float64), *self.compiled)


@njit(cache=True, nogil=True, error_model="numpy")
def drive_kernel(x, weights, kinds, gammas, curve_u, curve_y, n_points):
    """Compiled :meth:`Mapping.drive`: ``x`` (n_muscles,) -> ``y`` (n_servos,), NaN where a used input is not
    finite. ``kinds``: index into ``linear, gamma, piecewise``."""
    n_servos, n_muscles = weights.shape
    y = np.empty(n_servos)
    for s in range(n_servos):
        u, bad = 0.0, False
        for i in range(n_muscles):
            w = weights[s, i]
            if w != 0.0:
                if np.isfinite(x[i]):
                    u += w * x[i]
                else:
                    bad = True
        if bad or not np.isfinite(u):
            y[s] = np.nan
            continue
        if kinds[s] == 1:
            value = np.sign(u) * np.abs(u) ** gammas[s]
        elif kinds[s] == 2:
            n = n_points[s]
            value = np.interp(u, curve_u[s, :n], curve_y[s, :n])
        else:
            value = u
        y[s] = min(1.0, max(-1.0, value))
    return y


@njit(cache=True, nogil=True, error_model="numpy")
def raw_kernel(x, weights, kinds, gammas, curve_u, curve_y, n_points, neutral, minimum, maximum):
    """Compiled :meth:`Mapping.raw`: ``x`` (n_muscles,) -> raw targets (n_servos,), NaN where not finite."""
    y = drive_kernel(x, weights, kinds, gammas, curve_u, curve_y, n_points)
    raw = np.empty_like(y)
    for s in range(len(y)):
        if y[s] >= 0:
            raw[s] = neutral[s] + y[s] * (maximum[s] - neutral[s])
        else:  # a NaN drive lands here and stays NaN
            raw[s] = neutral[s] + (-y[s]) * (minimum[s] - neutral[s])
    return raw
