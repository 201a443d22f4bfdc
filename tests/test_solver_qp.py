"""The active-set box QP: KKT conditions, agreement with scipy's BVLS, degenerate cases, warm starts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from livebridge.qp import AT_LOWER, AT_UPPER, FREE, BoxQP


def _problem(seed: int, n_rows: int, n_vars: int, scale: float = 3.0):
    rng = np.random.default_rng(seed)
    d_matrix = rng.normal(size=(n_rows, n_vars))
    target = rng.normal(size=n_rows) * scale
    return d_matrix, target


def _kkt_violation(qp: BoxQP, x: np.ndarray, c: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """Largest violation of the KKT conditions of the box QP, relative to the problem's scale."""
    gradient = qp.gram @ x - c
    scale = np.abs(qp.gram).max() * max(1.0, np.abs(x).max()) + np.abs(c).max()
    at_lower = np.isclose(x, lower, rtol=0, atol=1e-12)
    at_upper = np.isclose(x, upper, rtol=0, atol=1e-12)
    inside = ~at_lower & ~at_upper
    violations = [
        np.maximum(lower - x, 0).max(initial=0), np.maximum(x - upper, 0).max(initial=0),  # feasibility
        np.abs(gradient[inside]).max(initial=0) / scale,  # stationarity of the free variables
        np.maximum(-gradient[at_lower & ~at_upper], 0).max(initial=0) / scale,  # multiplier signs
        np.maximum(gradient[at_upper & ~at_lower], 0).max(initial=0) / scale,
    ]
    return float(max(violations))


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**31), n_vars=st.integers(1, 12), extra_rows=st.integers(0, 40),
       exaggerate=st.booleans())
def test_kkt_conditions_hold_on_random_problems(seed, n_vars, extra_rows, exaggerate):
    d_matrix, target = _problem(seed, n_vars + extra_rows, n_vars)
    lower = np.zeros(n_vars)
    upper = np.full(n_vars, np.inf if exaggerate else 1.0)
    qp = BoxQP(d_matrix.T @ d_matrix, lower, upper)
    c = d_matrix.T @ target
    result = qp.solve(c)
    assert result.converged
    assert _kkt_violation(qp, result.x, c, lower, upper) < 1e-9
    # the reported working set agrees with x
    assert np.all(result.x[result.active == AT_LOWER] == 0.0)
    assert np.all(result.x[result.active == AT_UPPER] == 1.0)


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31), n_vars=st.integers(1, 12), extra_rows=st.integers(1, 40),
       exaggerate=st.booleans())
def test_matches_scipy_bvls_on_well_posed_problems(seed, n_vars, extra_rows, exaggerate):
    d_matrix, target = _problem(seed, n_vars + extra_rows, n_vars)
    upper = np.inf if exaggerate else 1.0
    if np.linalg.cond(d_matrix) > 1e4:
        return
    ours = BoxQP(d_matrix.T @ d_matrix, 0.0, upper).solve(d_matrix.T @ target).x
    reference = lsq_linear(d_matrix, target, bounds=(0.0, upper), method="bvls", tol=1e-12).x
    assert np.abs(ours - reference).max() <= 1e-6


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), n_vars=st.integers(2, 12), rank=st.integers(1, 11))
def test_rank_deficient_problems_reach_the_bvls_optimum(seed, n_vars, rank):
    """A singular Gram matrix: x is not unique, the objective is; ours must reach scipy's."""
    rng = np.random.default_rng(seed)
    rank = min(rank, n_vars - 1)
    d_matrix = rng.normal(size=(30, rank)) @ rng.normal(size=(rank, n_vars))  # rank < n_vars
    target = rng.normal(size=30) * 3
    qp = BoxQP(d_matrix.T @ d_matrix, 0.0, 1.0)
    assert qp.rank_deficient
    x = qp.solve(d_matrix.T @ target).x
    reference = lsq_linear(d_matrix, target, bounds=(0.0, 1.0), method="bvls", tol=1e-12).x
    ours_cost = np.sum((d_matrix @ x - target) ** 2)
    reference_cost = np.sum((d_matrix @ reference - target) ** 2)
    assert np.all((x >= 0) & (x <= 1))
    assert ours_cost <= reference_cost + 1e-6 * max(1.0, reference_cost)


def test_duplicate_columns_and_zero_columns():
    """Two identical elements and one element no marker sees: finite, feasible, optimal objective."""
    rng = np.random.default_rng(3)
    d_matrix = rng.normal(size=(20, 5))
    d_matrix[:, 3] = d_matrix[:, 1]
    d_matrix[:, 4] = 0.0
    target = d_matrix @ np.array([0.3, 0.4, 0.9, 0.4, 0.0]) + rng.normal(size=20) * 0.01
    qp = BoxQP(d_matrix.T @ d_matrix, 0.0, 1.0)
    x = qp.solve(d_matrix.T @ target).x
    assert np.all(np.isfinite(x))
    reference = lsq_linear(d_matrix, target, bounds=(0.0, 1.0), method="bvls").x
    assert np.sum((d_matrix @ x - target) ** 2) <= np.sum((d_matrix @ reference - target) ** 2) + 1e-9
    assert abs(x[1] + x[3] - 0.8) < 0.02  # only the sum of the duplicates is determined
    assert x[4] == pytest.approx(0.0, abs=1e-6)  # the unseen element stays near the minimum norm


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31), n_vars=st.integers(1, 12), start_seed=st.integers(0, 2**31))
def test_warm_start_gives_the_cold_start_result(seed, n_vars, start_seed):
    d_matrix, target = _problem(seed, n_vars + 10, n_vars)
    qp = BoxQP(d_matrix.T @ d_matrix, 0.0, 1.0)
    c = d_matrix.T @ target
    cold = qp.solve(c)
    guess = np.random.default_rng(start_seed).integers(-1, 2, size=n_vars).astype(np.int8)
    warm = qp.solve(c, active=guess)
    assert np.abs(warm.x - cold.x).max() <= 1e-10
    again = qp.solve(c, active=cold.active)
    assert again.iterations == 1
    assert np.abs(again.x - cold.x).max() <= 1e-12


def test_exaggeration_lets_contractions_exceed_one():
    rng = np.random.default_rng(5)
    d_matrix = rng.normal(size=(30, 4))
    truth = np.array([0.0, 0.5, 1.6, 2.5])
    target = d_matrix @ truth
    gram, c = d_matrix.T @ d_matrix, d_matrix.T @ target
    exaggerated = BoxQP(gram, 0.0, np.inf).solve(c)
    assert np.allclose(exaggerated.x, truth, atol=1e-10)
    assert not np.any(exaggerated.active == AT_UPPER)
    bounded = BoxQP(gram, 0.0, 1.0).solve(c)
    assert bounded.x.max() <= 1.0 and np.any(bounded.active == AT_UPPER)
    # an upper-bound working set on an infinite bound is read as free
    assert np.allclose(BoxQP(gram, 0.0, np.inf).solve(c, active=np.full(4, AT_UPPER, np.int8)).x, truth, atol=1e-10)


def test_general_bounds_and_unconstrained():
    rng = np.random.default_rng(9)
    d_matrix = rng.normal(size=(25, 6))
    target = rng.normal(size=25) * 4
    lower = np.array([-1.0, 0.0, 0.2, -0.5, 0.0, 0.1])
    upper = np.array([0.5, 1.0, 0.3, np.inf, 2.0, 0.1])
    qp = BoxQP(d_matrix.T @ d_matrix, lower, upper)
    x = qp.solve(d_matrix.T @ target).x
    reference = lsq_linear(d_matrix, target, bounds=(lower, upper + np.where(upper == lower, 1e-12, 0)),
                           method="bvls", tol=1e-12).x
    assert np.abs(x - reference).max() < 1e-6
    assert np.allclose(qp.unconstrained(d_matrix.T @ target), np.linalg.lstsq(d_matrix, target, rcond=None)[0])
    assert FREE == 0


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="square"):
        BoxQP(np.zeros((2, 3)), 0.0, 1.0)
    with pytest.raises(ValueError, match="bounds"):
        BoxQP(np.eye(2), np.array([0.0, 1.0]), np.array([1.0, 0.5]))
    with pytest.raises(ValueError, match="shape"):
        BoxQP(np.eye(2), 0.0, 1.0).solve(np.zeros(3))
