"""A node's clock against the host's: NTP-style offset and round-trip estimation, robust to outliers.

Each exchange gives four times: the host sends at ``t1`` (host clock), the node receives at ``t2`` and
replies at ``t3`` (node clock), the host receives at ``t4``. The round trip is ``(t4 - t1) - (t3 - t2)``
and the offset (node minus host) ``((t2 - t1) + (t3 - t4)) / 2``, off by at most half the round trip
(when all of the delay is on one side). A busy host or network delays some exchanges by far more than
others, so only the exchanges with the shortest round trips of a sliding window are used (their error
bound is smallest), and the offset over host time is fitted with a line through them (a drifting crystal
moves tens of microseconds a second), dropping points far off the line before the final fit.

A node whose clock is hardware-synchronised or PTP-disciplined to the host's says so
(``time_source``); its times are trusted as they come (offset 0), and the exchange only measures the
round trip.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClockSample:
    """One exchange: host time of its middle, offset (node minus host) and round trip, seconds."""

    t_host: float
    offset: float
    rtt: float


def exchange(t1: float, t2: float, t3: float, t4: float) -> ClockSample:
    """The :class:`ClockSample` of one ping/pong: ``t1``, ``t4`` host clock, ``t2``, ``t3`` node clock."""
    return ClockSample((t1 + t4) / 2, ((t2 - t1) + (t3 - t4)) / 2, (t4 - t1) - (t3 - t2))


@dataclass(frozen=True)
class ClockEstimate:
    """The node clock relative to the host's.

    Attributes
    ----------
    offset : float
        Node minus host seconds at ``t_ref`` (host clock).
    drift : float
        Change of the offset per host second (50 ppm: 5e-5).
    t_ref : float
    rtt : float
        Shortest recent round trip, seconds.
    jitter : float
        Spread (robust standard deviation) of the used exchanges around the fit, seconds.
    samples : int
        Exchanges used.
    trusted : bool
        The node's time is taken as it comes (PTP or hardware time); ``offset`` and ``drift`` are 0.
    """

    offset: float = math.nan
    drift: float = 0.0
    t_ref: float = 0.0
    rtt: float = math.nan
    jitter: float = math.nan
    samples: int = 0
    trusted: bool = False

    def offset_at(self, t_host: float) -> float:
        """Node minus host seconds at host time ``t_host`` (NaN before the first exchange)."""
        return self.offset + self.drift * (t_host - self.t_ref)

    def to_host(self, t_node: float) -> float:
        """Host time of node time ``t_node``."""
        if self.trusted:
            return t_node
        # offset_at is evaluated at the (nearly equal) node time: the drift makes the difference negligible
        return t_node - self.offset_at(t_node - self.offset)


class ClockEstimator:
    """Keeps a window of exchanges and the current :class:`ClockEstimate`.

    Parameters
    ----------
    window : int
        Exchanges kept (the newest).
    keep_fraction : float
        Share of the window with the shortest round trips that is used.
    min_drift_span_s : float
        Host seconds the used exchanges must span before a drift is fitted (before: offset only).
    """

    def __init__(self, window: int = 128, keep_fraction: float = 0.5, min_drift_span_s: float = 1.0):
        self._samples: deque[ClockSample] = deque(maxlen=window)
        self.keep_fraction = keep_fraction
        self.min_drift_span_s = min_drift_span_s
        self.estimate = ClockEstimate()
        self.trusted = False

    def add(self, t1: float, t2: float, t3: float, t4: float) -> ClockEstimate:
        """Add one exchange (see :func:`exchange`); exchanges with a negative or non-finite round trip (a
        clock that jumped) are left out. Returns the new estimate."""
        sample = exchange(t1, t2, t3, t4)
        if math.isfinite(sample.offset) and math.isfinite(sample.rtt) and sample.rtt >= 0:
            self._samples.append(sample)
            self.estimate = self._fit()
        return self.estimate

    def reset(self) -> None:
        """Forget every exchange (the node restarted: its clock may have changed)."""
        self._samples.clear()
        self.estimate = ClockEstimate()

    def _fit(self) -> ClockEstimate:
        samples = list(self._samples)
        rtt = np.array([s.rtt for s in samples])
        keep = max(3, int(math.ceil(self.keep_fraction * len(samples))))
        used = [samples[i] for i in np.argsort(rtt, kind="stable")[:keep]]
        t = np.array([s.t_host for s in used])
        offset = np.array([s.offset for s in used])
        t_ref = float(t.mean())
        if self.trusted:
            return ClockEstimate(0.0, 0.0, t_ref, float(rtt.min()), float(_spread(offset - np.median(offset))),
                                 len(used), True)
        fit_drift = len(used) >= 4 and np.ptp(t) >= self.min_drift_span_s
        line = _line(t - t_ref, offset, fit_drift)
        residual = offset - np.polyval(line, t - t_ref)
        spread = _spread(residual)
        inliers = np.abs(residual) <= max(3 * spread, 1e-6)
        if inliers.sum() >= 2 and not inliers.all():
            line = _line(t[inliers] - t_ref, offset[inliers], fit_drift and inliers.sum() >= 4)
            residual = offset[inliers] - np.polyval(line, t[inliers] - t_ref)
            spread = _spread(residual)
        return ClockEstimate(float(line[1]), float(line[0]), t_ref, float(rtt.min()), float(spread),
                             int(inliers.sum()), False)


def _line(t: np.ndarray, offset: np.ndarray, fit_drift: bool) -> np.ndarray:
    """``[slope, intercept]`` of ``offset`` over ``t``; slope 0 (the median) when not ``fit_drift``."""
    if fit_drift:
        return np.polyfit(t, offset, 1)
    return np.array([0.0, float(np.median(offset))])


def _spread(residual: np.ndarray) -> float:
    """Robust standard deviation (1.4826 x median absolute deviation)."""
    if residual.size == 0:
        return math.nan
    return float(1.4826 * np.median(np.abs(residual - np.median(residual))))
