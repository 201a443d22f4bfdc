"""3D thin-plate splines: the thesis's properties (eqs. 4.11-4.19), scipy's RBFInterpolator as the peer, warps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from livebridge.errors import InputError
from livebridge.retarget.tps import Kernel, ThinPlateSpline, Warp, fit_tps

KERNELS = [Kernel.BIHARMONIC, Kernel.THIN_PLATE]


def _cloud(rng, n, scale=60.0):
    """n random points in a face-sized box (mm)."""
    return rng.uniform(-scale, scale, (n, 3))


def _smooth_warp(points):
    """A smooth non-linear map of R^3 (mm), unknown to the spline."""
    x, y, z = points.T
    return np.column_stack([1.1 * x + 4 * np.sin(y / 30), 0.9 * y + 0.002 * x * z, z + 6 * np.cos(x / 25)])


def _random_affine(rng):
    return rng.normal(size=(3, 3)) + 2 * np.eye(3), rng.normal(scale=20, size=3)


def _thesis_coefficients(centres, values, kernel, smoothing=0.0):
    """``[W; A] = L^-1 [V; 0]`` with L built entry by entry from eqs. 4.11-4.15 (``s lambda`` on K's diagonal)."""
    n = len(centres)

    def u(r):
        if kernel is Kernel.BIHARMONIC:
            return r
        return 0.0 if r == 0 else r * r * math.log(r * r)

    system = np.zeros((n + 4, n + 4))
    for i in range(n):
        for j in range(n):
            system[i, j] = u(math.dist(centres[i], centres[j])) + (kernel.sign * smoothing if i == j else 0.0)
        system[i, n:] = system[n:, i] = [1.0, *centres[i]]
    rhs = np.vstack([values, np.zeros((4, 3))])
    return np.linalg.solve(system, rhs)


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("n, offset", [(4, 0.0), (30, 0.0), (400, 0.0), (2000, 1000.0)])
def test_interpolates_its_control_points(rng, kernel, n, offset):
    """To 1e-9 mm, also for 2000 points 1000 mm from the origin: in millimetres the r^2 ln r^2 terms reach 1e5
    and their rounding alone put 400 points 1.2e-9 mm off (2000: 4.8e-9 mm); the spline's frame keeps them small."""
    centres = _cloud(rng, n) + offset
    targets = _smooth_warp(centres - offset) + offset + rng.normal(scale=2, size=centres.shape)
    spline = fit_tps(centres, targets, kernel)
    assert np.abs(spline(centres) - targets).max() < 1e-9
    # side conditions: sum w = 0, sum w c = 0 (relative to the weights' size)
    scale = np.abs(np.vstack([spline.weights, spline.affine])).max()
    assert np.abs(spline.weights.sum(axis=0)).max() < 1e-9 * scale * n
    assert np.abs(centres.T @ spline.weights).max() < 1e-9 * scale * n * np.abs(centres).max()


@pytest.mark.parametrize("kernel", KERNELS)
def test_reproduces_any_affine_map_with_zero_bending_energy(rng, kernel):
    centres = _cloud(rng, 25)
    matrix, offset = _random_affine(rng)
    spline = fit_tps(centres, centres @ matrix + offset, kernel)
    elsewhere = _cloud(rng, 500, scale=120.0)
    assert np.abs(spline(elsewhere) - (elsewhere @ matrix + offset)).max() < 1e-9
    assert np.abs(spline.affine - np.vstack([offset, matrix])).max() < 1e-9
    assert abs(spline.bending_energy()) < 1e-12
    bent = fit_tps(centres, _smooth_warp(centres), kernel)
    assert bent.bending_energy() > 1e-3


def test_affine_map_of_the_builtin_face_from_its_landmarks(rng):
    """The built-in face's 68 landmarks under a known affine map carry every vertex of the face exactly."""
    from livebridge.face.builtin import builtin_basis, builtin_landmarks

    basis = builtin_basis()
    landmarks = builtin_landmarks().neutral_positions(basis)
    matrix, offset = _random_affine(rng)
    warp = Warp(landmarks, basis.neutral)
    assert np.abs(warp(landmarks @ matrix + offset) - (basis.neutral @ matrix + offset)).max() < 1e-9


@pytest.mark.parametrize("smoothing", [0.0, 3.0])
@pytest.mark.parametrize("kernel", KERNELS)
def test_equals_the_thesis_closed_form(rng, kernel, smoothing):
    """Weights, affine part and smoothing mean the thesis's, in the points' own millimetres (not the frame's)."""
    centres = _cloud(rng, 40)
    targets = centres + rng.normal(scale=5, size=centres.shape)
    spline = fit_tps(centres, targets, kernel, smoothing)
    expected = _thesis_coefficients(centres, targets, kernel, smoothing)
    scale = np.abs(expected).max()
    assert np.abs(spline.weights - expected[:-4]).max() < 1e-9 * scale
    assert np.abs(spline.affine - expected[-4:]).max() < 1e-9 * scale
    # bending energy: W^T K W = V^T (L^-1_n K L^-1_n) V (the thesis's proposition), up to the kernel's sign
    gram = kernel.matrix(centres, centres)
    assert spline.bending_energy() == pytest.approx(kernel.sign * np.trace(expected[:-4].T @ gram @ expected[:-4]))
    assert spline.bending_energy() > 0


@pytest.mark.parametrize("kernel", KERNELS)
def test_spline_from_its_weights_and_affine_is_the_same_spline(rng, kernel):
    """A spline a user builds from the public (centres, weights, affine, kernel) evaluates, differentiates and
    bends as the fitted one."""
    centres = _cloud(rng, 50) + 300.0
    fitted = fit_tps(centres, _smooth_warp(centres), kernel, smoothing=0.5)
    rebuilt = ThinPlateSpline(fitted.centres, fitted.weights, fitted.affine, fitted.kernel)
    queries = _cloud(rng, 200, scale=90.0) + 300.0
    assert np.abs(rebuilt(queries) - fitted(queries)).max() < 1e-11
    assert np.abs(rebuilt.jacobian(queries) - fitted.jacobian(queries)).max() < 1e-12
    assert rebuilt.bending_energy() == pytest.approx(fitted.bending_energy(), rel=1e-12)
    # and the spline as written in millimetres: [1, p] A + U(|p - c|) W
    by_definition = np.hstack([kernel.matrix(queries, centres), np.ones((200, 1)), queries]) @ np.vstack(
        [fitted.weights, fitted.affine])
    assert np.abs(fitted(queries) - by_definition).max() < 1e-8


@pytest.mark.parametrize("kernel", KERNELS)
def test_jacobian_equals_central_differences(rng, kernel):
    centres = _cloud(rng, 30) + np.array([0.0, 1000.0, -200.0])
    spline = fit_tps(centres, _smooth_warp(centres), kernel)
    points = _cloud(rng, 40, scale=70.0) + np.array([0.0, 1000.0, -200.0])
    step = 1e-3
    differences = np.stack([(spline(points + step * e) - spline(points - step * e)) / (2 * step)
                            for e in np.eye(3)], axis=2)  # (m, out, in)
    jacobian = spline.jacobian(points, chunk=16)
    assert jacobian.shape == (40, 3, 3)
    assert np.abs(jacobian - differences).max() < 1e-6
    assert np.abs(jacobian).max() > 0.5


@pytest.mark.parametrize("smoothing", [0.0, 25.0, "per point"])
def test_biharmonic_spline_equals_rbfinterpolator_linear(rng, smoothing):
    centres = _cloud(rng, 60)
    targets = _smooth_warp(centres) + rng.normal(scale=1, size=centres.shape)
    queries = _cloud(rng, 2000, scale=90.0)
    if smoothing == "per point":  # some points held loosely, some interpolated
        smoothing = np.where(rng.random(len(centres)) < 0.5, 0.0, rng.uniform(1.0, 100.0, len(centres)))
    ours = fit_tps(centres, targets, Kernel.BIHARMONIC, smoothing=smoothing)(queries)
    peer = RBFInterpolator(centres, targets, kernel="linear", degree=1, smoothing=smoothing)(queries)
    assert np.abs(ours - peer).max() < 1e-9


@pytest.mark.parametrize("kernel", KERNELS)
def test_warp_equals_a_fresh_fit_for_new_targets(rng, kernel):
    centres = _cloud(rng, 30)
    vertices = _cloud(rng, 3000, scale=80.0)
    warp = Warp(centres, vertices, kernel, smoothing=0.5)
    frames = centres + rng.normal(scale=3, size=(4,) + centres.shape)
    for targets in frames:
        fresh = fit_tps(centres, targets, kernel, smoothing=0.5)
        assert np.abs(warp(targets) - fresh(vertices)).max() < 1e-9
        weight_scale = max(1.0, np.abs(fresh.weights).max())
        assert np.abs(warp.spline(targets).weights - fresh.weights).max() < 1e-12 * weight_scale
    batch = warp(frames)
    assert batch.shape == (4, 3000, 3)
    assert np.abs(batch - np.stack([warp(t) for t in frames])).max() < 1e-12 * 100


@pytest.mark.parametrize("kernel", KERNELS)
def test_smoothing_trades_interpolation_for_less_bending(rng, kernel):
    centres = _cloud(rng, 50)
    noisy = _smooth_warp(centres) + rng.normal(scale=1.0, size=centres.shape)
    fits = [fit_tps(centres, noisy, kernel, smoothing=s) for s in (0.0, 1.0, 100.0)]
    residuals = [np.abs(f(centres) - noisy).max() for f in fits]
    energies = [f.bending_energy() for f in fits]
    assert residuals[0] < 1e-9 and residuals[1] > 1e-3 and residuals[2] > residuals[1]
    assert energies[0] > energies[1] > energies[2] > 0


def test_smoothing_recovers_a_smooth_map_from_noisy_landmarks(rng):
    """Against the true map: a smoothed spline through noisy landmarks is closer to it than the interpolating one."""
    centres = _cloud(rng, 300)
    noisy = _smooth_warp(centres) + rng.normal(scale=2.0, size=centres.shape)
    queries = _cloud(rng, 2000, scale=50.0)
    truth = _smooth_warp(queries)
    errors = {s: np.sqrt(np.mean((fit_tps(centres, noisy, smoothing=s)(queries) - truth) ** 2)) for s in (0.0, 50.0)}
    assert errors[50.0] < 0.8 * errors[0.0]


def test_spline_is_frozen(rng):
    spline = fit_tps(_cloud(rng, 10), _cloud(rng, 10))
    assert isinstance(spline, ThinPlateSpline)
    with pytest.raises(ValueError):
        spline.weights[0, 0] = 1.0
    with pytest.raises(AttributeError):
        spline.kernel = Kernel.THIN_PLATE


def test_kernel_by_name_or_value():
    assert Kernel.parse("r") is Kernel.parse("biharmonic") is Kernel.BIHARMONIC
    assert Kernel.parse("r2lnr2") is Kernel.parse("thin-plate") is Kernel.parse("THIN_PLATE") is Kernel.THIN_PLATE
    assert Kernel.THIN_PLATE.matrix(np.zeros((1, 3)), np.zeros((1, 3)))[0, 0] == 0.0


def _tetra_plus(extra):
    return np.vstack([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], *extra]).astype(float)


DEGENERATE = [
    ("three points", np.eye(3), None, "at least 4 control points"),
    ("coplanar", np.column_stack([np.random.default_rng(0).uniform(-50, 50, (12, 2)), np.full(12, 7.0)]), None,
     "lie on one plane"),
    ("tilted coplanar", np.random.default_rng(1).uniform(-50, 50, (12, 2)) @ np.array([[1.0, 2, 3], [0, 1, -1]]), None,
     "lie on one plane"),
    ("collinear", np.outer(np.arange(6.0), [1, 2, 3]), None, "lie on one plane"),
    ("duplicate", _tetra_plus([[3, 3, 3], [10, 0, 0]]), None, "control points 1 and 5 coincide"),
    ("nan point", _tetra_plus([[1, 2, np.nan]]), None, "control point 4 is not finite"),
    ("infinite point", _tetra_plus([[np.inf, 2, 1]]), None, "control point 4 is not finite"),
    ("nan target", _tetra_plus([[1, 2, 3]]), _tetra_plus([[np.nan, 2, 3]]), "target 4 is not finite"),
    ("too few targets", _tetra_plus([[1, 2, 3]]), _tetra_plus([]), "4 targets for 5 control points"),
    ("2D points", np.zeros((5, 2)), None, "must have shape (n, 3)"),
    ("text", [["a", "b", "c"]] * 4, None, "not numbers"),
]


@pytest.mark.parametrize("points, targets, message", [d[1:] for d in DEGENERATE], ids=[d[0] for d in DEGENERATE])
def test_degenerate_input_names_what_is_wrong(points, targets, message):
    values = points if targets is None else targets
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        fit_tps(points, values)
    if targets is None:
        with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
            Warp(points, np.zeros((3, 3)))


def test_bad_options_are_input_errors(rng):
    centres = _cloud(rng, 8)
    with pytest.raises(InputError, match="smoothing must be"):
        fit_tps(centres, centres, smoothing=-1.0)
    with pytest.raises(InputError, match=r"one per control point \(8\), got shape \(7,\)"):
        fit_tps(centres, centres, smoothing=np.ones(7))
    with pytest.raises(InputError, match="finite and >= 0 at every control point"):
        Warp(centres, centres, smoothing=np.r_[np.ones(7), np.inf])
    with pytest.raises(InputError, match="unknown TPS kernel 'gaussian'"):
        fit_tps(centres, centres, kernel="gaussian")
    with pytest.raises(InputError, match="vertex 2 is not finite"):
        Warp(centres, np.array([[0.0, 0, 0], [1, 1, 1], [np.nan, 0, 0]]))
