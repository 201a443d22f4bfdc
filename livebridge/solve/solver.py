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

Missing markers: ``Q`` (and its free-set factorisations) depend on which face markers are visible, so
one :class:`~livebridge.solve.qp.BoxQP` per region is built per visibility pattern and kept in a
least-recently-used cache. When *every* marker of a region is missing, that region's muscles keep their
previous value and the result flags them (:attr:`SolveResult.held`); their unconstrained value is NaN.

Cost of a frame: one matrix-vector product for ``c = D^T d_hat`` of both regions, the active-set steps
(usually one or two per region and sweep, warm-started from the previous frame's working set), one
product for the predicted marker displacements. A visibility pattern not in the cache costs, on top,
a rank-3 downdate of the all-visible Gram matrices per missing marker and one small Cholesky
factorisation per region (markers dropping out at random make most patterns new).

The unconstrained contractions (:attr:`SolveResult.unconstrained`, the basis-validation signal) are each
region's last QP of the frame solved without bounds, with the same right-hand side: ``Q^-1 c`` for
``joint`` and for each region of ``split``; for ``split-compensated`` each region's least-squares
contractions given the other region's (bounded) contractions of the last sweep. A badly sculpted
element shows up there as contractions far outside [0, 1] that the bounds would otherwise hide.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import REGIONS, Basis
from livebridge.face.markers import MarkerSet
from livebridge.solve.qp import BoxQP

MODES = ("split-compensated", "split", "joint")
BACKENDS = ("active-set", "scipy-bvls")


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
    cache_size : int
        Visibility patterns whose factorisations are kept.
    """

    mode: str = "split-compensated"
    exaggerate: bool = False
    sweeps: int = 2
    cache_size: int = 64

    def __post_init__(self):
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {MODES}, got {self.mode!r}", field="mode")
        if int(self.sweeps) < 1:
            raise InputError(f"sweeps must be >= 1, got {self.sweeps}", field="sweeps")
        if int(self.cache_size) < 1:
            raise InputError(f"cache_size must be >= 1, got {self.cache_size}", field="cache_size")


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

    def mean_mm(self, region: str) -> float:
        """Mean marker error of ``region`` in mm."""
        return float(self.mean_error_mm[REGIONS.index(region)])


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


@dataclass(frozen=True, eq=False)
class _BlockSpec:
    """One QP of a frame, independent of which markers are missing (beyond whole regions).

    Muscles are in the solver's internal order (grouped by region), so every index set is a slice.
    """

    region: int  # index into REGIONS; -1: all face markers (joint)
    muscles: slice  # muscles solved here, (k,)
    others: slice  # muscles whose prediction is subtracted when compensating, (M - k,)
    compensate: bool
    c_slice: slice  # where this block's D^T d lies in the per-frame product
    n_rows: int  # k
    marker_rows: np.ndarray  # (n_face, k, M): each marker's contribution to the Gram rows (0 outside the region)
    rows: np.ndarray  # (k, M): the Gram rows with every marker visible
    scale: float  # trace of the all-visible Gram matrix (bounds the trace of every pattern's)
    lower: float
    upper: float


@dataclass(frozen=True, eq=False)
class _SpecGroup:
    """The block specs of one held-region combination, stacked so a pattern's downdate is one product."""

    rows: np.ndarray  # (sum_b k_b M,): every block's all-visible Gram rows, flattened
    marker_rows: np.ndarray  # (n_face, sum_b k_b M): each marker's contribution, flattened the same way
    spans: list  # (start, stop) of each block in the flattened rows
    held: np.ndarray  # (M,) bool, external order
    held_internal: np.ndarray  # (M,) bool, internal order
    held_regions: tuple


@dataclass(eq=False)
class _Block:
    """One QP of a visibility pattern."""

    spec: _BlockSpec
    qp: BoxQP
    cross: np.ndarray  # (k, M - k): Q restricted to (muscles, others) over the visible rows


@dataclass(eq=False)
class _Pattern:
    """Everything that depends only on which face markers are visible."""

    visible: np.ndarray  # (n_face,) bool
    all_visible: bool
    blocks: list
    held: np.ndarray  # (M,) bool, external order
    held_internal: np.ndarray  # (M,) bool, internal order
    held_regions: tuple
    counts: np.ndarray  # (2,) visible markers per region


class ContractionSolver:
    """Contractions from marker displacements for one basis and marker set.

    Parameters
    ----------
    basis : Basis
    markers : MarkerSet
        Face markers are used (their region from the marker set); head markers are ignored.
    config : SolverConfig, optional
    backend : {"active-set", "scipy-bvls"}
        ``"active-set"`` is the product (:mod:`livebridge.solve.qp`); ``"scipy-bvls"`` solves each
        region's QP with ``scipy.optimize.lsq_linear(method="bvls")`` on the same rows instead, step
        for step (everything else shared): the reference for tests and benchmarks.
    displacement : ndarray, shape (n_markers, n_muscles, 3), optional
        ``d_ij`` to use instead of ``markers.displacement_matrix(basis)`` (basis refinement solves with
        marker displacements that no mesh has yet).
    """

    def __init__(self, basis: Basis, markers: MarkerSet, config: SolverConfig | None = None,
                 backend: str = "active-set", displacement: np.ndarray | None = None):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.config = config or SolverConfig()
        self.backend = backend
        self.basis = basis
        self.markers = markers
        self.muscle_names = basis.names
        n_muscles = self.n_muscles = basis.n_muscles
        self.n_markers = len(markers)
        self.face_index = np.flatnonzero(markers.face_mask)
        self._has_head = len(self.face_index) != self.n_markers
        n_face = len(self.face_index)
        n_regions = len(REGIONS)
        self.marker_region = np.array([REGIONS.index(markers.regions[i]) for i in self.face_index], dtype=int)
        self.muscle_region = np.array([REGIONS.index(m.region) for m in basis.muscles], dtype=int)
        # internal muscle order: grouped by region, so each region's muscles form a slice
        self._perm = np.argsort(self.muscle_region, kind="stable")
        self._inverse_perm = np.argsort(self._perm)
        self._permuted = not np.array_equal(self._perm, np.arange(n_muscles))
        region_sorted = self.muscle_region[self._perm]
        bounds = np.searchsorted(region_sorted, np.arange(n_regions + 1))
        self._region_slices = [slice(int(bounds[r]), int(bounds[r + 1])) for r in range(n_regions)]
        # d_ij of the face markers, (n_face, M, 3), external muscle order
        if displacement is None:
            displacement = markers.displacement_matrix(basis)
        elif np.shape(displacement) != (self.n_markers, n_muscles, 3):
            raise ValueError(f"displacement has shape {np.shape(displacement)}, "
                             f"expected {(self.n_markers, n_muscles, 3)}")
        self.displacement = np.asarray(displacement, dtype=np.float64)[self.face_index]
        internal = self.displacement[:, self._perm]
        # A (3 n_face, M): row 3j+k = coordinate k of marker j; internal muscle order
        self._a = np.ascontiguousarray(np.transpose(internal, (0, 2, 1)).reshape(3 * n_face, n_muscles))
        row_region = np.repeat(self.marker_region, 3)
        # per-frame products: split modes stack D_r^T d over each region's markers, (2 M,); joint D^T d, (M,)
        self._at_regions = np.ascontiguousarray(
            np.concatenate([self._a.T * (row_region == r) for r in range(n_regions)]))
        self._at = np.ascontiguousarray(self._a.T)
        self._region_onehot = np.stack([self.marker_region == r for r in range(n_regions)]).astype(float)
        self._marker_gram = np.einsum("jmk,jlk->jml", internal, internal)  # (n_face, M, M): D_j^T D_j
        self._upper_bound = np.inf if self.config.exaggerate else 1.0
        self._patterns: OrderedDict[bytes, _Pattern] = OrderedDict()
        self._specs: dict[tuple[bool, ...], list[_BlockSpec]] = {}
        self._spec_groups: dict[tuple[bool, ...], _SpecGroup] = {}
        self._sweeps = self.config.sweeps if self.config.mode == "split-compensated" else 1
        self._reference = backend != "active-set"
        self._shape = (self.n_markers, 3)
        self._ones3 = np.ones(3)

    # ------------------------------------------------------------------ state
    def initial_state(self) -> SolverState:
        """The state before the first frame: the neutral face, every muscle free."""
        return SolverState(np.zeros(self.n_muscles), np.zeros(self.n_muscles, dtype=np.int8), 0)

    # --------------------------------------------------------------- patterns
    def pattern(self, visible: np.ndarray) -> _Pattern:
        """The cached factorisations for a visibility mask of the face markers, shape (n_face,)."""
        key = visible.tobytes()
        hit = self._patterns.get(key)
        if hit is not None:
            self._patterns.move_to_end(key)
            return hit
        hit = self._build_pattern(visible)
        self._patterns[key] = hit
        if len(self._patterns) > self.config.cache_size:
            self._patterns.popitem(last=False)
        return hit

    def _build_pattern(self, visible: np.ndarray) -> _Pattern:
        counts = self._region_onehot @ visible
        held_key = (counts[0] == 0, counts[1] == 0)
        specs = self._specs.get(held_key)
        if specs is None:
            specs = self._specs[held_key] = self._block_specs(held_key)
        group = self._spec_groups[held_key]
        if visible.all():
            flat = group.rows
        else:
            # downdate the all-visible Gram rows by the missing markers' rank-3 contributions (one product)
            flat = group.rows - (1.0 - visible) @ group.marker_rows
        blocks = []
        for spec, (start, stop) in zip(specs, group.spans):
            rows = flat[start:stop].reshape(spec.n_rows, self.n_muscles)
            qp = BoxQP.internal(rows[:, spec.muscles], 0.0, self._upper_bound, spec.scale, self.config.cache_size)
            blocks.append(_Block(spec, qp, rows[:, spec.others]))
        return _Pattern(visible, bool(visible.all()), blocks, group.held, group.held_internal, group.held_regions,
                        counts)

    def _block_specs(self, held_key: tuple[bool, ...]) -> list[_BlockSpec]:
        """The QPs to solve when the regions flagged in ``held_key`` have no visible marker."""
        n_muscles = self.n_muscles
        everything = slice(0, n_muscles)
        empty = slice(0, 0)
        kept = [r for r, is_held in enumerate(held_key) if not is_held and self._region_slices[r].stop
                > self._region_slices[r].start]
        held_regions = [r for r, is_held in enumerate(held_key) if is_held]
        groups = []  # (marker region, muscles, others, compensate, c slice)
        if self.config.mode == "joint":
            if len(kept) == len(REGIONS):
                groups.append((-1, everything, empty, False, everything))
            elif kept:
                # one region's muscles from all visible markers; the held region's prediction subtracted
                muscles, others = self._region_slices[kept[0]], self._region_slices[held_regions[0]]
                groups.append((-1, muscles, others, True, muscles))
        else:
            compensate = self.config.mode == "split-compensated"
            for r in kept:
                muscles = self._region_slices[r]
                others = self._region_slices[1 - r]
                c_slice = slice(r * n_muscles + muscles.start, r * n_muscles + muscles.stop)
                groups.append((r, muscles, others, compensate or bool(held_key[1 - r]), c_slice))
        specs = []
        spans = []
        start = 0
        for region, muscles, others, compensate, c_slice in groups:
            in_rows = np.ones(len(self.face_index), dtype=bool) if region < 0 else self.marker_region == region
            marker_rows = np.ascontiguousarray(self._marker_gram[:, muscles, :] * in_rows[:, None, None])
            rows = marker_rows.sum(axis=0)
            n_rows = muscles.stop - muscles.start
            specs.append(_BlockSpec(region, muscles, others, compensate, c_slice, n_rows, marker_rows, rows,
                                    float(np.trace(rows[:, muscles])), 0.0, self._upper_bound))
            spans.append((start, start + n_rows * n_muscles))
            start += n_rows * n_muscles
        held_internal = np.zeros(n_muscles, dtype=bool)
        for r, is_held in enumerate(held_key):
            held_internal[self._region_slices[r]] = is_held
        n_face = len(self.face_index)
        self._spec_groups[held_key] = _SpecGroup(
            np.concatenate([spec.rows.ravel() for spec in specs]) if specs else np.zeros(0),
            np.concatenate([spec.marker_rows.reshape(n_face, -1) for spec in specs], axis=1)
            if specs else np.zeros((n_face, 0)),
            spans, held_internal[self._inverse_perm] if self._permuted else held_internal, held_internal,
            tuple(region for region, h in zip(REGIONS, held_key) if h))
        return specs

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
        observed = np.asarray(displacements, dtype=np.float64)
        if observed.shape != self._shape:
            raise ValueError(f"displacements have shape {observed.shape}, expected {self._shape}")
        face = observed[self.face_index] if self._has_head else observed
        row_sums = face @ self._ones3
        visible = row_sums == row_sums  # NaN in any coordinate: not seen
        pattern = self._patterns.get(visible.tobytes())
        if pattern is None:
            pattern = self.pattern(visible)
        d0 = face.ravel() if pattern.all_visible else np.where(visible[:, None], face, 0.0).ravel()
        joint = self.config.mode == "joint"
        c_all = (self._at if joint else self._at_regions) @ d0
        if self._permuted:
            x = state.contractions[self._perm]
            active = state.active[self._perm]
        else:
            x = state.contractions.copy()
            active = state.active.copy()
        reference = self._reference
        iterations = 0
        last = self._sweeps - 1
        unconstrained = np.full(self.n_muscles, np.nan)
        for sweep in range(self._sweeps):
            for block in pattern.blocks:
                spec = block.spec
                c = c_all[spec.c_slice]
                if spec.compensate:
                    c = c - block.cross @ x[spec.others]
                if sweep == last:
                    unconstrained[spec.muscles] = block.qp.unconstrained(c)
                if reference:
                    x[spec.muscles] = self._reference_block(pattern, spec, d0, x)
                    iterations += 1
                else:
                    x_block, working, used, _ = block.qp.solve_raw(c, active[spec.muscles])
                    x[spec.muscles] = x_block
                    active[spec.muscles] = working
                    iterations += used
        residual = d0 - self._a @ x
        squared = ((residual * residual).reshape(-1, 3) @ self._ones3) * visible
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(self._region_onehot @ squared / pattern.counts)
            mean = self._region_onehot @ np.sqrt(squared) / pattern.counts
        if self._permuted:
            x, active, unconstrained = x[self._inverse_perm], active[self._inverse_perm], \
                unconstrained[self._inverse_perm]
        result = SolveResult(x, unconstrained, rms, mean, pattern.held, pattern.held_regions,
                             int(pattern.counts.sum()), iterations)
        return SolverState(x, active, state.frame + 1), result

    def _reference_block(self, pattern: _Pattern, spec: _BlockSpec, d0: np.ndarray, x: np.ndarray) -> np.ndarray:
        """One region's QP by ``scipy.optimize.lsq_linear(method="bvls")`` on the block's visible rows."""
        from scipy.optimize import lsq_linear

        in_rows = pattern.visible if spec.region < 0 else pattern.visible & (self.marker_region == spec.region)
        rows = np.flatnonzero(np.repeat(in_rows, 3))
        a_rows = self._a[rows]
        target = d0[rows]
        if spec.compensate:
            target = target - a_rows[:, spec.others] @ x[spec.others]
        return lsq_linear(a_rows[:, spec.muscles], target, bounds=(spec.lower, spec.upper), method="bvls").x

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
