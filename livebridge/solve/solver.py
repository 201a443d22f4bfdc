"""The streaming contraction solver: marker displacements -> muscle contractions, every frame.

Per frame the observed marker displacements ``d_hat (n_markers, 3)`` (model frame, mm, NaN rows for
markers not seen) give the contractions ``x (n_muscles,)`` minimising ``sum_j |d_hat_j - sum_i x_i d_ij|^2``
subject to ``0 <= x_i <= 1`` (``x_i >= 0`` with ``exaggerate``). ``d_ij`` is the displacement of face
marker ``j`` under basis element ``i`` (:meth:`MarkerSet.displacement_matrix`); head markers are ignored.

Region modes (:class:`SolverConfig`):

- ``"joint"``: all muscles from all visible face markers;
- ``"split"`` (Choe & Ko): upper-face muscles from upper-face markers only, lower from lower;
- ``"split-compensated"`` (default): each region's muscles from its own markers, after subtracting the
  displacement that the *other* region's current contractions predict at those markers; the two
  regions alternate (upper, then lower) for ``sweeps`` sweeps. The first sweep uses the other region's
  contractions of the previous frame, so at 60 fps the compensation starts close to converged.

Missing markers: when *every* marker of a region is missing, that region's muscles keep their previous
value and the result flags them (:attr:`SolveResult.held`); their unconstrained value is NaN.

Cost of a frame. One compiled kernel (numba, :func:`_frame`) does the whole frame: ``c = D^T d_hat`` per
marker set, the Gram matrices of the visible markers, the active-set steps of every region and sweep
(:func:`livebridge.qp.box_qp_kernel`, warm-started from the previous frame's working set) and the
marker errors. The Gram matrices with every marker visible are precomputed, so a frame with the usual
visibility costs one matrix-vector product plus the active-set steps. Any other visibility pattern costs
a rank-3 downdate per missing marker (``M x M`` flops each), which is cheaper than looking a cached
pattern up would be, so no pattern cache is kept;
markers dropping out at random make most patterns new anyway. Why compiled: the QPs are tiny (<= 16
variables), and with numpy and LAPACK wrappers the per-call overhead, not the arithmetic, was the cost.
The kernels are compiled the first time a solver is constructed (seconds, once per installation: numba
caches them on disk; a later process loads them in well under a second), never in the middle of a take.

Rank-deficient blocks (a muscle that no visible marker moves): each block's Gram matrix is factored once
per frame and sweep; when a Cholesky pivot ``L_ii^2`` falls below ``1e-9`` times the trace of the block's
all-visible Gram matrix, the block gets the Tikhonov term of :mod:`livebridge.qp` for the frame.
Every free-set pivot is at least the corresponding pivot of the whole matrix (conditioning on fewer
variables leaves more variance), so the one test up front covers every working set the active-set
method can visit, and the decision does not depend on the warm start.

The unconstrained contractions (:attr:`SolveResult.unconstrained`, the basis-validation signal) are each
region's last QP of the frame solved without bounds, with the same right-hand side: ``Q^-1 c`` for
``joint`` and for each region of ``split``; for ``split-compensated`` each region's least-squares
contractions given the other region's (bounded) contractions of the last sweep. A badly sculpted
element shows up there as contractions far outside [0, 1] that the bounds would otherwise hide.

The reference for tests and benchmarks, :class:`livebridge.bench.solver.ReferenceSolver`, solves the same
frame step for step with each block's QP solved by ``scipy.optimize.lsq_linear(method="bvls")`` instead of
the active-set kernel (it replaces :attr:`ContractionSolver.frame_kernel`); everything else (visibility,
compensation, unconstrained solve, marker errors) runs through the same compiled helpers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from livebridge.errors import InputError
from livebridge.face.basis import REGIONS, Basis
from livebridge.face.markers import MarkerSet
from livebridge.qp import FREE, KKT_TOLERANCE, RANK_TOLERANCE, SINGULAR, box_qp_kernel

MODES = ("split-compensated", "split", "joint")
MAX_SWEEPS = 100


@dataclass(frozen=True)
class SolverConfig:
    """Per-session solver options.

    Attributes
    ----------
    mode : {"split-compensated", "split", "joint"}
    exaggerate : bool
        Allow contractions above 1 (only ``x >= 0``).
    sweeps : int
        Alternations of the two regions in ``split-compensated`` mode.
    """

    mode: str = "split-compensated"
    exaggerate: bool = False
    sweeps: int = 2

    def __post_init__(self):
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {MODES}, got {self.mode!r}", field="mode")
        if not 1 <= int(self.sweeps) <= MAX_SWEEPS:  # each sweep is a solve per frame: a huge count never ends
            raise InputError(f"sweeps must be in 1..{MAX_SWEEPS}, got {self.sweeps}", field="sweeps")


@dataclass(frozen=True)
class SolverState:
    """What the solver carries from one frame to the next.

    Attributes
    ----------
    contractions : ndarray, shape (n_muscles,)
        The previous frame's contractions (start of the compensation, value of held muscles).
    active : ndarray of int8, shape (n_muscles,)
        The previous frame's working set per muscle: -1 at lower bound, +1 at upper bound, 0 free.
    frame : int
        Frames solved so far.
    """

    contractions: np.ndarray
    active: np.ndarray
    frame: int = 0


@dataclass(frozen=True)
class SolveResult:
    """The solver's output for one frame.

    Attributes
    ----------
    contractions : ndarray, shape (n_muscles,)
    unconstrained : ndarray, shape (n_muscles,)
        The same region mode solved without bounds (least squares): the basis-validation signal.
        NaN for held muscles.
    rms_error_mm : ndarray, shape (2,)
        Per marker region (``upper``, ``lower``): ``sqrt(mean_j |d_hat_j - d_j|^2)`` over the visible
        face markers of that region, mm; NaN when none is visible.
    mean_error_mm : ndarray, shape (2,)
        Per marker region: ``sum_j |d_hat_j - d_j| / n`` over its ``n`` visible face markers, mm.
    held : ndarray of bool, shape (n_muscles,)
        Muscles that kept their previous value because every marker of their region was missing.
    held_regions : tuple of str
        The regions held this frame.
    n_visible : int
        Face markers seen.
    iterations : int
        Active-set sub-problem solves this frame (all regions and sweeps).
    """

    contractions: np.ndarray
    unconstrained: np.ndarray
    rms_error_mm: np.ndarray
    mean_error_mm: np.ndarray
    held: np.ndarray
    held_regions: tuple[str, ...]
    n_visible: int
    iterations: int

    def rms_mm(self, region: str) -> float:
        """RMS marker error of ``region`` in mm."""
        return float(self.rms_error_mm[REGIONS.index(region)])


@dataclass(frozen=True, eq=False)
class TakeSolution:
    """The solver's output for a whole take (one row per frame).

    Attributes
    ----------
    contractions : ndarray, shape (n_frames, n_muscles)
    unconstrained : ndarray, shape (n_frames, n_muscles)
    rms_error_mm : ndarray, shape (n_frames, 2)
    mean_error_mm : ndarray, shape (n_frames, 2)
    held : ndarray of bool, shape (n_frames, n_muscles)
    iterations : ndarray of int, shape (n_frames,)
    state : SolverState
        The state after the last frame.
    """

    contractions: np.ndarray
    unconstrained: np.ndarray
    rms_error_mm: np.ndarray
    mean_error_mm: np.ndarray
    held: np.ndarray
    iterations: np.ndarray
    state: SolverState


# ------------------------------------------------------------------------------------------ compiled kernels
# Muscles are in the solver's internal order (grouped by region), so every block's muscles are a slice.
# Marker sets: 0 the upper-face markers, 1 the lower-face markers, 2 all face markers (joint).
ALL_MARKERS = 2


@njit(cache=True, nogil=True)
def _prepare(observed, face_index, marker_region, a, marker_gram, full_gram, d, visible, grams, c, counts):
    """Visibility, Gram matrices and right-hand sides ``D^T d`` of one frame, per marker set.

    Parameters
    ----------
    observed : ndarray, shape (n_markers, 3)
        Marker displacements, NaN rows for markers not seen.
    face_index : ndarray of int64, shape (n_face,)
        Rows of ``observed`` that are face markers.
    marker_region : ndarray of int64, shape (n_face,)
    a : ndarray, shape (n_face, 3, M)
        ``d_ij`` per face marker and coordinate (internal muscle order).
    marker_gram : ndarray, shape (n_face, M, M)
        Each marker's contribution ``D_j^T D_j`` to the Gram matrices.
    full_gram : ndarray, shape (3, M, M)
        Gram matrix of each marker set with every marker visible.
    d : ndarray, shape (n_face, 3)
        Output: face displacements, zero rows for unseen markers.
    visible : ndarray of bool, shape (n_face,)
        Output.
    grams : ndarray, shape (3, M, M)
        Output: Gram matrix of each marker set over its visible markers (downdated from ``full_gram``).
    c : ndarray, shape (3, M)
        Output: ``D^T d`` of each marker set.
    counts : ndarray of int64, shape (2,)
        Output: visible markers per region.
    """
    n_muscles = a.shape[2]
    for s in range(3):
        for m in range(n_muscles):
            c[s, m] = 0.0
            for n in range(n_muscles):
                grams[s, m, n] = full_gram[s, m, n]
    counts[0] = counts[1] = 0
    for j in range(len(face_index)):
        row, region = face_index[j], marker_region[j]
        total = observed[row, 0] + observed[row, 1] + observed[row, 2]
        visible[j] = total == total  # NaN in any coordinate: not seen
        if visible[j]:
            counts[region] += 1
            for k in range(3):
                value = observed[row, k]
                d[j, k] = value
                for m in range(n_muscles):
                    c[region, m] += a[j, k, m] * value
        else:
            d[j, 0] = d[j, 1] = d[j, 2] = 0.0
            for m in range(n_muscles):  # downdate: remove the marker's rank-3 contribution
                for n in range(n_muscles):
                    grams[region, m, n] -= marker_gram[j, m, n]
                    grams[ALL_MARKERS, m, n] -= marker_gram[j, m, n]
    for m in range(n_muscles):
        c[ALL_MARKERS, m] = c[0, m] + c[1, m]


@njit(cache=True, nogil=True)
def _block_system(grams, full_gram, c, x, plan, block):
    """Block ``block``'s QP: its Gram matrix ``Q_BB`` and right-hand side ``c_B - Q_BO x_O``.

    Parameters
    ----------
    grams, full_gram : ndarray, shape (3, M, M); c : ndarray, shape (3, M)
        As in :func:`_prepare`.
    x : ndarray, shape (M,)
        Current contractions (internal order); ``x_O`` are the compensated muscles'.
    plan : ndarray of int64, shape (2, 5)
        The frame's blocks (see :meth:`ContractionSolver._block_plans`).
    block : int

    Returns
    -------
    (gram, rhs, scale) : (ndarray (k, k), ndarray (k,), float)
        ``scale`` is the trace of the block's all-visible Gram matrix (it sets the tolerances).
    """
    marker_set, start, size = plan[block, 0], plan[block, 1], plan[block, 2] - plan[block, 1]
    gram, rhs = np.empty((size, size)), np.empty(size)
    scale = 0.0
    for i in range(size):
        scale += full_gram[marker_set, start + i, start + i]
        for j in range(size):
            gram[i, j] = grams[marker_set, start + i, start + j]
        value = c[marker_set, start + i]
        for m in range(plan[block, 3], plan[block, 4]):
            value -= grams[marker_set, start + i, m] * x[m]
        rhs[i] = value
    return gram, rhs, max(scale, 1e-300)


@njit(cache=True, nogil=True)
def _errors(d, visible, marker_region, a, x, counts, errors):
    """Per-region marker errors of the fit ``x`` (M,): ``errors[0]`` RMS, ``errors[1]`` mean, shape (2, 2), mm.

    ``d`` (n_face, 3) and ``a`` (n_face, 3, M) as in :func:`_prepare`; NaN for a region with no visible marker.
    """
    for region in range(2):
        errors[0, region] = errors[1, region] = 0.0
    for j in range(len(visible)):
        if visible[j]:
            squared = 0.0
            for k in range(3):
                residual = d[j, k]
                for m in range(len(x)):
                    residual -= a[j, k, m] * x[m]
                squared += residual * residual
            errors[0, marker_region[j]] += squared
            errors[1, marker_region[j]] += np.sqrt(squared)
    for region in range(2):
        if counts[region]:
            errors[0, region] = np.sqrt(errors[0, region] / counts[region])
            errors[1, region] /= counts[region]
        else:
            errors[0, region] = errors[1, region] = np.nan


@njit(cache=True, nogil=True)
def _frame(observed, face_index, marker_region, a, marker_gram, full_gram, perm, plans, plan_sizes, sweeps, upper,
           x_previous, active_previous, x_out, active_out, unconstrained_out, errors):
    """One frame of :meth:`ContractionSolver.step` with the active-set QP.

    Parameters
    ----------
    observed, face_index, marker_region, a, marker_gram, full_gram
        As in :func:`_prepare`.
    perm : ndarray of int64, shape (M,)
        Internal muscle ``i`` is external muscle ``perm[i]``.
    plans : ndarray of int64, shape (4, 2, 5); plan_sizes : ndarray of int64, shape (4,)
        The blocks to solve for each combination of regions without a visible marker
        (:meth:`ContractionSolver._block_plans`).
    sweeps : int
        Times the blocks are solved in turn (1 except in split-compensated mode).
    upper : float
        Upper bound of every contraction (``inf``: exaggeration).
    x_previous : ndarray, shape (M,); active_previous : ndarray of int8, shape (M,)
        The previous frame's contractions and working set (external order).
    x_out, active_out, unconstrained_out : ndarray, shape (M,)
        Outputs (external order).
    errors : ndarray, shape (2, 2)
        Output, as in :func:`_errors`.

    Returns
    -------
    (iterations, upper_seen, lower_seen) : (int, int, int)
        Sub-problem solves; visible markers per region.
    """
    n_face, n_muscles = len(face_index), len(perm)
    d, visible = np.empty((n_face, 3)), np.empty(n_face, np.bool_)
    grams, c, counts = np.empty((3, n_muscles, n_muscles)), np.empty((3, n_muscles)), np.empty(2, np.int64)
    _prepare(observed, face_index, marker_region, a, marker_gram, full_gram, d, visible, grams, c, counts)
    held_code = (counts[0] == 0) + 2 * (counts[1] == 0)
    plan, n_blocks = plans[held_code], plan_sizes[held_code]
    x, active, unconstrained = np.empty(n_muscles), np.empty(n_muscles, np.int8), np.empty(n_muscles)
    for i in range(n_muscles):
        x[i], active[i], unconstrained[i] = x_previous[perm[i]], active_previous[perm[i]], np.nan
    iterations = 0
    for sweep in range(sweeps):
        for block in range(n_blocks):
            gram, rhs, scale = _block_system(grams, full_gram, c, x, plan, block)
            start, size = plan[block, 1], len(rhs)
            low, high, zero, bound = np.empty(size), np.empty(size), np.empty(size), np.empty(size)
            for i in range(size):
                low[i], high[i], zero[i], bound[i] = -np.inf, np.inf, 0.0, upper
            working, solution = np.empty(size, np.int8), np.empty(size)
            ridge = False
            # Two stages, one call site (the kernel is big): 0, the block without bounds from the all-free
            # working set, whose Cholesky pivots are the rank test and whose solution is the unconstrained
            # one; 1, the bounded QP warm-started from the previous working set. A SINGULAR status adds the
            # ridge and repeats the stage (stage 1 only at the rounding edge of the test of stage 0).
            stage = 0
            while stage < 2:
                for i in range(size):
                    working[i] = FREE if stage == 0 else active[start + i]
                used, status = box_qp_kernel(gram, rhs, low if stage == 0 else zero, high if stage == 0 else bound,
                                             working, solution, KKT_TOLERANCE * scale * size,
                                             0.0 if ridge else RANK_TOLERANCE * scale, ridge,
                                             1 if stage == 0 else 10 * size + 20)
                if status == SINGULAR and ridge:
                    break  # cannot happen with a finite basis (Q + ridge I is positive definite): x is kept
                if status == SINGULAR:
                    ridge = True
                    for i in range(size):
                        gram[i, i] += RANK_TOLERANCE * scale
                    continue
                for i in range(size):
                    if stage == 0 and sweep == sweeps - 1:
                        unconstrained[start + i] = solution[i]
                    elif stage == 1:
                        x[start + i], active[start + i] = solution[i], working[i]
                iterations += used if stage == 1 else 0
                stage += 1
    _errors(d, visible, marker_region, a, x, counts, errors)
    for i in range(n_muscles):
        x_out[perm[i]], active_out[perm[i]], unconstrained_out[perm[i]] = x[i], active[i], unconstrained[i]
    return iterations, counts[0], counts[1]


class ContractionSolver:
    """Contractions from marker displacements for one basis and marker set.

    Parameters
    ----------
    basis : Basis
    markers : MarkerSet
        Face markers are used (their region from the marker set); head markers are ignored.
    config : SolverConfig, optional
    displacement : ndarray, shape (n_markers, n_muscles, 3), optional
        ``d_ij`` to use instead of ``markers.displacement_matrix(basis)`` (basis refinement solves with
        marker displacements that no mesh has yet).
    """

    # One frame: compiled, with the active-set QP of :mod:`livebridge.qp` (see :func:`_frame` for the
    # arguments); the benchmarks' reference solver replaces it with one that solves each QP with scipy.
    frame_kernel = staticmethod(_frame)

    def __init__(self, basis: Basis, markers: MarkerSet, config: SolverConfig | None = None,
                 displacement: np.ndarray | None = None):
        self.config = config or SolverConfig()
        self.basis = basis
        self.markers = markers
        self.muscle_names = basis.names
        n_muscles = self.n_muscles = basis.n_muscles
        self.n_markers = len(markers)
        self.face_index = np.flatnonzero(markers.face_mask).astype(np.int64)
        self.marker_region = np.array([REGIONS.index(markers.regions[i]) for i in self.face_index], dtype=np.int64)
        self.muscle_region = np.array([REGIONS.index(m.region) for m in basis.muscles], dtype=np.int64)
        # internal muscle order: grouped by region, so each region's muscles form a slice
        self._perm = np.argsort(self.muscle_region, kind="stable").astype(np.int64)
        self._region_bounds = np.searchsorted(self.muscle_region[self._perm], np.arange(len(REGIONS) + 1)).astype(
            np.int64)
        # d_ij of the face markers, (n_face, M, 3), external muscle order
        if displacement is None:
            displacement = markers.displacement_matrix(basis)
        elif np.shape(displacement) != (self.n_markers, n_muscles, 3):
            raise ValueError(f"displacement has shape {np.shape(displacement)}, "
                             f"expected {(self.n_markers, n_muscles, 3)}")
        self.displacement = np.asarray(displacement, dtype=np.float64)[self.face_index]
        if not np.isfinite(self.displacement).all():
            raise ValueError("marker displacements d_ij must be finite")
        # (n_face, 3, M): coordinate k of marker j under each muscle, internal order; reshaped, the rows of D
        self._a = np.ascontiguousarray(np.transpose(self.displacement[:, self._perm], (0, 2, 1)))
        self._marker_gram = np.ascontiguousarray(np.einsum("jkm,jkl->jml", self._a, self._a))  # (n_face, M, M)
        self._full_gram = np.ascontiguousarray(np.stack(  # (3, M, M): upper markers, lower markers, all
            [self._marker_gram[self.marker_region == r].sum(axis=0) for r in range(len(REGIONS))]
            + [self._marker_gram.sum(axis=0)]))
        self._plans, self._plan_sizes = self._block_plans()
        self._upper_bound = np.inf if self.config.exaggerate else 1.0
        self._sweeps = int(self.config.sweeps) if self.config.mode == "split-compensated" else 1
        self._shape = (self.n_markers, 3)
        self._held = [self._held_of(code) for code in range(4)]
        self.step(self.initial_state(), np.zeros(self._shape))  # compile (or load) the kernels now, not mid-take

    def _block_plans(self) -> tuple[np.ndarray, np.ndarray]:
        """The QPs ("blocks") of a frame for each combination of regions without a visible marker.

        Returns
        -------
        plans : ndarray of int64, shape (4, 2, 5)
            For held code ``h`` (bit ``r`` set: region ``r`` unseen, its muscles held), one row per block in
            solving order: marker set (0 upper, 1 lower, 2 all), muscle start and stop (internal order), and
            start and stop of the muscles whose predicted displacement is subtracted first (empty: none).
        sizes : ndarray of int64, shape (4,)
            Blocks per held code.
        """
        bounds = self._region_bounds.tolist()
        muscles = [(bounds[r], bounds[r + 1]) for r in range(len(REGIONS))]
        plans, sizes = np.zeros((4, 2, 5), np.int64), np.zeros(4, np.int64)
        for code in range(4):
            held = [bool(code >> r & 1) for r in range(len(REGIONS))]
            if self.config.mode == "joint":
                # every seen muscle from all visible markers (regions are contiguous); a held region's prediction
                # is subtracted
                kept = [muscles[r] for r in range(2) if not held[r]]
                others = [muscles[r] for r in range(2) if held[r]]
                blocks = [(ALL_MARKERS, kept[0][0], kept[-1][1], *(others[0] if len(others) == 1 else (0, 0)))] \
                    if kept and kept[-1][1] > kept[0][0] else []
            else:
                compensated = self.config.mode == "split-compensated"
                blocks = [(r, *muscles[r], *(muscles[1 - r] if compensated or held[1 - r] else (0, 0)))
                          for r in range(2) if not held[r] and muscles[r][1] > muscles[r][0]]
            plans[code, :len(blocks)] = blocks if blocks else 0
            sizes[code] = len(blocks)
        return plans, sizes

    def _held_of(self, code: int) -> tuple[np.ndarray, tuple[str, ...]]:
        """(held muscles (M,) bool, read-only; held region names) for bit r of ``code`` = region r unseen."""
        regions = tuple(name for r, name in enumerate(REGIONS) if code >> r & 1)
        held = np.isin(self.muscle_region, [REGIONS.index(name) for name in regions])
        held.flags.writeable = False  # shared by every result with this combination
        return held, regions

    # ------------------------------------------------------------------ state
    def initial_state(self) -> SolverState:
        """The state before the first frame: the neutral face, every muscle free."""
        return SolverState(np.zeros(self.n_muscles), np.zeros(self.n_muscles, dtype=np.int8), 0)

    # ------------------------------------------------------------------ solve
    def step(self, state: SolverState, displacements: np.ndarray) -> tuple[SolverState, SolveResult]:
        """Solve one frame.

        Parameters
        ----------
        state : SolverState
        displacements : ndarray, shape (n_markers, 3)
            Observed marker displacements in the model frame, mm; NaN rows for markers not seen.
            Head-marker rows are ignored.

        Returns
        -------
        (SolverState, SolveResult)
        """
        observed = np.ascontiguousarray(displacements, dtype=np.float64)
        if observed.shape != self._shape:
            raise ValueError(f"displacements have shape {observed.shape}, expected {self._shape}")
        n_muscles = self.n_muscles
        x, active, unconstrained = np.empty(n_muscles), np.empty(n_muscles, np.int8), np.empty(n_muscles)
        errors = np.empty((2, 2))
        x_previous = np.ascontiguousarray(state.contractions, dtype=np.float64)
        active_previous = np.ascontiguousarray(state.active, dtype=np.int8)
        iterations, upper_seen, lower_seen = self.frame_kernel(
            observed, self.face_index, self.marker_region, self._a, self._marker_gram, self._full_gram, self._perm,
            self._plans, self._plan_sizes, self._sweeps, self._upper_bound, x_previous, active_previous,
            x, active, unconstrained, errors)
        held, held_regions = self._held[(upper_seen == 0) + 2 * (lower_seen == 0)]
        result = SolveResult(x, unconstrained, errors[0], errors[1], held, held_regions, upper_seen + lower_seen,
                             iterations)
        return SolverState(x, active, state.frame + 1), result

    def solve_take(self, displacements: np.ndarray, state: SolverState | None = None,
                   progress: bool = False) -> TakeSolution:
        """Solve every frame of a take in order.

        Parameters
        ----------
        displacements : ndarray, shape (n_frames, n_markers, 3)
            NaN rows for markers not seen.
        state : SolverState, optional
            Default: :meth:`initial_state`.
        progress : bool
            Show a tqdm progress bar.

        Returns
        -------
        TakeSolution
        """
        displacements = np.asarray(displacements, dtype=np.float64)
        if displacements.ndim != 3 or displacements.shape[1:] != (self.n_markers, 3):
            raise InputError(f"displacements have shape {displacements.shape}, "
                             f"expected (n_frames, {self.n_markers}, 3)", field="displacements")
        n_frames = len(displacements)
        out = {
            "contractions": np.empty((n_frames, self.n_muscles)),
            "unconstrained": np.empty((n_frames, self.n_muscles)),
            "rms_error_mm": np.empty((n_frames, len(REGIONS))),
            "mean_error_mm": np.empty((n_frames, len(REGIONS))),
            "held": np.empty((n_frames, self.n_muscles), dtype=bool),
            "iterations": np.empty(n_frames, dtype=np.int64),
        }
        state = state or self.initial_state()
        frames = range(n_frames)
        if progress:
            from tqdm import tqdm

            frames = tqdm(frames, desc="solve", unit="frame", leave=False)
        for i in frames:
            state, result = self.step(state, displacements[i])
            out["contractions"][i] = result.contractions
            out["unconstrained"][i] = result.unconstrained
            out["rms_error_mm"][i] = result.rms_error_mm
            out["mean_error_mm"][i] = result.mean_error_mm
            out["held"][i] = result.held
            out["iterations"][i] = result.iterations
        return TakeSolution(state=state, **out)


def solve_take(basis: Basis, markers: MarkerSet, displacements: np.ndarray, config: SolverConfig | None = None,
               progress: bool = False) -> TakeSolution:
    """Solve a whole take from the neutral state: ``ContractionSolver(basis, markers, config).solve_take(...)``.

    Parameters
    ----------
    displacements : ndarray, shape (n_frames, n_markers, 3)
    """
    return ContractionSolver(basis, markers, config).solve_take(displacements, progress=progress)
