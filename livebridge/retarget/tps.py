"""3D thin-plate splines (Erdoğdu eqs. 4.11-4.19): fit, evaluate, bending energy, fast repeated warps.

The spline maps a point ``p`` of R^3 to ``f(p) = [1, p] A + sum_i w_i U(|p - c_i|)`` through ``n`` control
points ``c_i`` with the side conditions ``sum_i w_i = 0`` and ``sum_i w_i c_i = 0``; ``[W; A] = L^-1 [V; 0]``
with ``L = [[K, P], [P^T, 0]]``, ``K_ij = U(|c_i - c_j|)`` and ``P = [1, c]``. With ``U(r) = r`` (the default)
this is the 3D biharmonic spline, the same function as ``scipy.interpolate.RBFInterpolator(kernel="linear",
degree=1)``; the thesis's ``U(r) = r^2 ln r^2`` is an option.

Fits and evaluations happen in centred, unit-sized coordinates (:class:`Frame`): for mm-scale points the
kernel terms in millimetres reach ``r^2 ln r^2 ~ 1e5`` and their double-precision rounding alone put a fitted
spline 1e-9 mm off its own control points.

A fit is one LAPACK ``gesv`` of ``L``, as RBFInterpolator's: `livebridge bench retarget` (both warmed up) measured
416 ms against its 374 at 3000 points, 4.3 against 3.7 at 500 (the rest is building ``L``: 44 ms at 3000, and
the checks of the control points, 0.15 ms at 22). It is kept for what scipy does not give: the thesis's kernel,
the frame's precision, the bending energy, the Jacobian and the factorised repeated warp (:class:`Warp`, 5.9
times faster a frame than RBFInterpolator's evaluation).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from functools import lru_cache

import numpy as np
from scipy.linalg import lu_factor, lu_solve
from scipy.linalg.lapack import dgesv
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from livebridge.errors import InputError

# Relative to the control points' extent: closer than this they coincide, flatter than this they are coplanar.
DEGENERACY_TOLERANCE = 1e-9


class Kernel(Enum):
    """The radial function ``U(r)`` of the spline."""

    BIHARMONIC = "r"
    """``U(r) = r``: the fundamental solution of the biharmonic equation in 3D (the default)."""
    THIN_PLATE = "r2lnr2"
    """``U(r) = r^2 ln r^2`` with ``U(0) = 0``: the thesis's eq. 4.4 (the 2D fundamental solution)."""

    @classmethod
    def parse(cls, value: Kernel | str) -> Kernel:
        """A kernel from itself, its name (``"biharmonic"``, ``"thin_plate"``) or its value (``"r"``, ``"r2lnr2"``)."""
        if isinstance(value, cls):
            return value
        text = str(value).strip()
        for kernel in cls:
            if text.lower() in (kernel.name.lower(), kernel.value, kernel.name.lower().replace("_", "-")):
                return kernel
        known = ", ".join(f"{k.name.lower()} ({k.value})" for k in cls)
        raise InputError(f"unknown TPS kernel {value!r}; known: {known}", field="kernel")

    def matrix(self, points: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """``U(|p_a - c_i|)``, shape (m, n), for points (m, 3) and centres (n, 3)."""
        if self is Kernel.BIHARMONIC:
            return cdist(points, centres)
        r2 = cdist(points, centres, "sqeuclidean")
        # r^2 ln r^2 -> 0 as r -> 0; the floor only keeps log away from -inf, the product stays 0
        return r2 * np.log(np.maximum(r2, np.finfo(float).tiny))

    def gradient_factor(self, r2: np.ndarray) -> np.ndarray:
        """``g`` with ``grad U(|p - c|) = g (p - c)``, from the squared distances ``r2`` (any shape); 0 at ``r = 0``."""
        if self is Kernel.BIHARMONIC:
            r = np.sqrt(r2)
            return np.divide(1.0, r, out=np.zeros_like(r), where=r > 0)
        factor = 2.0 * np.log(np.maximum(r2, np.finfo(float).tiny)) + 2.0
        factor[r2 == 0] = 0.0
        return factor

    @property
    def degree(self) -> int:
        """``k`` with ``U(s r) = s^k U(r)``; ``r^2 ln r^2`` adds ``s^2 ln(s^2) r^2`` (see :class:`Frame`)."""
        return 1 if self is Kernel.BIHARMONIC else 2

    @property
    def sign(self) -> float:
        """``s`` with ``s U`` conditionally positive definite under the side conditions.

        The bending energy is ``s trace(W^T K W) >= 0`` and smoothing adds ``s lambda`` to the diagonal of K
        (``-r`` and ``r^2 ln r`` are the conditionally positive definite forms).
        """
        return -1.0 if self is Kernel.BIHARMONIC else 1.0


@dataclass(frozen=True)
class ThinPlateSpline:
    """A fitted 3D thin-plate spline ``f(p) = [1, p] A + U(|p - c|) W``.

    ``weights`` and ``affine`` are in the points' own coordinates; the spline evaluates itself in the
    :class:`Frame` of its centres, from the same spline's coefficients there.

    Attributes
    ----------
    centres : ndarray, shape (n, 3)
        The control points ``c_i``.
    weights : ndarray, shape (n, 3)
        ``W``: one non-affine weight per control point and output coordinate (each column sums to 0 and is
        orthogonal to the centres' coordinates).
    affine : ndarray, shape (4, 3)
        ``A``: rows for ``1, x, y, z``.
    kernel : Kernel
    frame : Frame
        The centres' frame (derived from ``centres``).
    frame_coefficients : ndarray, shape (n + 4, 3)
        ``[W; A]`` of the same spline in ``frame`` (derived from ``weights`` and ``affine``).
    """

    centres: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    kernel: Kernel
    frame: Frame = field(init=False, repr=False, compare=False)
    frame_coefficients: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        for name in ("centres", "weights", "affine"):
            array = np.array(getattr(self, name), dtype=np.float64)
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        frame = Frame.of(self.centres)
        coefficients = frame.frame_coefficients(self.weights, self.affine, frame.to(self.centres), self.kernel)
        coefficients.setflags(write=False)
        object.__setattr__(self, "frame", frame)
        object.__setattr__(self, "frame_coefficients", coefficients)

    @classmethod
    def in_frame(cls, centres: np.ndarray, coefficients: np.ndarray, kernel: Kernel) -> ThinPlateSpline:
        """The spline with (n + 4, 3) ``coefficients`` ``[W; A]`` in the :class:`Frame` of its (n, 3) centres."""
        frame = Frame.of(centres)
        return cls(centres, *frame.weights_and_affine(coefficients, frame.to(centres), kernel), kernel)

    def __call__(self, points: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """``f(points)``, shape (m, 3), for points (m, 3); ``chunk`` points at a time to bound memory (the
        (m, n) kernel matrix of a 600k-vertex target and 1000 centres would be 4.7 GB)."""
        points = self.frame.to(_as_points(points, "points"))
        centres = self.frame.to(self.centres)
        weights, affine = self.frame_coefficients[:-4], self.frame_coefficients[-4:]
        out = affine[0] + points @ affine[1:]
        # the kernel and affine parts apart: the (m, n + 4) design matrix's copy cost more than its product
        for start in range(0, len(points), chunk):
            out[start:start + chunk] += self.kernel.matrix(points[start:start + chunk], centres) @ weights
        return out

    def jacobian(self, points: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """``df/dp`` at points (m, 3), shape (m, 3 out, 3 in), from the kernel's gradient.

        ``grad U(|p - c|) = g(r) (p - c)`` with ``g = 1 / r`` for ``U = r`` (0 at a centre, where ``r`` has no
        gradient) and ``g = 2 ln r^2 + 2`` for ``U = r^2 ln r^2``, taken in the frame (``df/dp = df/dq /
        scale``). Evaluated ``chunk`` points at a time to bound memory.
        """
        points = self.frame.to(_as_points(points, "points"))
        centres = self.frame.to(self.centres)
        weights, linear = self.frame_coefficients[:-4], self.frame_coefficients[-3:]
        # sum_n g W[n, out] (q - c_n)[in] = (g W)[out] q[in] - (g (W c^T))[out, in]: two products instead of
        # an (m, n, 3) array of offsets (10k points, 300 centres: 227 -> 101 ms for r, 422 -> 95 ms for r^2 ln r^2)
        weighted_centres = (weights[:, :, None] * centres[:, None, :]).reshape(len(centres), 9)
        out = np.empty((len(points), 3, 3))
        for start in range(0, len(points), chunk):
            part = points[start:start + chunk]
            gradient = self.kernel.gradient_factor(cdist(part, centres, "sqeuclidean"))
            along = (gradient @ weights)[:, :, None] * part[:, None, :]
            out[start:start + chunk] = (linear.T[None] + along - (gradient @ weighted_centres).reshape(-1, 3, 3))
        return out / self.frame.scale

    def bending_energy(self) -> float:
        """The bending energy up to the kernel's constant factor: ``s trace(W^T K W)`` (>= 0, 0 iff affine).

        ``s`` is :attr:`Kernel.sign`; summed over the three output coordinates (the thesis's ``W K W^T``).
        Taken in the frame: ``W K W^T`` there is ``scale^k`` times this (``k`` = :attr:`Kernel.degree`; the
        extra ``r^2`` term of ``r^2 ln r^2`` vanishes under the side conditions).
        """
        centres = self.frame.to(self.centres)
        weights = self.frame_coefficients[:-4]
        energy = np.einsum("ik,ij,jk->", weights, self.kernel.matrix(centres, centres), weights)
        return float(self.kernel.sign * energy / self.frame.scale ** self.kernel.degree)


def fit_tps(control_points: np.ndarray, targets: np.ndarray, kernel: Kernel | str = Kernel.BIHARMONIC,
            smoothing: float | np.ndarray = 0.0) -> ThinPlateSpline:
    """The spline that carries ``control_points`` to ``targets`` with the least bending energy.

    Parameters
    ----------
    control_points : ndarray, shape (n, 3)
        ``c_i``, n >= 4, distinct, not all on one plane.
    targets : ndarray, shape (n, 3)
        ``v_i``, where ``c_i`` goes.
    kernel : Kernel or str
    smoothing : float or ndarray, shape (n,)
        ``lambda >= 0``. 0 interpolates; above 0 the spline minimises ``sum |f(c_i) - v_i|^2 + lambda E(f)``
        (``E`` = :meth:`ThinPlateSpline.bending_energy`) for noisy landmarks, as scipy's ``RBFInterpolator``;
        one per control point weighs each residual by ``1 / lambda_i`` instead (a point held loosely).

    Raises
    ------
    InputError
        Fewer than 4 points, coincident or coplanar control points, non-finite values, wrong shapes,
        negative smoothing.
    """
    kernel = Kernel.parse(kernel)
    centres = check_control_points(control_points)
    values = check_targets(targets, len(centres))
    smoothing = check_smoothing(smoothing, len(centres))
    frame = Frame.of(centres)
    # LAPACK gesv as RBFInterpolator calls it: measured 2-4x faster than scipy.linalg.solve (which adds a
    # condition estimate) and than lu_factor + lu_solve (OpenBLAS threads getrs even for 26 x 26)
    _, _, coefficients, info = dgesv(system_matrix(frame.to(centres), kernel, frame.smoothing(smoothing, kernel)),
                                     np.vstack([values, np.zeros((4, 3))]), overwrite_a=True, overwrite_b=True)
    if info > 0:
        raise InputError("the spline's system is singular: control points nearly coincide or nearly lie on one "
                         "plane", field="control points")
    return ThinPlateSpline.in_frame(centres, coefficients, kernel)


class Warp:
    """The same mesh warped by the spline of the same control points towards new targets, many times.

    Built once from the control points and the mesh vertices: keeps the LU factorisation of ``L`` and the
    (m, n + 4) matrix ``[U(|v - c|), 1, v]`` of the vertices, both in the control points' :class:`Frame`, so a
    warp costs one (n + 4) solve and one (m, n + 4) @ (n + 4, 3) product.

    Parameters
    ----------
    control_points : ndarray, shape (n, 3)
    vertices : ndarray, shape (m, 3)
        The points to warp (a mesh's vertices).
    kernel : Kernel or str
    smoothing : float
        As in :func:`fit_tps`.
    """

    def __init__(self, control_points: np.ndarray, vertices: np.ndarray, kernel: Kernel | str = Kernel.BIHARMONIC,
                 smoothing: float = 0.0):
        self.kernel = Kernel.parse(kernel)
        self.control_points = check_control_points(control_points)
        self.control_points.setflags(write=False)
        self.smoothing = check_smoothing(smoothing, len(self.control_points))
        frame = Frame.of(self.control_points)
        centres = frame.to(self.control_points)
        self._lu = lu_factor(system_matrix(centres, self.kernel, frame.smoothing(self.smoothing, self.kernel)),
                             overwrite_a=True, check_finite=False)
        self._design = design_matrix(frame.to(_as_points(vertices, "vertices", "vertex")), centres, self.kernel)

    @property
    def n_vertices(self) -> int:
        return len(self._design)

    def spline(self, targets: np.ndarray) -> ThinPlateSpline:
        """The fitted spline for ``targets`` (n, 3)."""
        targets = check_targets(targets, len(self.control_points))
        with _blas_controller().limit(limits=1, user_api="blas"):
            coefficients = _solve(self._lu, targets)
        return ThinPlateSpline.in_frame(self.control_points, coefficients, self.kernel)

    def __call__(self, targets: np.ndarray) -> np.ndarray:
        """The warped vertices: (m, 3) for targets (n, 3), or (k, m, 3) for k target sets (k, n, 3) at once."""
        targets = np.asarray(targets, dtype=np.float64)
        n = len(self.control_points)
        if targets.ndim == 3:
            stacked = np.concatenate([check_targets(t, n) for t in targets], axis=1)
            warped = self._design @ _solve(self._lu, stacked)
            return warped.reshape(self.n_vertices, len(targets), 3).transpose(1, 0, 2)
        targets = check_targets(targets, n)
        # one frame is too small a job to wake BLAS threads: on a busy 2-core machine waking them made a
        # 10k-vertex frame 16 ms instead of 0.3 ms (OpenBLAS threads even getrs of a 26 x 26 system)
        with _blas_controller().limit(limits=1, user_api="blas"):
            return self._design @ _solve(self._lu, targets)


@lru_cache(maxsize=1)
def _blas_controller():
    """The BLAS libraries numpy and scipy loaded, found once (finding them costs more than a frame)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@dataclass(frozen=True)
class Frame:
    """Centred, unit-sized coordinates ``q = (p - shift) / scale`` in which a spline is solved and evaluated.

    They keep ``L`` well conditioned far from the origin (as scipy's RBFInterpolator does for the affine part)
    and the kernel terms small for points in millimetres. The spline is the same: with ``k`` =
    :attr:`Kernel.degree`, ``U(|p - c|) = scale^k U(|q - q_c|)``, so the weights in ``p`` are those in the frame
    over ``scale^k`` and the smoothing in the frame is ``lambda / scale^k``. ``r^2 ln r^2`` adds
    ``scale^2 ln(scale^2) |q - q_c|^2``, whose sum over the weights is, under the side conditions, the constant
    ``ln(scale^2) sum_i w_i |q_c,i|^2`` (frame weights ``w_i``): it moves into the affine part.
    """

    shift: np.ndarray
    scale: float

    @classmethod
    def of(cls, centres: np.ndarray) -> Frame:
        return cls(centres.mean(axis=0), max(float(np.ptp(centres, axis=0).max()) / 2, np.finfo(float).tiny))

    def to(self, points: np.ndarray) -> np.ndarray:
        """``(p - shift) / scale``, shape (m, 3), for points (m, 3)."""
        return (points - self.shift) / self.scale

    def smoothing(self, smoothing: float | np.ndarray, kernel: Kernel) -> float | np.ndarray:
        """The frame's ``lambda`` for the same spline as ``smoothing`` in the points' own units."""
        return smoothing / self.scale ** kernel.degree

    def weights_and_affine(self, coefficients: np.ndarray, centres: np.ndarray,
                           kernel: Kernel) -> tuple[np.ndarray, np.ndarray]:
        """``(W, A)`` in the points' own coordinates, shapes (n, 3) and (4, 3), from the frame's (n + 4, 3)
        coefficients ``[W; A]`` of a spline with centres (n, 3) in the frame."""
        weights = coefficients[:-4] / self.scale ** kernel.degree
        linear = coefficients[-3:] / self.scale
        constant = coefficients[-4] - self.shift @ linear - self._kernel_constant(coefficients[:-4], centres, kernel)
        return weights, np.vstack([constant, linear])

    def frame_coefficients(self, weights: np.ndarray, affine: np.ndarray, centres: np.ndarray,
                           kernel: Kernel) -> np.ndarray:
        """The frame's (n + 4, 3) ``[W; A]`` from ``W`` (n, 3) and ``A`` (4, 3) in the points' own coordinates
        (the inverse of :meth:`weights_and_affine`); ``centres`` (n, 3) in the frame."""
        frame_weights = weights * self.scale ** kernel.degree
        constant = affine[0] + self.shift @ affine[1:] + self._kernel_constant(frame_weights, centres, kernel)
        return np.vstack([frame_weights, constant, affine[1:] * self.scale])

    def _kernel_constant(self, weights: np.ndarray, centres: np.ndarray, kernel: Kernel) -> np.ndarray:
        """The (3,) affine constant the kernel gains from the points' units to the frame's, for frame weights."""
        if kernel is Kernel.BIHARMONIC:
            return np.zeros(weights.shape[1])
        return np.log(self.scale ** 2) * (np.einsum("nd,nd->n", centres, centres) @ weights)


def design_matrix(points: np.ndarray, centres: np.ndarray, kernel: Kernel) -> np.ndarray:
    """``[U(|p - c|), 1, p]``, shape (m, n + 4): the spline's value at points (m, 3) is this @ ``[W; A]``."""
    return np.hstack([kernel.matrix(points, centres), np.ones((len(points), 1)), points])


def system_matrix(centres: np.ndarray, kernel: Kernel, smoothing: float | np.ndarray = 0.0) -> np.ndarray:
    """``L = [[K + s lambda I, P], [P^T, 0]]``, shape (n + 4, n + 4) (eq. 4.13; ``s`` = :attr:`Kernel.sign`).

    ``P = [1, c]``; ``smoothing`` is ``lambda``, one for all or (n,) along the diagonal.
    """
    n = len(centres)
    system = np.zeros((n + 4, n + 4))
    system[:n, :n] = kernel.matrix(centres, centres)
    system[:n, :n][np.diag_indices(n)] += kernel.sign * smoothing
    system[:n, n:] = np.hstack([np.ones((n, 1)), centres])
    system[n:, :n] = system[:n, n:].T
    return system


def check_smoothing(smoothing: float | np.ndarray, n: int) -> float | np.ndarray:
    """``smoothing`` as a float ``lambda >= 0`` or a read-only (n,) array of them, or an :class:`InputError`."""
    if np.ndim(smoothing) == 0:
        if not (np.isfinite(smoothing) and smoothing >= 0):
            raise InputError(f"smoothing must be a finite number >= 0, got {smoothing}", field="smoothing")
        return float(smoothing)
    values = np.array(smoothing, dtype=np.float64)
    if values.shape != (n,):
        raise InputError(f"smoothing must be one number or one per control point ({n}), got shape {values.shape}",
                         field="smoothing")
    if not (np.isfinite(values).all() and (values >= 0).all()):
        raise InputError("smoothing must be finite and >= 0 at every control point", field="smoothing")
    values.setflags(write=False)
    return values


def check_control_points(points: np.ndarray) -> np.ndarray:
    """``points`` as a float (n, 3) array fit to anchor a 3D spline, or an :class:`InputError` naming the fault."""
    points = _as_points(points, "control points", "control point")
    if len(points) < 4:
        raise InputError(f"a 3D thin-plate spline needs at least 4 control points, got {len(points)}",
                         field="control points")
    extent = float(np.ptp(points, axis=0).max())
    tolerance = DEGENERACY_TOLERANCE * max(extent, 1.0)
    pairs = cKDTree(points).query_pairs(tolerance, output_type="ndarray")
    if len(pairs):
        i, j = sorted(min(pairs.tolist()))
        raise InputError(f"control points {i} and {j} coincide (at {_xyz(points[i])}); each point must be "
                         "given once", field="control points")
    centred = points - points.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    thickness = float(np.abs(centred @ normal).max())
    if thickness <= tolerance:
        raise InputError(f"the {len(points)} control points lie on one plane (normal {_xyz(normal, 3)}); a 3D "
                         "spline needs points off that plane (rank of [1, c] < 4)", field="control points")
    return points


def check_targets(targets: np.ndarray, n: int) -> np.ndarray:
    """``targets`` as a float (n, 3) array, or an :class:`InputError` naming the fault."""
    targets = _as_points(targets, "targets", "target")
    if len(targets) != n:
        raise InputError(f"{len(targets)} targets for {n} control points", field="targets")
    return targets


def _as_points(points: np.ndarray, what: str, one: str = "point") -> np.ndarray:
    """Float (m, 3) array with every value finite, or an :class:`InputError` naming the first bad point.

    ``what`` names the array (``"control points"``), ``one`` a row of it (``"control point"``).
    """
    try:
        array = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise InputError(f"{what} are not numbers: {error}", field=what) from error
    if array.ndim != 2 or array.shape[1] != 3:
        raise InputError(f"{what} must have shape (n, 3), got {array.shape}", field=what)
    bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
    if len(bad):
        raise InputError(f"{one} {bad[0]} is not finite "
                         f"({_xyz(array[bad[0]])}; {len(bad)} such)", field=what)
    return array


def _solve(lu, values: np.ndarray) -> np.ndarray:
    """``[W; A] = L^-1 [V; 0]``, shape (n + 4, columns of V)."""
    rhs = np.vstack([values, np.zeros((4, values.shape[1]))])
    return lu_solve(lu, rhs, check_finite=False)


def _xyz(point: np.ndarray, digits: int = 6) -> str:
    return "(" + ", ".join(f"{v:.{digits}g}" for v in point) + ")"
