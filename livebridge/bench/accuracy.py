"""Contraction accuracy of the three region modes on a performer take, all markers and 10% missing."""

from __future__ import annotations

import numpy as np


def run(quick: bool, log) -> dict:
    from livebridge.bench.solver import bench_setup
    from livebridge.solve.solver import MODES, ContractionSolver, SolverConfig

    n_frames = 400 if quick else 3000
    name, basis, markers, performance = bench_setup(n_frames, seed=2)
    rng = np.random.default_rng(0)
    observed = performance.marker_displacements + rng.normal(scale=0.2, size=performance.marker_displacements.shape)
    missing = observed.copy()
    missing[rng.random(observed.shape[:2]) < 0.10] = np.nan
    truth = performance.contractions
    result = {"basis": name, "frames": n_frames}
    for mode in MODES:
        key = mode.replace("-", "_")
        for suffix, data in (("", observed), ("_missing10", missing)):
            solution = ContractionSolver(basis, markers, SolverConfig(mode=mode)).solve_take(data)
            error = solution.contractions - truth
            result[f"rmse_{key}{suffix}"] = float(np.sqrt(np.mean(error ** 2)))
            if mode == "split-compensated" and not suffix:
                result["p99_abs_err"] = float(np.quantile(np.abs(error), 0.99))
                rms = solution.rms_error_mm
                result["marker_rms_mm_upper"] = float(np.sqrt(np.nanmean(rms[:, 0] ** 2)))
                result["marker_rms_mm_lower"] = float(np.sqrt(np.nanmean(rms[:, 1] ** 2)))
            log(f"{mode:18s} {'10% missing' if suffix else 'all visible':12s} "
                f"RMSE {result[f'rmse_{key}{suffix}']:.4f}")
    result["pass"] = bool(result["rmse_split_compensated"] <= 0.015
                          and result["rmse_split_compensated_missing10"] <= 0.02)
    return result
