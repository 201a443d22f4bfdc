"""Basis validation: does a training take fit the actuation basis, and which element is wrong?

The solver runs over the take; two per-muscle signals point at a badly sculpted element:

- **Range excursions** of the *unconstrained* contractions (:attr:`SolveResult.unconstrained`, the
  region's least squares without bounds): a correct element fitted to a performer who stays within
  the face's range gives values in about [0, 1]; an element sculpted too weak needs values far above
  1, one pointing the wrong way needs negative values. Reported: the fraction of frames outside
  ``[low, high]`` (default [-0.2, 1.2]) and by how much (largest and mean distance beyond the band).
- **Misfit**: the residual marker displacements, regressed on the contractions, frame by frame and
  marker by marker (the same least-squares re-fit that basis refinement makes): the correction
  ``delta_ij`` that element ``i`` would need at marker ``j``. Reported relative to the element:
  ``sqrt(sum_j |delta_ij|^2) / sqrt(sum_j |d_ij|^2)``. A correct element's misfit is at the noise level
  (a few per cent); an element scaled by 0.4 or rotated by tens of degrees has a misfit of order one.

A muscle is flagged when either signal passes its threshold. Per region the report gives the marker
error (RMS and mean, mm) over the take. :func:`plot_report` draws the contraction curves with the
per-region error below, like Figure 5 of Choe & Ko.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.face.basis import REGIONS, Basis
from livebridge.face.markers import MarkerSet
from livebridge.solve.solver import ContractionSolver, SolverConfig, TakeSolution

RANGE = (-0.2, 1.2)
OUTSIDE_THRESHOLD = 0.05  # fraction of frames
MISFIT_THRESHOLD = 0.4  # relative correction norm
EXERCISED_LEVEL, EXERCISED_FRAMES = 0.3, 10


@dataclass(frozen=True)
class MuscleCheck:
    """Validation figures of one basis element.

    Attributes
    ----------
    name, region : str
    fraction_outside : float
        Fraction of frames (where the muscle was solved) whose unconstrained contraction leaves the range.
    max_excursion : float
        Largest distance beyond the range (0 when never outside).
    mean_excursion : float
        Mean distance beyond the range over the frames outside (0 when never outside).
    unconstrained_min, unconstrained_max : float
    misfit : float
        Relative size of the least-squares correction the element would need (see the module docstring);
        NaN when the take does not exercise the muscle.
    exercised : bool
        The take holds the muscle above ``0.3`` for at least 10 frames (otherwise the misfit says nothing).
    flagged : bool
    """

    name: str
    region: str
    fraction_outside: float
    max_excursion: float
    mean_excursion: float
    unconstrained_min: float
    unconstrained_max: float
    misfit: float
    exercised: bool
    flagged: bool


@dataclass(frozen=True, eq=False)
class BasisReport:
    """The result of :func:`check_basis`.

    Attributes
    ----------
    muscles : tuple of MuscleCheck
    region_rms_mm : dict of str to float
        Per marker region, RMS over frames and visible markers of ``|d_hat_j - d_j|``, mm.
    region_mean_mm : dict of str to float
        Per marker region, the per-frame mean marker error averaged over frames, mm.
    t : ndarray, shape (n_frames,)
    solution : TakeSolution
    range : tuple of float
    """

    muscles: tuple[MuscleCheck, ...]
    region_rms_mm: dict
    region_mean_mm: dict
    t: np.ndarray
    solution: TakeSolution
    range: tuple[float, float]

    @property
    def flagged(self) -> tuple[str, ...]:
        """Names of the flagged muscles."""
        return tuple(m.name for m in self.muscles if m.flagged)

    def summary(self) -> str:
        """A plain-text table of the report."""
        low, high = self.range
        lines = [f"basis check over {len(self.t)} frames; unconstrained range [{low:g}, {high:g}], "
                 f"flag: outside > {OUTSIDE_THRESHOLD:.0%} of frames or misfit > {MISFIT_THRESHOLD:g}", ""]
        lines.append(f"{'muscle':24s} {'region':6s} {'outside':>8s} {'max exc':>8s} {'mean exc':>8s} "
                     f"{'min':>7s} {'max':>7s} {'misfit':>7s}")
        for m in self.muscles:
            lines.append(f"{m.name:24s} {m.region:6s} {m.fraction_outside:8.1%} {m.max_excursion:8.3f} "
                         f"{m.mean_excursion:8.3f} {m.unconstrained_min:7.2f} {m.unconstrained_max:7.2f} "
                         f"{m.misfit:7.3f}{'' if m.exercised else '  (not exercised)'}"
                         f"{'  <-- FLAGGED' if m.flagged else ''}")
        lines.append("")
        for region in REGIONS:
            lines.append(f"marker error {region:5s}: RMS {self.region_rms_mm[region]:.3f} mm, "
                         f"mean {self.region_mean_mm[region]:.3f} mm")
        lines.append("")
        lines.append("flagged: " + (", ".join(self.flagged) if self.flagged else "none"))
        return "\n".join(lines)


def marker_misfit(displacement: np.ndarray, observed: np.ndarray, contractions: np.ndarray,
                  ridge: float = 1e-6) -> np.ndarray:
    """Per-marker least-squares correction of ``d_ij`` given contractions over a take.

    Parameters
    ----------
    displacement : ndarray, shape (n_markers, n_muscles, 3)
        The basis' ``d_ij``.
    observed : ndarray, shape (n_frames, n_markers, 3)
        Observed displacements, NaN rows unseen.
    contractions : ndarray, shape (n_frames, n_muscles)
    ridge : float
        Relative Tikhonov term (muscles the take never moves get no correction).

    Returns
    -------
    ndarray, shape (n_markers, n_muscles, 3)
        ``argmin_delta sum_t |d_hat_j(t) - sum_i x_i(t) (d_ij + delta_ij)|^2`` per marker.
    """
    return refit_displacements(observed, contractions, ridge) - displacement


def refit_displacements(observed: np.ndarray, contractions: np.ndarray, ridge: float = 1e-6,
                        prior: np.ndarray | None = None) -> np.ndarray:
    """Least-squares ``d_ij`` per marker from contractions: ``argmin sum_t |d_hat_j(t) - x(t) D_j|^2``.

    Parameters
    ----------
    observed : ndarray, shape (n_frames, n_markers, 3)
        NaN rows unseen.
    contractions : ndarray, shape (n_frames, n_muscles)
    ridge : float or ndarray, shape (n_markers, n_muscles)
        A float: Tikhonov weight relative to ``trace(X^T X) / n_muscles``. An array: absolute weights per
        marker and muscle (a Gaussian prior ``d_ij ~ N(prior_ij, sigma^2 / ridge_ij)``). Pulls towards
        ``prior`` (default 0).
    prior : ndarray, shape (n_markers, n_muscles, 3), optional

    Returns
    -------
    ndarray, shape (n_markers, n_muscles, 3)
    """
    n_frames, n_markers, _ = observed.shape
    n_muscles = contractions.shape[1]
    seen = ~np.isnan(observed).any(axis=2)  # (T, n)
    data = np.where(seen[:, :, None], observed, 0.0)
    # normal equations of every marker at once: G_j = sum_t seen_tj x_t x_t^T, b_j = sum_t seen_tj x_t d_tj^T
    gram = np.einsum("tj,tm,tl->jml", seen.astype(float), contractions, contractions)
    rhs = np.einsum("tm,tjk->jmk", contractions, data)
    if np.ndim(ridge) == 0:
        scale = np.trace(gram, axis1=1, axis2=2)[:, None] / n_muscles
        lam = ridge * np.maximum(scale, 1e-12) * np.ones((1, n_muscles))  # (n, M)
    else:
        lam = np.asarray(ridge, dtype=np.float64)
    if prior is not None:
        rhs = rhs + lam[:, :, None] * prior
    index = np.arange(n_muscles)
    gram[:, index, index] += lam
    return np.linalg.solve(gram, rhs)


def check_basis(basis: Basis, markers: MarkerSet, displacements: np.ndarray, t: np.ndarray | None = None,
                config: SolverConfig | None = None, low: float = RANGE[0], high: float = RANGE[1],
                outside_threshold: float = OUTSIDE_THRESHOLD, misfit_threshold: float = MISFIT_THRESHOLD,
                progress: bool = False) -> BasisReport:
    """Validate a basis on a training take.

    Parameters
    ----------
    basis : Basis
    markers : MarkerSet
    displacements : ndarray, shape (n_frames, n_markers, 3)
        Observed marker displacements (model frame, mm), NaN rows unseen; in the marker set's order.
    t : ndarray, shape (n_frames,), optional
        Timestamps for the plot (default: frame numbers).
    config : SolverConfig, optional

    Returns
    -------
    BasisReport
    """
    displacements = np.asarray(displacements, dtype=np.float64)
    solver = ContractionSolver(basis, markers, config)
    solution = solver.solve_take(displacements, progress=progress)
    unconstrained = solution.unconstrained
    solved = ~solution.held
    below = np.where(solved, np.maximum(low - unconstrained, 0.0), 0.0)
    above = np.where(solved, np.maximum(unconstrained - high, 0.0), 0.0)
    excursion = np.nan_to_num(below + above)
    outside = excursion > 0
    n_solved = np.maximum(solved.sum(axis=0), 1)
    face = solver.face_index
    correction = marker_misfit(solver.displacement, displacements[:, face], solution.contractions)
    element_norm = np.sqrt((solver.displacement ** 2).sum(axis=(0, 2)))
    misfit = np.sqrt((correction ** 2).sum(axis=(0, 2))) / np.maximum(element_norm, 1e-12)
    exercised = (solution.contractions > EXERCISED_LEVEL).sum(axis=0) >= EXERCISED_FRAMES
    misfit = np.where(exercised, misfit, np.nan)
    checks = []
    for i, muscle in enumerate(basis.muscles):
        fraction = float(outside[:, i].sum() / n_solved[i])
        values = unconstrained[solved[:, i], i]
        checks.append(MuscleCheck(
            muscle.name, muscle.region, fraction, float(excursion[:, i].max(initial=0.0)),
            float(excursion[outside[:, i], i].mean()) if outside[:, i].any() else 0.0,
            float(values.min()) if values.size else float("nan"), float(values.max()) if values.size else float("nan"),
            float(misfit[i]), bool(exercised[i]),
            bool(fraction > outside_threshold or (exercised[i] and misfit[i] > misfit_threshold)),
        ))
    rms = solution.rms_error_mm
    region_rms = {region: float(np.sqrt(np.nanmean(rms[:, r] ** 2))) for r, region in enumerate(REGIONS)}
    region_mean = {region: float(np.nanmean(solution.mean_error_mm[:, r])) for r, region in enumerate(REGIONS)}
    t = np.arange(len(displacements), dtype=float) if t is None else np.asarray(t, dtype=float)
    return BasisReport(tuple(checks), region_rms, region_mean, t, solution, (low, high))


def plot_report(report: BasisReport, path: str | Path, muscle_names: tuple[str, ...] | None = None) -> None:
    """Contraction curves (unconstrained, the band shaded) with the per-region marker error below; a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = muscle_names or tuple(m.name for m in report.muscles)
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(12, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    low, high = report.range
    top.axhspan(low, high, color="0.92", zorder=0)
    top.axhline(0, color="0.6", lw=0.5)
    top.axhline(1, color="0.6", lw=0.5)
    colors = plt.get_cmap("tab20")(np.linspace(0, 1, len(names)))
    for i, (name, check) in enumerate(zip(names, report.muscles)):
        top.plot(report.t, report.solution.unconstrained[:, i], lw=2.2 if check.flagged else 0.8,
                 color="crimson" if check.flagged else colors[i], label=name + (" (flagged)" if check.flagged else ""),
                 zorder=3 if check.flagged else 2)
    top.set_ylabel("unconstrained contraction")
    top.legend(fontsize=6, ncol=4, loc="upper right")
    flagged = ", ".join(report.flagged) + " flagged" if report.flagged else "no element flagged"
    top.set_title(f"basis check: {flagged}")
    for r, region in enumerate(REGIONS):
        bottom.plot(report.t, report.solution.rms_error_mm[:, r], lw=0.8, label=f"{region} face")
    bottom.set_ylabel("marker RMS (mm)")
    bottom.set_xlabel("time (s)")
    bottom.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
