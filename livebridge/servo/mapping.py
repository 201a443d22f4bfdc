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

import numpy as np


@dataclass(frozen=True)
class Curve:
    """A mapping curve: ``kind`` in {'linear', 'gamma', 'piecewise'}."""

    kind: str = "linear"
    gamma: float = 1.0
    points: tuple[tuple[float, float], ...] = ()

    def __post_init__(self):
        if self.kind not in ("linear", "gamma", "piecewise"):
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

    def drive(self, contractions: np.ndarray) -> np.ndarray:
        """Mixed and curved drive ``y`` in [-1, 1], shape (n_servos,), from contractions (n_muscles,).

        Non-finite contractions give NaN for exactly the servos that use them.
        """
        x = np.asarray(contractions, dtype=float)
        used = self.weights != 0
        bad = used & ~np.isfinite(x)[None, :]
        u = np.where(used, self.weights * np.where(np.isfinite(x), x, 0.0)[None, :], 0.0).sum(axis=1)
        y = np.array([curve(value) for curve, value in zip(self.curves, u)], dtype=float)
        y = np.clip(y, -1.0, 1.0)
        y[bad.any(axis=1) | ~np.isfinite(u)] = np.nan
        return y

    def raw(self, contractions: np.ndarray) -> np.ndarray:
        """Raw targets, shape (n_servos,), inside [low, high]; NaN where an input was non-finite."""
        y = self.drive(contractions)
        up = self.neutral + y * (self.maximum - self.neutral)
        down = self.neutral + (-y) * (self.minimum - self.neutral)
        return np.where(y >= 0, up, down)  # NaN y makes both branches NaN
