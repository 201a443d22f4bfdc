"""Basis refinement: the fixed point recovers a perturbed basis, the scale is pinned, densify is exact."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from solver_factories import noisy_training

from livebridge.bench.refine import perturbed_basis
from livebridge.cli import main
from livebridge.face.basis import Basis
from livebridge.solve.refine import densify, refine_basis
from livebridge.take.npz import Take


@pytest.fixture(scope="module")
def setup(ict):
    rng = np.random.default_rng(31)
    markers, training, observed = noisy_training(ict, rng, seed=4)
    draft, scales = perturbed_basis(ict, markers, rng)
    return markers, training, observed, draft, scales


def test_densify_reproduces_the_marker_displacements(ict, setup):
    markers, _, _, _, _ = setup
    rng = np.random.default_rng(0)
    face = markers.face_mask
    wanted = markers.displacement_matrix(ict) + rng.normal(scale=0.3, size=(len(markers), ict.n_muscles, 3))
    dense = densify(ict, markers, wanted)
    assert np.abs(markers.displacement_matrix(dense)[face] - wanted[face]).max() < 0.01
    far = np.linalg.norm(ict.neutral - markers.neutral_positions(ict)[face].mean(axis=0), axis=1) > 400
    assert np.allclose(dense.elements[:, far], ict.elements[:, far], atol=1e-6)  # faded out far away


def test_refinement_recovers_scale_and_displacements(ict, setup):
    markers, _, observed, draft, scales = setup
    lines = []
    result = refine_basis(draft, markers, observed, log=lines.append)
    face = markers.face_mask
    truth = markers.displacement_matrix(ict)[face]
    draft_error = np.linalg.norm(markers.displacement_matrix(draft)[face] - truth)
    refined_error = np.linalg.norm(result.displacement[face] - truth)
    assert refined_error < 0.8 * draft_error
    assert result.errors[-1] < 0.8 * result.errors[0] and len(lines) >= 2
    # the anchor pins each element's scale: the refined norms are much closer to the truth than the draft's
    def scale_error(displacement):
        return np.abs(np.sqrt((displacement ** 2).sum(axis=(0, 2)) / (truth ** 2).sum(axis=(0, 2))) - 1)

    assert np.median(scale_error(result.displacement[face])) < 0.7 * np.median(scale_error(
        markers.displacement_matrix(draft)[face]))
    assert np.median(scale_error(result.displacement[face])) < 0.1
    assert isinstance(result.basis, Basis) and result.densify_error_mm < 0.01


def test_norm_anchor_keeps_the_draft_scale(ict, setup):
    markers, _, observed, draft, _ = setup
    result = refine_basis(draft, markers, observed, anchor="norm", max_iterations=2)
    face = markers.face_mask
    norm = np.sqrt((result.displacement[face] ** 2).sum(axis=(0, 2)))
    draft_norm = np.sqrt((markers.displacement_matrix(draft)[face] ** 2).sum(axis=(0, 2)))
    assert np.allclose(norm, draft_norm, rtol=1e-9)


def test_basis_refine_cli(ict, setup, tmp_path):
    markers, training, observed, draft, _ = setup
    draft.save(tmp_path / "draft.npz")
    markers.save(tmp_path / "markers.toml")
    Take(t=training.t, marker_names=markers.names, displacements=observed).save(tmp_path / "train.npz")
    result = CliRunner().invoke(main, ["basis", "refine", "--basis", str(tmp_path / "draft.npz"), "--markers",
                                       str(tmp_path / "markers.toml"), "--take", str(tmp_path / "train.npz"),
                                       "--out", str(tmp_path / "refined.npz"), "--max-iterations", "3"])
    assert result.exit_code == 0, result.output
    assert "iteration  1" in result.output and "element scale factors" in result.output
    assert Basis.load(tmp_path / "refined.npz").n_muscles == ict.n_muscles


def test_fixed_point_error_never_rises(ict, setup):
    # solve and re-fit minimise the same total error: with no early stop the curve must not rise
    # (it did when the re-fit regressed on the unconstrained contractions)
    from livebridge.solve.refine import refine_markers

    markers, _, observed, draft, _ = setup
    _, errors, _, iterations, _, _ = refine_markers(draft, markers, observed, max_iterations=4, tolerance=-1.0)
    assert iterations == 4 and len(errors) == 5
    assert all(later <= earlier * (1 + 1e-6) for earlier, later in zip(errors, errors[1:])), errors
