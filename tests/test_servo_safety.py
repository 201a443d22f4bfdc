"""Mapping curves and the safety stage: property tests over arbitrary inputs, watchdog, soft start, E-stop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livebridge.servo.mapping import Curve, Mapping
from livebridge.servo.safety import Filter, SafetyMapper, to_raw_int

N_MUSCLES = 3


def _mapper(filters=None, watchdog_s=0.5, soft_start_s=0.0, ease_s=1.0):
    weights = np.array([[1.0, 0.0, 0.0], [0.5, -0.8, 0.0], [0.0, 0.0, 1.0]])
    curves = (Curve("linear"), Curve("gamma", gamma=0.5), Curve("piecewise", points=((0, 0), (0.5, 0.8), (1, 1))))
    mapping = Mapping(weights, curves, neutral=np.array([2048.0, 1500.0, 1200.0]),
                      minimum=np.array([1800.0, 1900.0, 1000.0]), maximum=np.array([2600.0, 1100.0, 2000.0]))
    filters = filters or (Filter("none"), Filter("exponential", tau=0.05), Filter("one_euro", min_cutoff=1.0,
                                                                                    beta=0.5))
    return SafetyMapper(mapping, slew=[1000.0, 500.0, 2000.0], filters=filters, watchdog_s=watchdog_s,
                        soft_start_s=soft_start_s, ease_s=ease_s)


def test_curves_and_inverted_range():
    mapper = _mapper()
    m = mapper.mapping
    raw = m.raw(np.array([1.0, 0.0, 1.0]))
    assert raw[0] == 2600 and raw[2] == 2000
    # servo 1 is inverted (max 1100 < min 1900): drive +0.5 -> gamma 0.5 -> 0.707 of the way from 1500 down to 1100
    assert raw[1] == pytest.approx(1500 - math.sqrt(0.5) * 400)
    # negative drive goes toward min
    assert m.raw(np.array([0.0, 1.0, 0.0]))[1] == pytest.approx(1500 + math.sqrt(0.8) * 400)
    assert m.raw(np.array([0.0, 0.0, 0.25]))[2] == pytest.approx(1200 + 0.4 * 800)
    assert np.isnan(m.raw(np.array([np.nan, 0.0, 0.0])))[:2].all()
    assert np.isfinite(m.raw(np.array([np.nan, 0.0, 0.0]))[2])
    with pytest.raises(ValueError):
        Curve("piecewise", points=((0, 0), (0, 1)))


finite_or_not = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                          st.floats(-2, 2), st.sampled_from([1e300, -1e300, np.nan, np.inf]))
frames = st.lists(st.tuples(st.one_of(st.none(), st.lists(finite_or_not, min_size=N_MUSCLES, max_size=N_MUSCLES)),
                            st.one_of(st.floats(-1, 0.5), st.floats(allow_nan=True, allow_infinity=True),
                                      st.floats(0, 1e6))),
                  min_size=1, max_size=40)


@settings(max_examples=300, deadline=None)
@given(frames, st.floats(-10, 10), st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3,
                                                  max_size=3), st.floats(0, 2))
def test_no_input_ever_leaves_limits_or_exceeds_slew(sequence, t0, present, soft_start):
    mapper = _mapper(soft_start_s=soft_start)
    state = mapper.start(np.array(present), t0)
    assert np.all((state.target >= mapper.low) & (state.target <= mapper.high))
    for contractions, dt in sequence:
        previous, t_prev = state.target.copy(), state.t
        t = t_prev + dt if math.isfinite(dt) else dt
        state, targets = mapper.step(state, contractions, t)
        assert np.all(np.isfinite(targets))
        assert np.all(targets >= mapper.low) and np.all(targets <= mapper.high)
        elapsed = max(0.0, state.t - t_prev)
        with np.errstate(over="ignore"):  # a huge elapsed time allows an infinite move: the limits bind then
            allowed = mapper.slew * elapsed
        assert np.all(np.abs(targets - previous) <= allowed + 1e-9 * (1 + np.abs(previous)))
        raw = to_raw_int(targets, mapper.low, mapper.high)
        assert np.all(raw >= mapper.low) and np.all(raw <= mapper.high)


def _run(mapper, state, x, t0, t1, dt=0.01):
    for t in np.arange(t0, t1, dt):
        state, targets = mapper.step(state, x, t)
    return state, targets


def test_non_finite_holds_only_the_servos_using_that_muscle():
    mapper = _mapper()
    state = mapper.start(mapper.neutral, 0.0)
    state, before = _run(mapper, state, np.array([0.5, 0.0, 0.5]), 0.0, 2.0)
    state, after = _run(mapper, state, np.array([np.nan, 0.0, 1.0]), 2.0, 4.0)
    assert after[0] == pytest.approx(before[0]) and after[1] == pytest.approx(before[1])
    assert after[2] == pytest.approx(2000, abs=1)


def test_soft_start_ramps_speed_from_zero():
    mapper = _mapper(soft_start_s=1.0)
    state = mapper.start(np.array([1800.0, 1500.0, 1000.0]), 0.0)
    state, first = mapper.step(state, np.array([1.0, 0.0, 1.0]), 0.01)
    assert abs(first[0] - 1800) <= 1000 * 0.01 * 0.01 + 1e-9  # speed limit ramps: 1% of slew at 10 ms
    state, later = _run(mapper, state, np.array([1.0, 0.0, 1.0]), 0.02, 3.0)
    assert later[0] == pytest.approx(2600)


def test_watchdog_eases_to_neutral_then_input_resumes_without_jump():
    mapper = _mapper(watchdog_s=0.2, ease_s=1.0)
    state = mapper.start(mapper.neutral, 0.0)
    state, moved = _run(mapper, state, np.array([1.0, 0.0, 1.0]), 0.0, 1.0)
    assert moved[0] == pytest.approx(2600)
    state, _ = mapper.step(state, None, 1.1)
    assert not state.watchdog
    state, targets = _run(mapper, state, None, 1.11, 1.5)
    assert state.watchdog and 2048 < targets[0] < 2600  # easing, not jumping
    state, targets = _run(mapper, state, None, 1.5, 4.0)
    assert targets == pytest.approx(mapper.neutral)
    previous, t_previous = targets.copy(), state.t
    state, resumed = mapper.step(state, np.array([1.0, 0.0, 1.0]), 4.01)
    assert not state.watchdog and np.all(np.abs(resumed - previous) <= mapper.slew * (4.01 - t_previous) + 1e-9)


def test_estop_latches():
    mapper = _mapper()
    state = mapper.start(mapper.neutral, 0.0)
    state = mapper.estop(state)
    state, targets = _run(mapper, state, np.array([1.0, 1.0, 1.0]), 0.0, 1.0)
    assert targets == pytest.approx(mapper.neutral) and state.estopped


def test_filter_delay_is_as_stated():
    tau = 0.1
    mapper = _mapper(filters=(Filter("exponential", tau=tau),) * 3)
    mapper.slew[:] = 1e9
    state = mapper.start(mapper.neutral, 0.0)
    dt = 0.001
    ts = np.arange(dt, 4.0, dt)
    out = []
    for t in ts:
        state, targets = mapper.step(state, np.array([0.2 * t, 0.0, 0.0]), t)  # a slow ramp
        out.append(targets[0])
    # for a ramp, a first-order low-pass lags by exactly tau: compare with the unfiltered ramp
    ramp = 2048 + 0.2 * ts * (2600 - 2048)
    lag = (ramp[-1] - out[-1]) / (0.2 * (2600 - 2048))
    assert lag == pytest.approx(Filter("exponential", tau=tau).delay_s, rel=0.02)
    assert Filter("one_euro", min_cutoff=2.0).delay_s == pytest.approx(1 / (4 * np.pi))
