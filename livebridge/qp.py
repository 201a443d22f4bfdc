"""A primal active-set solver for box-constrained least squares over a precomputed Gram matrix.

The contraction solve of one frame is ``min_x |D x - d|^2`` subject to ``lower <= x <= upper``
(``upper`` may be ``+inf``: exaggeration). Written with ``Q = D^T D`` and ``c = D^T d`` that is the
convex quadratic programme

    minimise   1/2 x^T Q x - c^T x      subject to   lower <= x <= upper.

``Q`` depends only on the basis and on which markers are visible; a frame supplies ``c`` and the
previous frame's working set. :class:`BoxQP` is the checked Python interface for one ``Q``; the
contraction solver calls the compiled kernel :func:`box_qp_kernel` directly from its own per-frame
kernel (:mod:`livebridge.solve.solver`), and the label tracker's face-model check calls
:func:`nonnegative_least_squares` (:mod:`livebridge.reconstruct.track`): the module sits at the top of the
package so that neither stage imports the other.

Algorithm (primal active set, exact KKT termination)
----------------------------------------------------
The working set ``W`` marks each variable as held at its lower bound (-1), at its upper bound (+1)
or free (0). Starting from a feasible point with the bound variables on their bounds:

1. Solve the equality-constrained sub-problem on the free set ``F``:
   ``Q_FF z = c_F - Q_FB x_B`` (Cholesky factorisation of ``Q_FF``).
2. If ``z`` is inside the box, take it. Then the gradient ``g = Q x - c`` gives the Lagrange
   multipliers of the bound variables: a variable at its lower bound needs ``g_i >= 0`` and one at
   its upper bound ``g_i <= 0``. If every multiplier has the right sign (to a tolerance of
   ``1e-11 n trace(Q)``) ``x`` satisfies the KKT conditions and, ``Q`` being positive
   (semi-)definite, it is the global minimum: stop. Otherwise free the most violating variable.
3. If ``z`` leaves the box, move from ``x`` towards ``z`` as far as the box allows and add the
   variables that hit a bound to the working set.

Warm start: the previous frame's working set is only a guess, so the solver first makes up to
three *block exchanges* (as in block principal pivoting, Kim & Park 2011): solve the sub-problem,
then at once put every free variable outside the box on the bound it crossed and free every bound
variable whose multiplier has the wrong sign. A sub-problem solution that is inside the box with
correct multipliers satisfies the KKT conditions and is returned. Otherwise the point is clipped
into the box (bound variables on their bounds) and the monotone primal method above takes over,
which guarantees termination. With 60 fps input the exchanges usually finish in one or two solves.

The objective falls strictly at every step that moves, so no working set can come back and the
method terminates in a finite number of steps. A working set that does come back can only do so
through rounding (multipliers at the level of the round-off); the solver then stops, optimal to
working precision.

Rank-deficient ``Q`` (a muscle no visible marker sees, two elements that move the visible markers
alike): the minimiser is then not unique and ``Q_FF`` may be singular. :class:`BoxQP` adds a
Tikhonov term ``lambda I`` with ``lambda = 1e-9 trace(Q)`` when the Cholesky factorisation of ``Q``
fails or LAPACK's reciprocal condition estimate (``dpocon``) is below ``1e-9`` (and
:attr:`BoxQP.ridge` says so), or later, when a free-set factor has a pivot ``L_ii^2`` below
``1e-9 trace(Q)``; every sub-problem solve then gets one step of iterative refinement. This makes
the problem strictly convex, picks among the minimisers the one of smallest norm (to first order),
and changes the objective by at most ``lambda |x|^2``, far below any measurement noise; well-posed
problems are solved without any regularisation, exactly.

Why compiled: the problems are tiny (n <= 16, a few hundred flops per sub-problem), so with numpy
and LAPACK wrappers the Python call overhead was the whole cost. The kernel refactors ``Q_FF`` for
every working set it visits instead of caching factors: a 10 x 10 Cholesky (a fraction of a
microsecond) costs about what the cache lookup did. The kernel is compiled on first use and cached on
disk by numba (``cache=True``), so the compile (seconds) is paid once per installation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.linalg import lapack

RANK_TOLERANCE = 1e-9  # pivot / reciprocal condition number below which Q counts as rank-deficient
KKT_TOLERANCE = 1e-11  # multiplier sign test, relative to the problem's scale
AT_LOWER, FREE, AT_UPPER = -1, 0, 1
EXCHANGES = 3  # block-exchange steps from the warm start before the monotone method
CONVERGED, ITERATION_LIMIT, SINGULAR = 0, 1, 2  # status codes of box_qp_kernel


@dataclass(frozen=True)
class QPResult:
    """The solution of one box-constrained QP.

    Attributes
    ----------
    x : ndarray, shape (n,)
    active : ndarray of int8, shape (n,)
        Working set at the solution: -1 at lower bound, +1 at upper bound, 0 free.
    iterations : int
        Sub-problem solves used.
    converged : bool
        False only if the iteration limit was hit (never observed; kept as a guard).
    """

    x: np.ndarray
    active: np.ndarray
    iterations: int
    converged: bool


# ---------------------------------------------------------------------------------------- compiled kernel
# One function on purpose: numba links every callee into each caller and optimises and compiles it again
# there, so helpers multiply the first-call compile time (it was ~3x with the steps split into functions).
@njit(cache=True, nogil=True)
def box_qp_kernel(gram, c, lower, upper, working, x, tolerance, pivot_floor, refine, max_iterations):
    """Solve ``min 1/2 x^T Q x - c^T x`` s.t. ``lower <= x <= upper``, warm-started from ``working``.

    With ``lower = -inf``, ``upper = inf`` and an all-free working set this is one Cholesky solve,
    ``x = Q^-1 c``, and a ``SINGULAR`` status is the rank test of ``Q``.

    Parameters
    ----------
    gram : ndarray, shape (n, n)
        ``Q`` (symmetric; with the ridge already added when ``refine``).
    c, lower, upper : ndarray, shape (n,)
    working : ndarray of int8, shape (n,)
        In: the starting working set (entries outside -1..1, and +-1 on an infinite bound, read as free).
        Out: the working set at the solution.
    x : ndarray, shape (n,)
        Output.
    tolerance : float
        Multiplier sign test (``KKT_TOLERANCE n trace(Q)``).
    pivot_floor : float
        Smallest acceptable free-set Cholesky pivot ``L_ii^2``; below it the kernel stops with ``SINGULAR``.
    refine : bool
        One step of iterative refinement in every sub-problem solve.
    max_iterations : int
        Sub-problem solves allowed.

    Returns
    -------
    (iterations, status) : (int, int)
        ``status`` is ``CONVERGED``, ``ITERATION_LIMIT`` or ``SINGULAR`` (``x`` undefined: regularise and
        call again).
    """
    n = len(c)
    index, factor = np.empty(n, np.int64), np.empty((n, n))
    z, rhs, step, violation = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    seen = np.empty((max(max_iterations, 0), n), np.int8)  # working sets left by freeing a variable (phase 2)
    n_seen = 0
    for i in range(n):  # a feasible start: bound variables on their bounds, free ones clipped from 0
        if not (working[i] == AT_LOWER and lower[i] > -np.inf or working[i] == AT_UPPER and upper[i] < np.inf):
            working[i] = FREE
        x[i] = lower[i] if working[i] == AT_LOWER else upper[i] if working[i] == AT_UPPER else \
            min(max(0.0, lower[i]), upper[i])
    if n == 0:
        return 0, CONVERGED
    for iteration in range(1, max_iterations + 1):
        exchanging = iteration <= EXCHANGES  # phase 1: block exchanges; phase 2: monotone primal steps
        # -- the sub-problem on the free set F: Q_FF z = c_F - Q_FB x_B
        n_free = 0
        for i in range(n):
            if working[i] == FREE:
                index[n_free] = i
                n_free += 1
        for j in range(n_free):  # Cholesky factor L of Q_FF, column by column
            pivot = gram[index[j], index[j]]
            for k in range(j):
                pivot -= factor[j, k] * factor[j, k]
            if not (pivot > 0.0 and pivot >= pivot_floor):
                return iteration, SINGULAR
            factor[j, j] = np.sqrt(pivot)
            for i in range(j + 1, n_free):
                value = gram[index[i], index[j]]
                for k in range(j):
                    value -= factor[i, k] * factor[j, k]
                factor[i, j] = value / factor[j, j]
        for t in range(n_free):
            value = c[index[t]]
            for j in range(n):
                if working[j] != FREE:
                    value -= gram[index[t], j] * x[j]
            rhs[t], z[t] = value, 0.0
        for _ in range(2 if refine else 1):  # solve for the residual of z; a second pass refines z
            for t in range(n_free):
                value = rhs[t]
                for s in range(n_free):
                    value -= gram[index[t], index[s]] * z[s]
                step[t] = value
            for t in range(n_free):  # L y = r, then L^T d = y, in place
                for k in range(t):
                    step[t] -= factor[t, k] * step[k]
                step[t] /= factor[t, t]
            for t in range(n_free - 1, -1, -1):
                for k in range(t + 1, n_free):
                    step[t] -= factor[k, t] * step[k]
                step[t] /= factor[t, t]
            for t in range(n_free):
                z[t] += step[t]
        outside = False
        for t in range(n_free):
            outside = outside or z[t] < lower[index[t]] or z[t] > upper[index[t]]
        if outside and not exchanging:
            # -- primal step towards z, as far as the box allows; blocking variables join the working set
            alpha = np.inf
            for t in range(n_free):
                i = index[t]
                step[t] = np.inf  # the step length at which variable i reaches the bound z crosses
                if z[t] < lower[i]:
                    step[t] = max((lower[i] - x[i]) / (z[t] - x[i]), 0.0)
                elif z[t] > upper[i]:
                    step[t] = max((upper[i] - x[i]) / (z[t] - x[i]), 0.0)
                alpha = min(alpha, step[t])
            for t in range(n_free):
                i = index[t]
                blocking = step[t] <= alpha
                x[i] += alpha * (z[t] - x[i])
                if blocking and z[t] < lower[i]:
                    working[i], x[i] = AT_LOWER, lower[i]
                elif blocking:
                    working[i], x[i] = AT_UPPER, upper[i]
            continue
        for t in range(n_free):
            x[index[t]] = z[t]
        # -- Lagrange multipliers of the bound variables: working_i (Q x - c)_i > 0 is a wrong sign
        worst = -1
        for i in range(n):
            violation[i] = -np.inf
            if working[i] != FREE:
                gradient = -c[i]
                for j in range(n):
                    gradient += gram[i, j] * x[j]
                violation[i] = working[i] * gradient
                if worst < 0 or violation[i] > violation[worst]:
                    worst = i
        if not outside and (worst < 0 or violation[worst] <= tolerance):
            return iteration, CONVERGED  # the KKT conditions hold
        if exchanging:
            # -- block exchange: free every wrongly signed variable, bind every free one outside the box
            for i in range(n):
                if violation[i] > tolerance:
                    working[i] = FREE  # x keeps the bound value: x stays feasible for phase 2
            for t in range(n_free):
                i = index[t]
                if z[t] < lower[i]:
                    working[i], x[i] = AT_LOWER, lower[i]
                elif z[t] > upper[i]:
                    working[i], x[i] = AT_UPPER, upper[i]
            continue
        # -- primal: z is inside the box but a multiplier is wrong: free the worst variable
        for r in range(n_seen):
            same = True
            for i in range(n):
                same = same and seen[r, i] == working[i]
            if same:
                # a working set seen before can only come back through rounding (the objective falls
                # strictly otherwise): x is then optimal to working precision
                return iteration, CONVERGED
        for i in range(n):
            seen[n_seen, i] = working[i]
        n_seen += 1
        working[worst] = FREE
    return max_iterations, ITERATION_LIMIT


def nonnegative_least_squares(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``argmin |D x - d|^2`` subject to ``x >= 0``, from ``gram = D^T D (n, n)`` and ``rhs = D^T d (n,)``.

    The compiled active-set kernel, cold-started; a rank-deficient ``gram`` gets the ridge of
    :class:`BoxQP` (the smallest-norm minimiser, to first order), as scipy's ``nnls`` would not.
    """
    gram = np.ascontiguousarray(gram, dtype=np.float64)
    rhs = np.ascontiguousarray(rhs, dtype=np.float64)
    n = len(rhs)
    scale = max(float(np.trace(gram)), 1e-300)
    lower, upper = np.zeros(n), np.full(n, np.inf)
    x, working = np.empty(n), np.zeros(n, np.int8)
    _, status = box_qp_kernel(gram, rhs, lower, upper, working, x, KKT_TOLERANCE * scale * max(n, 1),
                              RANK_TOLERANCE * scale, False, 10 * n + 20)
    if status == SINGULAR:
        working[:] = 0
        box_qp_kernel(gram + RANK_TOLERANCE * scale * np.eye(n), rhs, lower, upper, working, x,
                      KKT_TOLERANCE * scale * max(n, 1), 0.0, True, 10 * n + 20)
    return x


# ----------------------------------------------------------------------------------------- Python interface
class BoxQP:
    """``min 1/2 x^T Q x - c^T x`` s.t. ``lower <= x <= upper`` for one fixed ``Q`` and box.

    Parameters
    ----------
    gram : ndarray, shape (n, n)
        ``Q = D^T D``, symmetric positive semi-definite.
    lower, upper : float or ndarray, shape (n,)
        Finite lower bounds; upper bounds (``inf`` allowed), ``lower <= upper``.
    """

    def __init__(self, gram: np.ndarray, lower, upper):
        gram = np.asarray(gram, dtype=np.float64)
        if gram.ndim != 2 or gram.shape[0] != gram.shape[1]:
            raise ValueError(f"gram must be square, got shape {gram.shape}")
        n = self.n = len(gram)
        self.gram = np.ascontiguousarray(0.5 * (gram + gram.T))
        self.lower = np.array(np.broadcast_to(np.asarray(lower, dtype=np.float64), (n,)))  # own, writable copies
        self.upper = np.array(np.broadcast_to(np.asarray(upper, dtype=np.float64), (n,)))
        if not np.isfinite(self.lower).all() or np.isnan(self.upper).any() or (self.upper < self.lower).any():
            raise ValueError("bounds must satisfy finite lower <= upper")
        self.scale = max(float(self.gram.trace()), 1e-300)
        self._tolerance = KKT_TOLERANCE * self.scale * max(n, 1)
        self._pivot_floor = RANK_TOLERANCE * self.scale
        self.ridge = 0.0
        if n:  # decide up front whether Q is rank-deficient
            factor, info = lapack.dpotrf(self.gram)
            if info == 0:
                rcond, info = lapack.dpocon(factor, n * self.scale)
            if info != 0 or rcond < RANK_TOLERANCE:
                self._regularise()

    def _regularise(self) -> None:
        """Add the Tikhonov term ``1e-9 trace(Q) I`` (see the module docstring)."""
        self.ridge = RANK_TOLERANCE * self.scale
        self.gram = self.gram + self.ridge * np.eye(self.n)
        self._pivot_floor = 0.0

    @property
    def rank_deficient(self) -> bool:
        """True once the Tikhonov term has been added."""
        return self.ridge > 0.0

    def unconstrained(self, c: np.ndarray) -> np.ndarray:
        """The minimiser without bounds, ``Q^-1 c`` (regularised as described when ``Q`` is singular), shape (n,)."""
        unbounded = np.full(self.n, np.inf)
        return self._run(self._check(c), -unbounded, unbounded, np.zeros(self.n, np.int8), 1).x

    def solve(self, c: np.ndarray, active: np.ndarray | None = None,
              max_iterations: int | None = None) -> QPResult:
        """Solve for one right-hand side, warm-started from a working set.

        Parameters
        ----------
        c : ndarray, shape (n,)
            ``D^T d``.
        active : ndarray of int8, shape (n,), optional
            Starting working set (-1 lower, 0 free, +1 upper), e.g. the previous frame's; default: all
            free. ``+1`` on an infinite upper bound is read as free.
        max_iterations : int, optional
            Sub-problem solves allowed; default ``10 n + 20``.

        Returns
        -------
        QPResult
        """
        c = self._check(c)
        start = np.zeros(self.n, dtype=np.int8) if active is None else np.array(active, dtype=np.int8)
        if start.shape != (self.n,):
            raise ValueError(f"active has shape {start.shape}, expected {(self.n,)}")
        limit = 10 * self.n + 20 if max_iterations is None else int(max_iterations)
        return self._run(c, self.lower, self.upper, start, limit)

    def _run(self, c, lower, upper, start, limit) -> QPResult:
        """:func:`box_qp_kernel` from the working set ``start`` (n,), regularising ``Q`` if it turns out singular."""
        while True:
            working, x = start.copy(), np.empty(self.n)
            iterations, status = box_qp_kernel(self.gram, c, lower, upper, working, x, self._tolerance,
                                               self._pivot_floor, self.rank_deficient, limit)
            if status != SINGULAR:
                return QPResult(x, working, iterations, status == CONVERGED)
            if self.rank_deficient:
                raise ValueError("Cholesky factorisation failed on a regularised Gram matrix")
            self._regularise()

    def _check(self, c) -> np.ndarray:
        c = np.ascontiguousarray(c, dtype=np.float64)
        if c.shape != (self.n,):
            raise ValueError(f"c has shape {c.shape}, expected {(self.n,)}")
        return c
