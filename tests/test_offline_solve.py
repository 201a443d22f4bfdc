"""livebridge solve: an offline solve of a marker file equals the live path's solver and meets ground truth."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.face.builtin import builtin_basis, builtin_markers
from livebridge.simulators.performer import perform
from livebridge.solve.offline import NeutralChoice, match_markers, neutral_for_set, solve_positions
from livebridge.solve.solver import ContractionSolver
from livebridge.take.trajectories import Trajectories


@pytest.fixture(scope="module")
def take():
    """A head-moving everyday take on the built-in face with its designed markers (ground truth attached)."""
    return perform(builtin_basis(), builtin_markers(), 300, seed=3, script="everyday")


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


def test_cli_solve_equals_the_live_solver_and_meets_ground_truth(take, tmp_path):
    path = tmp_path / "take.npz"
    take.to_take().save(path)
    builtin_markers().save(tmp_path / "markers.toml")
    out = tmp_path / "c.csv"
    result = CliRunner().invoke(main, ["solve", str(path), "--markers", str(tmp_path / "markers.toml"),
                                       "--out", str(out), "--take", str(tmp_path / "solved.npz")])
    assert result.exit_code == 0, result.output
    assert "neutral frame" in result.output and "chosen automatically" in result.output
    with out.open() as stream:
        rows = list(csv.reader(stream))
    assert rows[0] == ["time", *builtin_basis().names]
    written = np.array(rows[1:], dtype=float)
    np.testing.assert_allclose(written[:, 0], take.t, atol=1e-9)
    # the live path's solver on the ground-truth model-frame displacements
    live = ContractionSolver(builtin_basis(), builtin_markers()).solve_take(take.marker_displacements)
    np.testing.assert_allclose(written[:, 1:], live.contractions, atol=1e-9)
    rmse = _rmse(written[:, 1:], take.contractions)
    print(f"offline solve, designed markers, head moving: contraction RMSE {rmse:.4f}")
    assert rmse <= 0.02
    rms_rows = (tmp_path / "c.rms.csv").read_text().splitlines()
    assert rms_rows[0] == "time,upper_rms_mm,lower_rms_mm" and len(rms_rows) == take.n_frames + 1
    assert (tmp_path / "c.png").stat().st_size > 1000 and (tmp_path / "solved.npz").is_file()


def test_same_displacements_same_contractions(take):
    basis, markers = builtin_basis(), builtin_markers()
    # a take that starts mid-expression: the neutral frame is found later, at rest
    start = int(np.argmax(take.contractions.max(axis=1) > 0.3))
    positions = take.marker_positions[start:]
    choice = neutral_for_set(positions, basis, markers, None)
    assert take.contractions[start + choice.frame].max() < 0.05, choice.reason
    result = solve_positions(take.t[start:], positions, basis, markers, choice)
    again = ContractionSolver(basis, result.markers).solve_take(result.displacements)
    np.testing.assert_allclose(result.solution.contractions, again.contractions, atol=1e-9)
    assert _rmse(result.solution.contractions, take.contractions[start:]) <= 0.02


def test_without_head_markers_the_pose_comes_from_the_steadiest_face_markers(take):
    basis, markers = builtin_basis(), builtin_markers()
    face = markers.subset(markers.face_mask)
    positions = take.marker_positions[:, markers.face_mask]
    result = solve_positions(take.t, positions, basis, face, NeutralChoice(0, "given"))
    rmse = _rmse(result.solution.contractions, take.contractions)
    print(f"offline solve without head markers: contraction RMSE {rmse:.4f}")
    # measured 0.0003 (0.040 from the weighted rigid fit alone, which leans on markers the expression moves a
    # little): the pose refitted to the positions the solved contractions predict, until they settle
    assert rmse <= 0.01


def test_markers_are_matched_by_name_and_mismatches_named(take):
    markers = builtin_markers()
    order = np.random.default_rng(0).permutation(len(markers))
    names = tuple(markers.names[i] for i in order)
    trajectories = Trajectories(names, take.t, take.marker_positions[:, order])
    np.testing.assert_array_equal(match_markers(trajectories, markers), take.marker_positions)
    renamed = Trajectories(("stray",) + names[1:], take.t, take.marker_positions[:, order])
    with pytest.raises(InputError, match=f"missing from the file: '{names[0]}'.*not in the marker set: 'stray'"):
        match_markers(renamed, markers)


def test_neutral_frame_out_of_range_names_the_option(take, tmp_path):
    path = tmp_path / "take.npz"
    take.to_take().save(path)
    builtin_markers().save(tmp_path / "markers.toml")
    result = CliRunner().invoke(main, ["solve", str(path), "--markers", str(tmp_path / "markers.toml"),
                                       "--neutral-frame", "5000", "--out", str(tmp_path / "c.csv")])
    assert result.exit_code != 0 and "--neutral-frame" in result.output and "outside the take" in result.output


def _solve_cli(path, tmp_path, *options) -> np.ndarray:
    """``livebridge solve`` through the command line; the contractions it wrote, shape (n_frames, n_muscles)."""
    out = tmp_path / f"{path.stem}-{path.suffix[1:]}.csv"
    result = CliRunner().invoke(main, ["solve", str(path), "--out", str(out), *options])
    assert result.exit_code == 0, result.output
    return np.loadtxt(out, delimiter=",", skiprows=1)[:, 1:]


def test_every_marker_file_format_solves_as_the_take_it_was_exported_from(take, tmp_path):
    """The same take as .npz, TRC, CSV and C3D: the same contractions (C3D stores float32 coordinates)."""
    from livebridge.take.trajectories import read_trajectories, write_trajectories

    builtin_markers().save(tmp_path / "markers.toml")
    options = ("--markers", str(tmp_path / "markers.toml"), "--neutral-frame", "0")
    take.to_take().save(tmp_path / "take.npz")
    reference = _solve_cli(tmp_path / "take.npz", tmp_path, *options)
    trajectories = read_trajectories(tmp_path / "take.npz")
    for suffix, atol in ((".trc", 1e-9), (".csv", 1e-9), (".c3d", 2e-3)):
        write_trajectories(tmp_path / f"take{suffix}", trajectories)
        contractions = _solve_cli(tmp_path / f"take{suffix}", tmp_path, *options)
        np.testing.assert_allclose(contractions, reference, atol=atol, err_msg=suffix)
    assert _rmse(reference, take.contractions) <= 0.02


def test_an_openface_landmark_file_solves_with_the_68_point_set(tmp_path):
    """OpenFace's CSV layout (3D landmarks X_0..Z_67 in mm with one decimal, as OpenFace writes them, numbered)
    against builtin-68, matched by number."""
    from livebridge.face.builtin import builtin_landmarks

    performance = perform(builtin_basis(), builtin_landmarks(), 240, fps=30.0, seed=5, script="everyday")
    points = performance.marker_positions
    header = ["frame", " face_id", " timestamp", " confidence", " success"]
    header += [f" {axis}_{k}" for axis in "XYZ" for k in range(68)] + [" AU01_r", " AU12_r"]
    lines = [",".join(header)]
    for k, frame in enumerate(points):
        values = [str(k + 1), "0", f"{k / 30:.3f}", "0.98", "1"]
        values += [f"{frame[j, axis]:.1f}" for axis in range(3) for j in range(68)] + ["0.00", "1.20"]
        lines.append(", ".join(values))
    (tmp_path / "openface.csv").write_text("\n".join(lines) + "\n")
    contractions = _solve_cli(tmp_path / "openface.csv", tmp_path, "--markers", "builtin-68")
    rmse = _rmse(contractions, performance.contractions)
    print(f"OpenFace CSV layout, builtin-68: contraction RMSE {rmse:.4f}")
    assert rmse <= 0.03
