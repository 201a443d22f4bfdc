"""Basis validation: a badly sculpted element stands out, a correct basis passes; the CLI writes its report."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation
from solver_factories import noisy_training

from livebridge.cli import main
from livebridge.solve.validate import check_basis
from livebridge.take.npz import Take


@pytest.fixture(scope="module")
def training(ict):
    return noisy_training(ict, np.random.default_rng(21), seed=3)


def test_a_correct_basis_is_not_flagged(ict, training):
    markers, _, observed = training
    report = check_basis(ict, markers, observed)
    assert report.flagged == ()
    assert 0.2 < report.region_rms_mm["upper"] < 0.5 and 0.2 < report.region_rms_mm["lower"] < 0.5
    assert all(m.exercised for m in report.muscles)


@pytest.mark.parametrize(("muscle", "damage"), [
    ("orbicularis_oculi_L", "scale"), ("orbicularis_oris", "scale"),
    ("corrugator_L", "rotate"), ("zygomatic_major_R", "rotate"),
])
def test_a_badly_sculpted_element_stands_out(ict, training, muscle, damage):
    markers, _, observed = training
    index = ict.index(muscle)
    elements = ict.elements.copy()
    if damage == "scale":
        elements[index] *= 0.4
    else:
        elements[index] = Rotation.from_euler("z", 60, degrees=True).apply(elements[index])
    report = check_basis(ict.with_elements(elements), markers, observed)
    assert report.flagged == (muscle,)
    worst = max(report.muscles, key=lambda m: m.misfit)
    assert worst.name == muscle
    if damage == "scale":  # the unconstrained contraction has to reach 1 / 0.4
        assert report.muscles[index].unconstrained_max > 1.8


def test_basis_check_cli_writes_summary_and_plot(ict, training, tmp_path):
    markers, performance, observed = training
    elements = ict.elements.copy()
    elements[ict.index("corrugator_L")] *= 0.4
    ict.with_elements(elements).save(tmp_path / "basis.npz")
    markers.save(tmp_path / "markers.toml")
    Take(t=performance.t, marker_names=markers.names, displacements=observed).save(tmp_path / "train.npz")
    result = CliRunner().invoke(main, ["basis", "check", "--basis", str(tmp_path / "basis.npz"), "--markers",
                                       str(tmp_path / "markers.toml"), "--take", str(tmp_path / "train.npz"),
                                       "--out-dir", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "flagged: corrugator_L" in result.output
    assert (tmp_path / "out" / "train.basis-check.png").stat().st_size > 10_000
    assert "corrugator_L" in (tmp_path / "out" / "train.basis-check.txt").read_text()
    bad = CliRunner().invoke(main, ["basis", "check", "--basis", str(tmp_path / "basis.npz"), "--markers",
                                    str(tmp_path / "markers.toml"), "--take", str(tmp_path / "missing.npz")])
    assert bad.exit_code != 0 and "missing.npz" in bad.output
