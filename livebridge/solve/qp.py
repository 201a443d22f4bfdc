"""A primal active-set solver for box-constrained least squares over a precomputed Gram matrix.

The contraction solve of one frame is ``min_x |D x - d|^2`` subject to ``lower <= x <= upper``
(``upper`` may be ``+inf``: exaggeration). Written with ``Q = D^T D`` and ``c = D^T d`` that is the
convex quadratic programme

    minimise   1/2 x^T Q x - c^T x      subject to   lower <= x <= upper.

``Q`` depends only on the basis and on which markers are visible, so :class:`BoxQP` is built once
per visibility pattern; a frame supplies only ``c`` and the previous frame's active set.

Algorithm (primal active set, exact KKT termination)
----------------------------------------------------
The working set ``W`` marks each variable as held at its lower bound (-1), at its upper bound (+1)
or free (0). Starting from a feasible point with the bound variables on their bounds:

1. Solve the equality-constrained sub-problem on the free set ``F``:
   ``Q_FF z = c_F - Q_FB x_B`` (LAPACK Cholesky, ``dpotrf``/``dpotrs``).
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
method terminates in a finite number of steps; warm-started from the previous frame's working set
it usually needs one or two. A working set that does come back can only do so through rounding
(multipliers at the level of the round-off); the solver then stops, optimal to working precision.

Rank-deficient ``Q`` (a muscle no visible marker sees, two elements that move the visible markers
alike): the minimiser is then not unique and ``Q_FF`` may be singular. When the Cholesky
factorisation of ``Q`` fails or LAPACK's reciprocal condition estimate (``dpocon``) is below
``1e-9``, a Tikhonov term ``lambda I`` with ``lambda = 1e-9 * max(diag(Q))`` is added (and
:attr:`BoxQP.ridge` says so); every sub-problem solve then gets one step of iterative refinement. This makes the
problem strictly convex, picks among the minimisers the one of smallest norm (to first order), and
changes the objective by at most ``lambda |x|^2``, far below any measurement noise; well-posed
problems are solved without any regularisation, exactly.

Everything that depends only on the working set (the free-set Cholesky factor, the bound
variables' contribution to the right-hand side and to the gradient) is cached per working set
(first in, first out), so an exchange step costs one triangular solve pair and one small
matrix-vector product; the code avoids every per-call allocation it can, because the problems are
tiny (n <= 16) and Python overhead, not arithmetic, is the cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

RANK_TOLERANCE = 1e-9  # reciprocal condition number below which Q counts as rank-deficient
KKT_TOLERANCE = 1e-11  # multiplier sign test, relative to the problem's scale
AT_LOWER, FREE, AT_UPPER = -1, 0, 1
EXCHANGES = 3  # block-exchange steps from the warm start before the monotone method


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


class _Singular(Exception):
    """A free-set sub-matrix turned out (numerically) singular: regularise and start again."""


class BoxQP:
    """``min 1/2 x^T Q x - c^T x`` s.t. ``lower <= x <= upper`` for one fixed ``Q`` and box.

    Parameters
    ----------
    gram : ndarray, shape (n, n)
        ``Q = D^T D``, symmetric positive semi-definite.
    lower, upper : float or ndarray, shape (n,)
        Finite lower bounds; upper bounds (``inf`` allowed), ``lower <= upper``. Scalars (the same
        box for every variable, as for contractions) take a faster path.
    cache_size : int
        Working sets whose factorisations are kept.
    """

    def __init__(self, gram: np.ndarray, lower, upper, cache_size: int = 64):
        gram = np.asarray(gram, dtype=np.float64)
        if gram.ndim != 2 or gram.shape[0] != gram.shape[1]:
            raise ValueError(f"gram must be square, got shape {gram.shape}")
        n = len(gram)
        gram = 0.5 * (gram + gram.T)
        if np.ndim(lower) == 0 and np.ndim(upper) == 0:
            low0, high0, lower_array, upper_array = float(lower), float(upper), None, None
            if not (np.isfinite(low0) and low0 <= high0):
                raise ValueError("bounds must satisfy finite lower <= upper")
        else:
            low0 = high0 = None
            lower_array = np.broadcast_to(np.asarray(lower, dtype=np.float64), (n,)).copy()
            upper_array = np.broadcast_to(np.asarray(upper, dtype=np.float64), (n,)).copy()
            if not np.isfinite(lower_array).all() or np.isnan(upper_array).any() or (upper_array < lower_array).any():
                raise ValueError("bounds must satisfy finite lower <= upper")
        self._setup(gram, low0, high0, float(gram.trace()), cache_size)
        self._lower, self._upper = lower_array, upper_array
        if n:  # decide up front whether Q is rank-deficient (internal callers find out lazily)
            factor, info = lapack.dpotrf(gram)
            if info == 0:
                rcond, info = lapack.dpocon(factor, n * self.scale)
            if info != 0 or rcond < RANK_TOLERANCE:
                self._regularise()

    @classmethod
    def internal(cls, gram: np.ndarray, low0: float, high0: float, scale: float, cache_size: int = 64) -> BoxQP:
        """A QP for a Gram matrix the caller built (symmetric, shape (n, n)) and a uniform box, without checks.

        Rank deficiency is detected lazily, when a free-set factorisation has a tiny pivot.
        ``scale`` is an upper bound of ``trace(Q)`` (it sets the tolerances).
        """
        qp = cls.__new__(cls)
        qp._setup(gram, low0, high0, scale, cache_size)
        qp._lower = qp._upper = None
        return qp

    def _setup(self, gram, low0, high0, scale, cache_size):
        n = len(gram)
        self.n = n
        self.gram = gram
        self._low0, self._high0 = low0, high0
        self.scale = max(scale, 1e-300)
        self._tolerance = KKT_TOLERANCE * self.scale * max(n, 1)
        self._pivot_floor = RANK_TOLERANCE * self.scale
        self.ridge = 0.0
        self._entries: dict[bytes, tuple] = {}
        self._cache_size = int(cache_size)
        self._all_free = np.zeros(n, dtype=np.int8)
        self._all_free_key = self._all_free.tobytes()
        self._all_index = np.arange(n)

    def _regularise(self) -> None:
        """Add the Tikhonov term ``1e-9 trace(Q) I`` (see the module docstring) and forget the factorisations."""
        self.ridge = RANK_TOLERANCE * self.scale
        self.gram = self.gram + self.ridge * np.eye(self.n)
        self._pivot_floor = 0.0
        self._entries = {}

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds, shape (n,)."""
        if self._lower is None:
            self._lower = np.full(self.n, self._low0)
        return self._lower

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds, shape (n,)."""
        if self._upper is None:
            self._upper = np.full(self.n, self._high0)
        return self._upper

    @property
    def rank_deficient(self) -> bool:
        """True once the Tikhonov term has been added."""
        return self.ridge > 0.0

    def _entry(self, working: np.ndarray, key: bytes) -> tuple:
        """What depends only on the working set (n,): ``(index (f,), Cholesky factor of Q_FF (f, f), Q_FF,
        Q[:, F] (n, f), Q x_B (n,) or None, (Q x_B)_F (f,) or None, x_B (n,) with zeros at the free
        variables)``."""
        gram = self.gram
        if key == self._all_free_key:
            index, sub = self._all_index, gram
        else:
            index = (working == FREE).nonzero()[0]
            sub = gram.take(index, 0).take(index, 1)
        if len(index):
            factor, info = lapack.dpotrf(sub)
            if info != 0 or min(factor.diagonal().tolist()) ** 2 < self._pivot_floor:
                if self.ridge:
                    raise ValueError(f"Cholesky factorisation failed on free set {index}")
                raise _Singular
        else:
            factor = sub
        if self._low0 == 0.0:
            if b"\x01" in key:  # a variable at its upper bound
                bound_values = (working == AT_UPPER) * self._high0
            else:
                bound_values = None
        else:
            bound_values = np.where(working == AT_LOWER, self.lower, np.where(working == AT_UPPER, self.upper, 0.0))
        if bound_values is None:
            base = offset = None
            bound_values = np.zeros(self.n)
        else:
            base = gram @ bound_values
            offset = base.take(index)
        entry = (index, factor, sub, sub if sub is gram else gram.take(index, 1), base, offset, bound_values)
        if len(self._entries) >= self._cache_size:
            self._entries.pop(next(iter(self._entries)))
        self._entries[key] = entry
        return entry

    def _get(self, working: np.ndarray) -> tuple:
        key = working.tobytes()
        entry = self._entries.get(key)
        return entry if entry is not None else self._entry(working, key)

    def _sub_solve(self, factor: np.ndarray, sub: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        z = lapack.dpotrs(factor, rhs)[0]
        if self.ridge:
            z = z + lapack.dpotrs(factor, rhs - sub @ z)[0]  # one step of iterative refinement
        return z

    def unconstrained(self, c: np.ndarray) -> np.ndarray:
        """The minimiser without bounds, ``Q^-1 c`` (regularised as described when ``Q`` is singular), shape (n,)."""
        if not self.n:
            return np.zeros(0)
        try:
            entry = self._get(self._all_free)
        except _Singular:
            self._regularise()
            entry = self._get(self._all_free)
        return self._sub_solve(entry[1], entry[2], c)

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

        Returns
        -------
        QPResult
        """
        c = np.asarray(c, dtype=np.float64)
        if c.shape != (self.n,):
            raise ValueError(f"c has shape {c.shape}, expected {(self.n,)}")
        working = np.zeros(self.n, dtype=np.int8) if active is None else np.array(active, dtype=np.int8)
        working[(working == AT_UPPER) & (self.upper == np.inf)] = FREE
        working[(working < AT_LOWER) | (working > AT_UPPER)] = FREE
        x, working, iterations, converged = self.solve_raw(c, working, max_iterations)
        return QPResult(x, working, iterations, converged)

    def solve_raw(self, c: np.ndarray, working: np.ndarray, max_iterations: int | None = None):
        """:meth:`solve` without checks or result object: ``(x (n,), working (n,), iterations, converged)``.

        ``working`` (int8) must be a valid working set (no ``+1`` on an infinite bound); it is not modified.
        """
        try:
            return self._solve(c, working, max_iterations)
        except _Singular:
            self._regularise()
            return self._solve(c, working, max_iterations)

    def _solve(self, c: np.ndarray, working: np.ndarray, max_iterations: int | None):
        n = self.n
        if n == 0:
            return np.zeros(0), working.copy(), 0, True
        limit = EXCHANGES if max_iterations is None else min(EXCHANGES, max_iterations)
        tolerance = self._tolerance
        low0, high0 = self._low0, self._high0
        entries = self._entries
        owned = False
        iteration = 0
        # phase 1: block exchanges from the warm-start guess
        while iteration < limit:
            iteration += 1
            key = working.tobytes()
            entry = entries.get(key)
            if entry is None:
                entry = self._entry(working, key)
            index, factor, sub, cols, base, offset, bound_values = entry
            if len(index):
                rhs = c.take(index) if offset is None else c.take(index) - offset
                z = lapack.dpotrs(factor, rhs)[0]
                if self.ridge:
                    z += lapack.dpotrs(factor, rhs - sub @ z)[0]
                gradient = cols @ z - c
                if low0 is not None:
                    values = z.tolist()  # tiny arrays: Python's min/max beat numpy's reductions
                    outside = min(values) < low0 or max(values) > high0
                else:
                    outside = bool((z < self._lower.take(index)).any() or (z > self._upper.take(index)).any())
            else:
                z = np.zeros(0)
                gradient = -c
                outside = False
            if base is not None:
                gradient += base
            violation = working * gradient
            wrong = max(violation.tolist()) > tolerance
            if not wrong and not outside:
                if len(index) == n:
                    return z, working, iteration, True
                x = bound_values.copy()
                x[index] = z
                return x, working, iteration, True
            if not owned:
                working = working.copy()
                owned = True
            if wrong:
                working[violation > tolerance] = FREE
            if outside:
                working[index[z < (low0 if low0 is not None else self._lower.take(index))]] = AT_LOWER
                working[index[z > (high0 if high0 is not None else self._upper.take(index))]] = AT_UPPER
        # phase 2: the monotone primal active-set method from the feasible point nearest the last guess
        if not owned:
            working = working.copy()
        lower, upper = self.lower, self.upper
        x = bound_values.copy()
        if len(index):
            x[index] = np.minimum(np.maximum(z, lower.take(index)), upper.take(index))
        x = np.where(working == AT_LOWER, lower, np.where(working == AT_UPPER, upper, x))
        total = max_iterations if max_iterations is not None else 10 * n + 20
        return self._primal(c, working, x, iteration, total, tolerance)

    def _primal(self, c, working, x, iteration, limit, tolerance):
        gram, lower, upper = self.gram, self.lower, self.upper
        seen: set[bytes] = set()
        while iteration < limit:
            iteration += 1
            index, factor, sub = self._get(working)[:3]
            low, high = lower.take(index), upper.take(index)
            if len(index):
                z = self._sub_solve(factor, sub, (c - gram @ np.where(working == FREE, 0.0, x)).take(index))
                below, above = z < low, z > high
                if below.any() or above.any():
                    # step towards z as far as the box allows; blocking variables join the working set
                    x_free = x[index]
                    step = z - x_free
                    with np.errstate(divide="ignore", invalid="ignore"):
                        ratio = np.where(below, (low - x_free) / step, np.where(above, (high - x_free) / step, np.inf))
                    ratio = np.maximum(ratio, 0.0)
                    alpha = float(ratio.min())
                    x[index] = x_free + alpha * step
                    blocking = ratio <= alpha
                    hit_low = index[blocking & below]
                    hit_high = index[blocking & above]
                    x[hit_low] = lower[hit_low]
                    x[hit_high] = upper[hit_high]
                    working[hit_low] = AT_LOWER
                    working[hit_high] = AT_UPPER
                    continue
                x[index] = z
            # Lagrange multipliers of the bound variables: working * gradient > 0 is a wrong sign
            violation = working * (gram @ x - c)
            worst = int(violation.argmax())
            if violation[worst] <= tolerance:
                return x, working, iteration, True
            key = working.tobytes()
            if key in seen:
                # a working set seen before can only come back through rounding (the objective falls
                # strictly otherwise): x is then optimal to working precision
                return x, working, iteration, True
            seen.add(key)
            working[worst] = FREE
        return x, working, limit, False
