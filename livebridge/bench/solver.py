"""Contraction solver: our active-set QP vs scipy lsq_linear(bvls), same region mode step for step."""

from __future__ import annotations

import time

import numpy as np


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
    from livebridge.solve.solver import ContractionSolver, SolverConfig

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
    reference = ContractionSolver(basis, markers, config, backend="scipy-bvls")
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
