"""Basis retargeting (livebridge.retarget.basis): self-transfer and a known non-linear warp as ground truth.

The ICT basis when the reference data is here, else the built-in face; run with ``-s`` to see per-element
figures for both kernels.
"""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.bench.data import ict_basis
from livebridge.retarget.basis import naive_transfer, relative_errors, retarget_basis
from livebridge.retarget.landmarks import load_landmark_set
from livebridge.retarget.tps import Kernel

SELF_LIMIT = 0.05
WARP_LIMIT = 0.15
NAIVE_RATIO = 0.5


@pytest.fixture(scope="module")
def face():
    """(name, basis, landmark set on it)."""
    basis = ict_basis()
    if basis is not None:
        return "ict", basis, load_landmark_set("ict-22")
    from livebridge.face.builtin import builtin_basis

    return "builtin", builtin_basis(), load_landmark_set("builtin-22")


def known_warp(points: np.ndarray, landmarks: dict[str, np.ndarray]) -> np.ndarray:
    """phi: a smooth non-linear warp giving other proportions (points (n, 3) mm -> (n, 3) mm).

    Per-axis scale 0.85 / 1.2 / 0.9 (narrower, taller, flatter), a wider mouth (x stretched up to 25% near
    the mouth), a longer nose (the nose tip region pushed down and out) and a bent face (z falls off with x^2).
    """
    mouth = 0.5 * (landmarks["mouth_corner_L"] + landmarks["mouth_corner_R"])
    tip = landmarks["nose_tip"]
    size = float(np.ptp(np.array(list(landmarks.values())), axis=0).max())
    q = points - mouth
    near_mouth = np.exp(-((q[:, 1] / (0.35 * size)) ** 2))
    to_tip = points - tip
    near_nose = np.exp(-np.sum((to_tip / (0.3 * size)) ** 2, axis=1))
    x = 0.85 * q[:, 0] * (1 + 0.25 * near_mouth)
    y = 1.2 * q[:, 1] - 0.08 * size * near_nose
    z = 0.9 * q[:, 2] + 0.04 * size * near_nose - 0.25 * q[:, 0] ** 2 / size
    return np.stack([x, y, z], axis=1) + mouth


def _rows(name, errors):
    return [f"{name:24s} " + " ".join(f"{e:6.3f}" for e in row) for row in errors]


def test_self_transfer_reproduces_every_element(face):
    name, basis, landmarks = face
    for kernel in Kernel:
        out = retarget_basis(basis, landmarks, basis.neutral, basis.triangles, landmarks, kernel)
        errors = relative_errors(out.elements, basis.elements)
        print(f"\nself-transfer on {name}, kernel {kernel.value}: worst {np.nanmax(errors):.2e} of element RMS")
        assert out.names == basis.names and [m.region for m in out.muscles] == [m.region for m in basis.muscles]
        assert np.nanmax(errors) <= SELF_LIMIT, dict(zip(basis.names, errors))


def test_known_warp_beats_naive_baseline(face):
    name, basis, landmarks = face
    positions = landmarks.as_dict(basis.neutral, basis.triangles)
    target = known_warp(basis.neutral, positions)
    truth = np.stack([known_warp(basis.neutral + e, positions) - target for e in basis.elements])
    target_landmarks = landmarks  # same topology: the landmarks sit on the same triangles of the warped mesh
    naive = relative_errors(naive_transfer(basis, landmarks, target, basis.triangles, target_landmarks), truth)
    print(f"\nknown warp on {name}: error / element RMS (naive | r | r2lnr2)")
    per_kernel = {}
    for kernel in Kernel:
        out = retarget_basis(basis, landmarks, target, basis.triangles, target_landmarks, kernel)
        per_kernel[kernel] = relative_errors(out.elements, truth)
    for k, muscle in enumerate(basis.names):
        print(f"  {muscle:24s} {naive[k]:6.3f} | {per_kernel[Kernel.BIHARMONIC][k]:6.3f} | "
              f"{per_kernel[Kernel.THIN_PLATE][k]:6.3f}")
    for kernel, errors in per_kernel.items():
        print(f"  {kernel.value}: worst {np.nanmax(errors):.3f}, mean {np.nanmean(errors):.3f}, "
              f"worst ratio to naive {np.nanmax(errors / naive):.3f}")
    errors = per_kernel[Kernel.BIHARMONIC]
    assert np.nanmax(errors) <= WARP_LIMIT, dict(zip(basis.names, errors))
    assert np.nanmax(errors / naive) <= NAIVE_RATIO, dict(zip(basis.names, errors / naive))
