"""Basis retargeting (livebridge.retarget.basis): self-transfer and a known non-linear warp as ground truth.

The ICT basis when the reference data is here, else the built-in face; run with ``-s`` to see per-element
figures for both kernels.
"""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.bench.retarget import bench_basis, known_warp
from livebridge.retarget.basis import naive_transfer, relative_errors, retarget_basis
from livebridge.retarget.tps import Kernel

SELF_LIMIT = 0.05
WARP_LIMIT = 0.15
NAIVE_RATIO = 0.5


@pytest.fixture(scope="module")
def face():
    """(name, basis, landmark set on it)."""
    return bench_basis()


def _open_on_builtin(name: str) -> None:
    """Open (issue 16): the correspondence does not yet break ties between coincident vertices."""
    if name != "ict":
        pytest.xfail("the built-in face's closed lip seam: coincident upper/lower-lip vertices match either lip")


def test_self_transfer_reproduces_every_element(face):
    name, basis, landmarks = face
    _open_on_builtin(name)
    for kernel in Kernel:
        out = retarget_basis(basis, landmarks, basis.neutral, basis.triangles, landmarks, kernel)
        errors = relative_errors(out.elements, basis.elements)
        print(f"\nself-transfer on {name}, kernel {kernel.value}: worst {np.nanmax(errors):.2e} of element RMS")
        assert out.names == basis.names and [m.region for m in out.muscles] == [m.region for m in basis.muscles]
        assert np.nanmax(errors) <= SELF_LIMIT, dict(zip(basis.names, errors))


@pytest.fixture(scope="module")
def warped(face):
    """The face under the known warp phi: (name, basis, landmarks, target vertices, truth (k, n, 3), naive errors).

    Same topology, so the landmarks sit on the same triangles of the warped mesh (= phi(landmarks) up to the
    curvature of phi across one triangle). Ground truth per element: phi(E0 + e_i) - phi(E0).
    """
    name, basis, landmarks = face
    positions = landmarks.as_dict(basis.neutral, basis.triangles)
    target = known_warp(basis.neutral, positions)
    truth = np.stack([known_warp(basis.neutral + e, positions) - target for e in basis.elements])
    naive = relative_errors(naive_transfer(basis, landmarks, target, basis.triangles, landmarks), truth)
    errors = {}
    for kernel in Kernel:
        out = retarget_basis(basis, landmarks, target, basis.triangles, landmarks, kernel)
        errors[kernel] = relative_errors(out.elements, truth)
    print(f"\nknown warp on {name}: error / element RMS over the vertices it moves (naive | r | r2lnr2)")
    for k, muscle in enumerate(basis.names):
        print(f"  {muscle:24s} {naive[k]:6.3f} | {errors[Kernel.BIHARMONIC][k]:6.3f} | "
              f"{errors[Kernel.THIN_PLATE][k]:6.3f}")
    for kernel, e in errors.items():
        print(f"  {kernel.value}: worst {np.nanmax(e):.3f}, mean {np.nanmean(e):.3f}, "
              f"worst ratio to naive {np.nanmax(e / naive):.3f}")
    return basis, naive, errors


def test_known_warp_within_15_percent(face, warped):
    _open_on_builtin(face[0])
    basis, _, errors = warped
    for kernel, e in errors.items():
        assert np.nanmax(e) <= WARP_LIMIT, (kernel, dict(zip(basis.names, e)))


@pytest.mark.xfail(strict=True, reason="open: with 22 landmarks the TPS Jacobian misses phi's by ~10%; where phi "
                   "is nearly a similarity (zygomatic, risorius: naive 0.17) the ratio is 0.6-0.8")
def test_known_warp_at_most_half_the_naive_error(warped):
    basis, naive, errors = warped
    ratio = errors[Kernel.BIHARMONIC] / naive
    assert np.nanmax(ratio) <= NAIVE_RATIO, dict(zip(basis.names, ratio))


def test_cli_writes_the_retargeted_basis_and_names_a_missing_landmark(tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    out = tmp_path / "target.npz"
    args = ["retarget", "basis", "--source", "builtin", "--source-landmarks", "builtin-22", "--target", "builtin",
            "--out", str(out)]
    result = CliRunner().invoke(main, args + ["--target-landmarks", "builtin-22"])
    assert result.exit_code == 0, result.output
    # not exact on the built-in face: its 27 coincident lip-seam vertices pick either lip (see the report)
    assert np.nanmax(relative_errors(Basis.load(out).elements, builtin_basis().elements)) <= 0.15
    partial = load_landmark_set("builtin-22")
    partial.subset(np.array([name != "nose_tip" for name in partial.names])).save(tmp_path / "lm.toml")
    result = CliRunner().invoke(main, args + ["--force", "--target-landmarks", str(tmp_path / "lm.toml")])
    assert result.exit_code != 0 and "nose_tip" in result.output and "Error" in result.output, result.output
