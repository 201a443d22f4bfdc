"""Safety between contractions and servos: a state/step mapper.

``step(state, contractions, t) -> (state, targets)`` turns one frame of
contractions into raw targets for every servo, and guarantees, for any input
whatsoever (NaN, inf, huge values, time going backwards):

- every target lies inside the servo's [low, high] limits;
- no target moves more than ``slew * dt`` from the previous one (``dt`` the
  time since the previous step; a step at the same or an earlier time moves
  nothing);
- a non-finite contraction holds the last safe target of exactly the servos
  that use that muscle;
- **smoothing** per servo: ``none``, ``exponential`` (first-order low-pass,
  time constant ``tau``: delay ``tau`` seconds) or ``one_euro`` (Casiez et
  al. 2012; delay ``1 / (2 pi min_cutoff)`` at rest, less when moving fast),
  applied in normalised units (0..1 over the servo's range) so ``beta`` does
  not depend on raw units; :attr:`Filter.delay_s` states the delay;
- **soft start**: from :meth:`SafetyMapper.start` (the present positions when
  torque comes on) the allowed speed ramps from 0 to ``slew`` over
  ``soft_start_s``;
- **watchdog**: when no valid contractions arrived for ``watchdog_s``, the
  targets ease to neutral at ``range / ease_s`` per second (never faster than
  the slew limit) until input returns;
- **E-stop**: :meth:`SafetyMapper.estop` latches; targets are held and the
  output sends nothing until :meth:`SafetyMapper.start` is called again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from livebridge.servo.mapping import Mapping, raw_kernel

_KINDS = ("none", "exponential", "one_euro")


@dataclass(frozen=True)
class Filter:
    """A smoothing filter: ``kind`` in {'none', 'exponential', 'one_euro'}."""

    kind: str = "none"
    tau: float = 0.0  # exponential: time constant, seconds
    min_cutoff: float = 1.0  # one_euro: Hz
    beta: float = 0.0  # one_euro: speed coefficient (normalised units)
    d_cutoff: float = 1.0  # one_euro: Hz, for the speed estimate

    def __post_init__(self):
        if self.kind not in _KINDS:
            raise ValueError(f"unknown filter {self.kind!r} ({', '.join(_KINDS)})")
        for name in ("tau", "min_cutoff", "beta", "d_cutoff"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"filter {name} must be a finite number >= 0, got {value}")
        if self.kind == "one_euro" and (self.min_cutoff <= 0 or self.d_cutoff <= 0):
            raise ValueError("one_euro cutoffs must be > 0 Hz")

    @property
    def delay_s(self) -> float:
        """Delay of the filter on slow motion, seconds (the one-euro filter lags less when moving fast)."""
        if self.kind == "exponential":
            return self.tau
        if self.kind == "one_euro":
            return 1.0 / (2 * math.pi * self.min_cutoff)
        return 0.0


@dataclass(frozen=True, eq=False)
class SafetyState:
    """Between-frame state of :class:`SafetyMapper` (all arrays shape (n_servos,), raw units)."""

    target: np.ndarray  # last target sent, always inside [low, high]
    desired: np.ndarray  # last safe desired target (held through non-finite input)
    filtered: np.ndarray  # smoothing filter output, normalised 0..1
    speed: np.ndarray  # one-euro speed estimate, normalised units / s
    t: float  # time of the last step
    t_input: float  # time valid contractions last arrived
    t_start: float  # when torque came on (soft start origin)
    estopped: bool = False
    watchdog: bool = False  # True while easing to neutral for lack of input


class SafetyMapper:
    """Contractions -> safe raw targets (see the module docstring).

    Parameters
    ----------
    mapping : Mapping
        Mixing, curves and raw ranges of the servos.
    slew : array_like, shape (n_servos,)
        Maximum target speed, raw units per second (> 0).
    filters : sequence of Filter, length n_servos
    watchdog_s : float
        Input silence after which the targets ease to neutral.
    soft_start_s : float
        Time for the allowed speed to ramp from 0 to ``slew`` after ``start``.
    ease_s : float
        Time a full-range move to neutral takes under the watchdog.
    """

    def __init__(self, mapping: Mapping, slew, filters, watchdog_s: float = 0.5, soft_start_s: float = 1.0,
                 ease_s: float = 2.0):
        self.mapping = mapping
        self.low = np.asarray(mapping.low, dtype=float)
        self.high = np.asarray(mapping.high, dtype=float)
        self.neutral = np.clip(np.asarray(mapping.neutral, dtype=float), self.low, self.high)
        self.slew = np.broadcast_to(np.asarray(slew, dtype=float), self.low.shape).copy()
        if not np.all(np.isfinite(self.slew) & (self.slew > 0)):
            raise ValueError("slew limits must be finite and > 0")
        self.filters = tuple(filters)
        if len(self.filters) != len(self.low):
            raise ValueError(f"{len(self.filters)} filters for {len(self.low)} servos")
        self.watchdog_s = float(watchdog_s)
        self.soft_start_s = float(soft_start_s)
        self.span = np.maximum(self.high - self.low, 1e-9)
        self.ease_rate = np.minimum(self.slew, self.span / max(float(ease_s), 1e-9))
        kinds = np.array([_KINDS.index(f.kind) for f in self.filters])
        self._exp = kinds == 1
        self._euro = kinds == 2
        self._tau = np.array([f.tau for f in self.filters], dtype=float)
        self._min_cutoff = np.array([f.min_cutoff for f in self.filters], dtype=float)
        self._beta = np.array([f.beta for f in self.filters], dtype=float)
        self._d_cutoff = np.array([f.d_cutoff for f in self.filters], dtype=float)
        self._limits = (self.low, self.high, self.span, self.neutral, self.slew, self.ease_rate, self._exp,
                        self._euro, self._tau, self._min_cutoff, self._beta, self._d_cutoff, self.watchdog_s)

    @property
    def n_servos(self) -> int:
        return len(self.low)

    def _norm(self, raw: np.ndarray) -> np.ndarray:
        return (raw - self.low) / self.span

    def start(self, present, t: float) -> SafetyState:
        """State when torque comes on at ``t``; ``present`` (n_servos,) raw positions (NaN: unknown -> neutral)."""
        present = np.asarray(present, dtype=float)
        target = np.clip(np.where(np.isfinite(present), present, self.neutral), self.low, self.high)
        t = float(t) if math.isfinite(t) else 0.0
        return SafetyState(target=target, desired=target.copy(), filtered=self._norm(target),
                           speed=np.zeros_like(target), t=t, t_input=t, t_start=t)

    def estop(self, state: SafetyState) -> SafetyState:
        """Latch the E-stop: targets freeze, the output must stop the servos."""
        return replace(state, estopped=True)

    def step(self, state: SafetyState, contractions, t: float) -> tuple[SafetyState, np.ndarray]:
        """One frame.

        Parameters
        ----------
        state : SafetyState
        contractions : array_like, shape (n_muscles,), or None
            ``None`` when no frame arrived (the watchdog keeps counting).
        t : float
            Seconds on the monotonic clock.

        Returns
        -------
        state : SafetyState
        targets : ndarray, shape (n_servos,)
            Raw targets inside [low, high].
        """
        if state.estopped:
            return state, state.target.copy()
        t = float(t) if t is not None and math.isfinite(float(t)) else state.t
        dt = t - state.t
        if not (math.isfinite(dt) and dt > 0):
            dt, t = 0.0, state.t
        x = _NO_INPUT
        if contractions is not None:
            x = np.array(contractions, dtype=np.float64).reshape(-1)
            if x.shape[0] != self.mapping.weights.shape[1]:
                x = _NO_INPUT
        ramp = 1.0 if self.soft_start_s <= 0 else min(1.0, max(0.0, (t - state.t_start) / self.soft_start_s))
        target, desired, filtered, speed, t_input, tripped = _step_kernel(
            x, len(x) > 0, self.mapping.compiled, state.target, state.desired, state.filtered, state.speed, t, dt,
            state.t_input, ramp, self._limits)
        state = SafetyState(target=target, desired=desired, filtered=filtered, speed=speed, t=t, t_input=t_input,
                            t_start=state.t_start, watchdog=bool(tripped))
        return state, target.copy()


_NO_INPUT = np.zeros(0)


@njit(cache=True, nogil=True, error_model="numpy")
def _step_kernel(x, has_input, mapping, target, desired, filtered, speed, t, dt, t_input, ramp, limits):
    """One frame of :meth:`SafetyMapper.step` on arrays (compiled: the step runs on the servo write's
    critical path). ``mapping``: :attr:`Mapping.compiled`; ``limits``: ``SafetyMapper._limits``.

    Returns ``target, desired, filtered, speed, t_input, tripped``.
    """
    low, high, span, neutral, slew, ease_rate, exp, euro, tau, min_cutoff, beta, d_cutoff, watchdog_s = limits
    n = len(low)
    desired = desired.copy()
    if has_input:
        raw = raw_kernel(x, *mapping)
        for s in range(n):
            if np.isfinite(raw[s]):
                desired[s] = min(high[s], max(low[s], raw[s]))
                t_input = t
    tripped = t - t_input > watchdog_s
    new_target, new_filtered, new_speed = np.empty(n), np.empty(n), np.empty(n)
    for s in range(n):
        x_s = (desired[s] - low[s]) / span[s]
        if tripped:  # follow the eased target, so returning input continues from there without a jump
            f, v = (target[s] - low[s]) / span[s], 0.0
        elif dt <= 0:
            f, v = filtered[s], speed[s]
        else:
            f, v = _smooth(x_s, filtered[s], speed[s], dt, exp[s], euro[s], tau[s], min_cutoff[s], beta[s],
                           d_cutoff[s])
        new_filtered[s], new_speed[s] = f, v
        rate = slew[s] * ramp
        if tripped:
            goal, rate = neutral[s], min(rate, ease_rate[s])
        else:
            goal = low[s] + f * span[s]
        if not np.isfinite(goal):
            goal = target[s]
        limit = rate * dt
        move = min(limit, max(-limit, goal - target[s]))
        if not np.isfinite(move):
            move = 0.0
        new_target[s] = min(high[s], max(low[s], target[s] + move))
    return new_target, desired, new_filtered, new_speed, t_input, tripped


@njit(cache=True, nogil=True, error_model="numpy")
def _smooth(x, prev, speed, dt, exp, euro, tau, min_cutoff, beta, d_cutoff):
    """One servo's smoothing filter (normalised units, ``dt > 0``): ``(filtered, speed)``."""
    out = x
    if exp:
        alpha = -np.expm1(-dt / tau) if tau > 0 else 1.0
        out = prev + alpha * (x - prev)
    elif euro:
        raw_speed = min(1e6, max(-1e6, (x - prev) / dt))
        speed = speed + _alpha(d_cutoff, dt) * (raw_speed - speed)
        out = prev + _alpha(min_cutoff + beta * abs(speed), dt) * (x - prev)
    if not np.isfinite(out):
        out = x
    return min(1.0, max(0.0, out)), (speed if np.isfinite(speed) else 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _alpha(cutoff: float, dt: float) -> float:
    """Smoothing factor of a first-order low-pass with ``cutoff`` Hz at step ``dt`` s."""
    tau = 1.0 / (2 * np.pi * cutoff)
    return dt / (dt + tau)


def to_raw_int(targets: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Round targets to integer raw units, kept inside [ceil(low), floor(high)]; shape (n_servos,)."""
    return np.clip(np.rint(targets), np.ceil(low), np.floor(high)).astype(np.int64)
