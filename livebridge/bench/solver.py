"""Contraction solver: our active-set QP vs scipy lsq_linear(bvls), same region mode step for step."""

from __future__ import annotations

import time

import numpy as np

from livebridge.qp import RANK_TOLERANCE, SINGULAR, box_qp_kernel
from livebridge.solve.solver import ALL_MARKERS, ContractionSolver, _block_system, _errors, _prepare


class ReferenceSolver(ContractionSolver):
    """The contraction solver's reference for tests and benchmarks: the same frame, step for step, with each
    block's QP solved by ``scipy.optimize.lsq_linear(method="bvls")`` on the block's marker rows instead of the
    active-set kernel; everything else (visibility, compensation, unconstrained solve, marker errors) runs
    through the solver's own compiled helpers. Same constructor and methods as
    :class:`~livebridge.solve.solver.ContractionSolver`.
    """

    def frame_kernel(self, observed, face_index, marker_region, a, marker_gram, full_gram, perm, plans, plan_sizes,
                     sweeps, upper, x_previous, active_previous, x_out, active_out, unconstrained_out, errors):
        """The compiled frame kernel with each block's QP solved by ``scipy.optimize.lsq_linear(method="bvls")``.

        Same arguments and return value. The unconstrained solution is the active-set kernel's (as in
        the compiled kernel); the working set is carried over unchanged, one "iteration" per QP.
        """
        from scipy.optimize import lsq_linear

        n_face, n_muscles = len(face_index), len(perm)
        d, visible = np.empty((n_face, 3)), np.empty(n_face, bool)
        grams, c, counts = np.empty((3, n_muscles, n_muscles)), np.empty((3, n_muscles)), np.empty(2, np.int64)
        _prepare(observed, face_index, marker_region, a, marker_gram, full_gram, d, visible, grams, c, counts)
        held_code = (counts[0] == 0) + 2 * (counts[1] == 0)
        plan, n_blocks = plans[held_code], plan_sizes[held_code]
        x, unconstrained = x_previous[perm], np.full(n_muscles, np.nan)
        rows_of, targets = a.reshape(3 * n_face, n_muscles), d.ravel()
        for sweep in range(sweeps):
            for block in range(n_blocks):
                marker_set, start, stop, other_start, other_stop = plan[block].tolist()
                if sweep == sweeps - 1:
                    gram, rhs, scale = _block_system(grams, full_gram, c, x, plan, block)
                    unconstrained[start:stop] = _reference_unconstrained(gram, rhs, scale)
                in_rows = visible if marker_set == ALL_MARKERS else visible & (marker_region == marker_set)
                rows = np.flatnonzero(np.repeat(in_rows, 3))
                a_rows = rows_of[rows]
                target = targets[rows] - a_rows[:, other_start:other_stop] @ x[other_start:other_stop]
                x[start:stop] = lsq_linear(a_rows[:, start:stop], target, bounds=(0.0, upper), method="bvls").x
        _errors(d, visible, marker_region, a, x, counts, errors)
        x_out[perm], unconstrained_out[perm] = x, unconstrained
        active_out[:] = active_previous
        return sweeps * n_blocks, int(counts[0]), int(counts[1])


def _reference_unconstrained(gram: np.ndarray, rhs: np.ndarray, scale: float) -> np.ndarray:
    """Stage 0 of the compiled frame kernel: ``Q^-1 c`` (k,), with the same rank test and ridge."""
    unbounded, solution = np.full(len(rhs), np.inf), np.empty(len(rhs))
    _, status = box_qp_kernel(gram, rhs, -unbounded, unbounded, np.zeros(len(rhs), np.int8), solution, 0.0,
                              RANK_TOLERANCE * scale, False, 1)
    if status == SINGULAR:
        box_qp_kernel(gram + RANK_TOLERANCE * scale * np.eye(len(rhs)), rhs, -unbounded, unbounded,
                      np.zeros(len(rhs), np.int8), solution, 0.0, 0.0, True, 1)
    return solution


def bench_setup(n_frames: int, seed: int = 0, script: str = "mixed"):
    """(name of the basis, basis, 64 designed markers, performance) for the solver benchmarks."""
    from livebridge.bench.data import ict_basis
    from livebridge.face.layout import design_markers
    from livebridge.simulators.performer import perform

    basis = ict_basis()
    name = "ict"
    if basis is None:
        from livebridge.face.builtin import builtin_basis

        basis, name = builtin_basis(), "builtin"
    markers = design_markers(basis, 64)
    return name, basis, markers, perform(basis, markers, n_frames, seed=seed, script=script)


def run(quick: bool, log) -> dict:
    from livebridge.solve.solver import SolverConfig

    n_frames = 300 if quick else 3000
    name, basis, markers, performance = bench_setup(n_frames, seed=1)
    rng = np.random.default_rng(0)
    observed = performance.marker_displacements + rng.normal(scale=0.2, size=performance.marker_displacements.shape)
    observed[rng.random(observed.shape[:2]) < 0.05] = np.nan
    config = SolverConfig()
    log(f"{name} basis, {basis.n_muscles} muscles, {int(markers.face_mask.sum())} face markers, {n_frames} frames, "
        f"5% missing, mode {config.mode}")
    start = time.perf_counter()
    ours = ContractionSolver(basis, markers, config)  # compiles the numba kernels, or loads them from the cache
    construction_s = time.perf_counter() - start
    reference = ReferenceSolver(basis, markers, config)
    # interleave chunks so that load on a shared machine hits both alike; CPU time of this process
    chunk = 100
    ours_time = reference_time = 0.0
    state, reference_state = ours.initial_state(), reference.initial_state()
    x_ours = np.empty((n_frames, basis.n_muscles))
    x_reference = np.empty_like(x_ours)
    for start in range(0, n_frames, chunk):
        frames = range(start, min(start + chunk, n_frames))
        t0 = time.process_time()
        for i in frames:
            state, result = ours.step(state, observed[i])
            x_ours[i] = result.contractions
        t1 = time.process_time()
        for i in frames:
            reference_state, result = reference.step(reference_state, observed[i])
            x_reference[i] = result.contractions
        t2 = time.process_time()
        ours_time += t1 - t0
        reference_time += t2 - t1
    ours_us = ours_time / n_frames * 1e6
    scipy_us = reference_time / n_frames * 1e6
    max_abs_diff = float(np.abs(x_ours - x_reference).max())
    speedup = scipy_us / ours_us
    log(f"ours {ours_us:.1f} us/frame, scipy {scipy_us:.1f} us/frame, speedup {speedup:.2f}, "
        f"max |diff| {max_abs_diff:.2e}")
    return {
        "basis": name, "frames": n_frames, "mode": config.mode,
        "ours_us_per_frame": round(ours_us, 2), "scipy_us_per_frame": round(scipy_us, 2),
        "speedup": round(speedup, 2), "max_abs_diff": max_abs_diff, "ours_construction_s": round(construction_s, 3),
        "rmse_vs_truth": float(np.sqrt(np.mean((x_ours - performance.contractions) ** 2))),
        "pass": bool(speedup >= 10 and max_abs_diff <= 1e-6),
    }
