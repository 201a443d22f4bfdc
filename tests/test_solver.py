"""The streaming contraction solver: region modes against scipy's BVLS, held regions, warm starts."""

from __future__ import annotations

import numpy as np
import pytest
from factories import random_basis
from solver_factories import random_markers

from livebridge.bench.solver import ReferenceSolver
from livebridge.errors import InputError
from livebridge.face.basis import Basis, Muscle
from livebridge.face.markers import MarkerSet
from livebridge.solve.solver import MODES, ContractionSolver, SolverConfig, solve_take


def smooth_contractions(n_frames: int, n_muscles: int, rng: np.random.Generator, peak: float = 1.0) -> np.ndarray:
    """Smooth random contractions (n_frames, n_muscles) in [0, peak], with long stretches at 0 and at peak."""
    t = np.linspace(0, 1, n_frames)[:, None]
    phases = rng.uniform(0, 2 * np.pi, size=(3, n_muscles))
    rates = rng.uniform(1, 6, size=(3, n_muscles))
    wave = sum(np.sin(2 * np.pi * rates[k] * t + phases[k]) for k in range(3)) / 2
    return np.clip(wave, 0, 1) * peak


def observed(markers: MarkerSet, basis: Basis, x: np.ndarray, rng: np.random.Generator, noise: float = 0.2,
             missing: float = 0.0) -> np.ndarray:
    """Marker displacements (n_frames, n_markers, 3) for contractions ``x`` with noise and missing markers."""
    displacements = markers.marker_positions(basis, x) - markers.neutral_positions(basis)
    displacements = displacements + rng.normal(scale=noise, size=displacements.shape)
    displacements[rng.random(displacements.shape[:2]) < missing] = np.nan
    return displacements


@pytest.fixture(scope="module")
def small():
    """A 6-muscle random basis with 24 face markers and 2 head markers."""
    rng = np.random.default_rng(11)
    basis = random_basis(rng, n_vertices=400, n_muscles=6)
    return basis, random_markers(basis, 24, rng, n_head=2)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("exaggerate", [False, True])
def test_modes_match_scipy_bvls_step_for_step(small, mode, exaggerate):
    basis, markers = small
    rng = np.random.default_rng(2)
    x = smooth_contractions(120, basis.n_muscles, rng, peak=1.4 if exaggerate else 1.0)
    data = observed(markers, basis, x, rng, noise=0.3, missing=0.1)
    config = SolverConfig(mode=mode, exaggerate=exaggerate)
    ours = ContractionSolver(basis, markers, config).solve_take(data)
    reference = ReferenceSolver(basis, markers, config).solve_take(data)
    assert np.abs(ours.contractions - reference.contractions).max() <= 1e-6
    assert np.allclose(ours.rms_error_mm, reference.rms_error_mm, atol=1e-6, equal_nan=True)
    if exaggerate:
        assert ours.contractions.max() > 1.05
    else:
        assert ours.contractions.max() <= 1.0
    assert ours.contractions.min() >= 0.0


def test_ict_modes_match_scipy_step_for_step(ict, rng):
    markers = random_markers(ict, 48, rng)
    x = smooth_contractions(150, ict.n_muscles, rng)
    data = observed(markers, ict, x, rng, noise=0.2, missing=0.05)
    for mode in MODES:
        config = SolverConfig(mode=mode)
        ours = ContractionSolver(ict, markers, config).solve_take(data)
        reference = ReferenceSolver(ict, markers, config).solve_take(data)
        assert np.abs(ours.contractions - reference.contractions).max() <= 1e-6, mode


def test_noise_free_data_is_recovered_exactly(small):
    basis, markers = small
    rng = np.random.default_rng(4)
    x = smooth_contractions(40, basis.n_muscles, rng)
    data = observed(markers, basis, x, rng, noise=0.0)
    for mode in ("joint", "split-compensated"):
        solution = solve_take(basis, markers, data, SolverConfig(mode=mode, sweeps=30))
        assert np.abs(solution.contractions - x).max() < 1e-6, mode
        assert np.nanmax(solution.rms_error_mm) < 1e-5


def test_a_region_with_every_marker_missing_is_held(small):
    basis, markers = small
    rng = np.random.default_rng(5)
    x = smooth_contractions(30, basis.n_muscles, rng)
    data = observed(markers, basis, x, rng, noise=0.1)
    upper_markers = markers.region_mask("upper")
    upper_muscles = basis.region_mask("upper")
    data[10:15][:, upper_markers] = np.nan
    data[20][markers.face_mask] = np.nan
    for mode in MODES:
        solver = ContractionSolver(basis, markers, SolverConfig(mode=mode))
        reference = ReferenceSolver(basis, markers, SolverConfig(mode=mode))
        state, ref_state = solver.initial_state(), reference.initial_state()
        for i, frame in enumerate(data):
            before = state.contractions
            state, result = solver.step(state, frame)
            ref_state, ref_result = reference.step(ref_state, frame)
            assert np.abs(result.contractions - ref_result.contractions).max() <= 1e-6
            if 10 <= i < 15:
                assert result.held_regions == ("upper",)
                assert np.array_equal(result.held, upper_muscles)
                assert np.array_equal(result.contractions[upper_muscles], before[upper_muscles])
                assert np.all(np.isnan(result.unconstrained[upper_muscles]))
                assert np.all(np.isfinite(result.unconstrained[~upper_muscles]))
                assert np.isnan(result.rms_mm("upper")) and np.isfinite(result.rms_mm("lower"))
            elif i == 20:
                assert result.held_regions == ("upper", "lower") and result.held.all()
                assert np.array_equal(result.contractions, before)
            else:
                assert result.held_regions == () and not result.held.any()
        if mode != "split-compensated":  # history-free modes: after the gap, as if there had been none
            _, fresh = ContractionSolver(basis, markers, SolverConfig(mode=mode)).step(solver.initial_state(),
                                                                                      data[-1])
            assert np.abs(state.contractions - fresh.contractions).max() <= 1e-9


def test_warm_start_gives_the_cold_start_result(small):
    """The working set carried in the state only speeds the solve up: a cold working set gives the same x."""
    basis, markers = small
    rng = np.random.default_rng(6)
    x = smooth_contractions(80, basis.n_muscles, rng)
    data = observed(markers, basis, x, rng, noise=0.3, missing=0.05)
    for mode in MODES:
        solver = ContractionSolver(basis, markers, SolverConfig(mode=mode))
        cold_solver = ContractionSolver(basis, markers, SolverConfig(mode=mode))
        state = solver.initial_state()
        for frame in data:
            cold_state = type(state)(state.contractions, np.zeros_like(state.active), state.frame)
            state, warm = solver.step(state, frame)
            _, cold = cold_solver.step(cold_state, frame)
            assert np.abs(warm.contractions - cold.contractions).max() <= 1e-10


def test_results_are_frozen_and_state_is_not_mutated(small):
    basis, markers = small
    solver = ContractionSolver(basis, markers)
    state = solver.initial_state()
    frame = observed(markers, basis, np.full((1, basis.n_muscles), 0.5), np.random.default_rng(0))[0]
    new_state, result = solver.step(state, frame)
    assert np.all(state.contractions == 0) and np.all(state.active == 0)
    assert new_state.frame == 1 and result.n_visible == 24
    with pytest.raises(AttributeError):
        result.contractions = None
    # head markers are ignored: garbage in their rows changes nothing
    frame2 = frame.copy()
    frame2[markers.head_mask] = 1e6
    _, result2 = solver.step(state, frame2)
    assert np.array_equal(result.contractions, result2.contractions)


def test_bad_configuration_and_input():
    with pytest.raises(InputError, match="mode"):
        SolverConfig(mode="both")
    with pytest.raises(InputError, match="sweeps"):
        SolverConfig(sweeps=0)
    rng = np.random.default_rng(0)
    basis = random_basis(rng, n_vertices=100, n_muscles=4)
    solver = ContractionSolver(basis, random_markers(basis, 10, rng))
    with pytest.raises(ValueError, match="shape"):
        solver.step(solver.initial_state(), np.zeros((9, 3)))
    with pytest.raises(InputError, match="displacements"):
        solver.solve_take(np.zeros((5, 9, 3)))


def test_unconstrained_is_each_blocks_least_squares(small):
    """The validation signal: per region (split) or for all muscles (joint), lstsq over the visible rows."""
    basis, markers = small
    rng = np.random.default_rng(7)
    frame = observed(markers, basis, np.full((1, basis.n_muscles), 0.6), rng, noise=0.5, missing=0.2)[0]
    seen = markers.face_mask & ~np.isnan(frame).any(axis=1)
    d_matrix = markers.displacement_matrix(basis)  # (n, M, 3)
    regions = [(seen & markers.region_mask(r), basis.region_mask(r)) for r in ("upper", "lower")]
    for mode, groups in (("joint", [(seen, np.ones(basis.n_muscles, bool))]), ("split", regions)):
        solver = ContractionSolver(basis, markers, SolverConfig(mode=mode))
        _, result = solver.step(solver.initial_state(), frame)
        for rows, muscles in groups:
            a_rows = np.transpose(d_matrix[rows][:, muscles], (0, 2, 1)).reshape(-1, muscles.sum())
            expected = np.linalg.lstsq(a_rows, frame[rows].ravel(), rcond=None)[0]
            assert np.allclose(result.unconstrained[muscles], expected, atol=1e-9), mode


def test_rank_deficient_basis_reaches_the_bvls_fit():
    """Two identical elements: x is not unique, the fit is; every mode must reach scipy's marker error."""
    rng = np.random.default_rng(8)
    basis = random_basis(rng, n_vertices=400, n_muscles=6)
    elements = basis.elements.copy()
    elements[4] = elements[2]  # both upper-face muscles in random_basis (even indices)
    basis = Basis(basis.neutral, basis.triangles, elements, basis.muscles)
    markers = random_markers(basis, 24, rng)
    x = smooth_contractions(40, basis.n_muscles, rng) * 0.5
    data = observed(markers, basis, x, rng, noise=0.2, missing=0.05)
    for mode in MODES:
        ours = ContractionSolver(basis, markers, SolverConfig(mode=mode)).solve_take(data)
        reference = ReferenceSolver(basis, markers, SolverConfig(mode=mode)).solve_take(data)
        assert np.all(np.isfinite(ours.contractions)) and ours.contractions.min() >= 0 and ours.contractions.max() <= 1
        assert np.allclose(ours.rms_error_mm, reference.rms_error_mm, atol=1e-5, equal_nan=True), mode
        duplicate_sum = ours.contractions[:, 2] + ours.contractions[:, 4]
        assert np.allclose(duplicate_sum, reference.contractions[:, 2] + reference.contractions[:, 4], atol=1e-4)


def test_every_muscle_in_one_region(rng):
    """A basis without lower-face muscles: joint uses every marker, split ignores the lower-face markers."""
    basis = random_basis(rng, n_vertices=300, n_muscles=4)
    basis = Basis(basis.neutral, basis.triangles, basis.elements,
                  tuple(Muscle(m.name, "upper", None, "") for m in basis.muscles))
    triangles = rng.choice(len(basis.triangles), size=16, replace=False)
    markers = MarkerSet(tuple(f"m{i}" for i in range(16)), triangles, rng.dirichlet(np.ones(3), size=16),
                        tuple("upper" if i % 2 else "lower" for i in range(16)), ("face",) * 16)
    data = observed(markers, basis, smooth_contractions(20, 4, rng), rng, noise=0.1, missing=0.1)
    for mode in MODES:
        ours = ContractionSolver(basis, markers, SolverConfig(mode=mode)).solve_take(data)
        reference = ReferenceSolver(basis, markers, SolverConfig(mode=mode)).solve_take(data)
        assert np.abs(ours.contractions - reference.contractions).max() <= 1e-6, mode
