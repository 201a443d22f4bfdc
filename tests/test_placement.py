"""Automatic marker placement on a layout livebridge did not design."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from livebridge.cli import main
from livebridge.face.builtin import builtin_basis
from livebridge.face.markers import MarkerSet
from livebridge.simulators.performer import perform
from livebridge.simulators.rig import generate_markers
from livebridge.solve.offline import place_from_positions, solve_positions
from livebridge.take.npz import Take


def _foreign_take(seed: int):
    """Random sites, unknown names, shuffled, in a world rotated/translated/scaled by a random similarity."""
    basis = builtin_basis()
    rng = np.random.default_rng(seed)
    layout = generate_markers(basis, n_face=50, n_head=4, seed=seed)
    order = rng.permutation(len(layout))
    names = tuple(f"M{k}_{rng.integers(10**6)}" for k in range(len(layout)))
    layout = MarkerSet(names, layout.triangles[order], layout.barycentric[order],
                       tuple(layout.regions[i] for i in order), tuple(layout.roles[i] for i in order))
    performance = perform(basis, layout, 300, seed=seed, script="everyday")
    scale = rng.uniform(0.3, 3.0)
    rotation = Rotation.random(random_state=seed).as_matrix()
    world = scale * np.einsum("ij,fnj->fni", rotation, performance.marker_positions) + rng.uniform(-1000, 1000, 3)
    return basis, layout, performance, world


@pytest.mark.parametrize("seed", [7, 3, 19])
def test_auto_placement_finds_the_head_markers_and_solves_within_tolerance(seed):
    basis, layout, performance, world = _foreign_take(seed)
    # the take starts mid-expression: the first frame is no neutral, the choice must find one later
    start = int(np.argmax(performance.contractions.max(axis=1) > 0.3))
    world, truth = world[start:], performance.contractions[start:]
    placement, choice = place_from_positions(world, layout.names, basis, None)
    assert truth[choice.frame].max() < 0.05, choice.reason
    truth_head = {n for n, r in zip(layout.names, layout.roles) if r == "head"}
    found_head = {n for n, r in zip(placement.markers.names, placement.markers.roles) if r == "head"}
    assert truth_head <= found_head
    error = np.linalg.norm(placement.markers.neutral_positions(basis) - layout.neutral_positions(basis), axis=1)
    result = solve_positions(performance.t[start:], world, basis, placement.markers, choice)
    rmse = float(np.sqrt(np.mean((result.solution.contractions - truth) ** 2)))
    print(f"auto placement (seed {seed}): {choice.reason}; placement error median {np.median(error):.2f} mm, "
          f"max {error.max():.2f} mm; head markers {len(truth_head)}/{len(truth_head)} found "
          f"(+{len(found_head - truth_head)} rigid sites); contraction RMSE {rmse:.4f}")
    assert rmse <= 0.02


def test_correspondences_give_the_rough_alignment():
    basis, layout, performance, world = _foreign_take(3)
    vertices = basis.triangles[layout.triangles, np.argmax(layout.barycentric, axis=1)]
    correspond = {layout.names[k]: int(vertices[k]) for k in range(0, 20, 4)}
    placement, _ = place_from_positions(world, layout.names, basis, 0, correspond)
    assert "named correspondences" in placement.how
    error = np.linalg.norm(placement.markers.neutral_positions(basis) - layout.neutral_positions(basis), axis=1)
    assert np.median(error) < 2.0, np.median(error)


def test_cli_place_writes_a_marker_set_that_report_reads(tmp_path):
    basis, layout, performance, world = _foreign_take(11)
    Take(t=performance.t, marker_names=layout.names, positions=world).save(tmp_path / "take.npz")
    out = tmp_path / "placed.toml"
    result = CliRunner().invoke(main, ["markers", "place", str(tmp_path / "take.npz"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert MarkerSet.load(out).names == layout.names
    report = CliRunner().invoke(main, ["markers", "report", str(out)])
    assert report.exit_code == 0 and "condition number" in report.output, report.output


def test_cli_solve_with_auto_markers_meets_ground_truth(tmp_path):
    basis, layout, performance, world = _foreign_take(11)
    Take(t=performance.t, marker_names=layout.names, positions=world).save(tmp_path / "take.npz")
    out = tmp_path / "c.csv"
    result = CliRunner().invoke(main, ["solve", str(tmp_path / "take.npz"), "--markers", "auto", "--out", str(out),
                                       "--markers-out", str(tmp_path / "placed.toml")])
    assert result.exit_code == 0, result.output
    assert "least deformation from rest" in result.output and "head markers:" in result.output, result.output
    written = np.loadtxt(out, delimiter=",", skiprows=1)
    rmse = float(np.sqrt(np.mean((written[:, 1:] - performance.contractions) ** 2)))
    print(f"livebridge solve --markers auto (seed 11): contraction RMSE {rmse:.4f}")
    assert rmse <= 0.02
    assert MarkerSet.load(tmp_path / "placed.toml").names == layout.names
