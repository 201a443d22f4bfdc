"""Marker files of other systems (C3D, TRC, CSV incl. OpenFace): round trips, other systems' layouts, the
``take show`` / ``take convert`` commands. Ground truth: a simulated performance of the built-in face."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.simulators.performer import perform
from livebridge.take.trajectories import Trajectories, read_trajectories, write_trajectories

FPS = 60.0


@pytest.fixture(scope="module")
def performance():
    from livebridge.face.builtin import builtin_basis, builtin_markers

    return perform(builtin_basis(), builtin_markers(), 40, fps=FPS, seed=5)


@pytest.fixture(scope="module")
def truth(performance) -> Trajectories:
    """The performance's marker positions with markers and whole frames unseen."""
    rng = np.random.default_rng(7)
    points = performance.marker_positions.copy()
    points[rng.random(points.shape[:2]) < 0.1] = np.nan
    points[3] = np.nan
    return Trajectories(performance.marker_names, performance.t - performance.t[0], points)


def _seen(points):
    return np.all(np.isfinite(points), axis=-1)


@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".csv", ".tsv"])
def test_a_take_written_and_read_back_equals_the_original(truth, tmp_path, suffix):
    path = write_trajectories(tmp_path / f"take{suffix}", truth)
    back = read_trajectories(path)
    assert back.names == truth.names and back.source == path
    assert np.array_equal(_seen(back.points), _seen(truth.points))
    if suffix == ".c3d":  # float32 storage, times from the header's rate
        expected = truth.points.astype(np.float32).astype(np.float64)
        np.testing.assert_array_equal(back.points, expected)
        np.testing.assert_allclose(back.t, truth.t, atol=1e-9)
        assert back.unit == "mm"
    else:  # text: the shortest repr reads back exactly
        np.testing.assert_array_equal(back.points, truth.points)
        np.testing.assert_array_equal(back.t, truth.t)
    assert back.rate == pytest.approx(FPS)


def test_c3d_stores_the_frames_nobody_recorded_as_invalid_points(truth, tmp_path):
    keep = np.ones(len(truth.t), bool)
    keep[[5, 6, 20]] = False
    holey = Trajectories(truth.names, truth.t[keep], truth.points[keep])
    back = read_trajectories(write_trajectories(tmp_path / "gaps.c3d", holey))
    assert len(back.t) == len(truth.t)
    assert not _seen(back.points)[~keep].any()
    np.testing.assert_allclose(back.points[keep], truth.points[keep], atol=1e-4)
    assert np.array_equal(_seen(back.points)[keep], _seen(truth.points)[keep])


def _raw_c3d(path, labels, points, residual, rate, units, scale):
    """A C3D written by py-c3d itself: ``points`` (n_frames, n_markers, 3) in ``units``, ``residual`` per point."""
    import c3d

    writer = c3d.Writer(point_rate=rate, point_scale=scale, point_units=units)
    writer.set_point_labels(labels)
    rows = np.concatenate([points, residual[..., None], np.zeros(residual.shape + (1,))], axis=-1)
    writer.add_frames([(frame, np.zeros((0, 0))) for frame in rows])
    with open(path, "wb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(handle)


@pytest.mark.parametrize(("units", "per_mm", "scale", "atol"), [
    ("m", 1e-3, -1.0, 1e-4), ("cm", 0.1, -1.0, 1e-4), ("mm", 1.0, 0.05, 0.051)])  # py-c3d truncates to the 16-bit grid
def test_c3d_of_other_systems_units_invalid_and_all_zero_points(truth, tmp_path, units, per_mm, scale, atol):
    mm = np.nan_to_num(truth.points[:10, :6])
    residual = np.where(np.random.default_rng(1).random(mm.shape[:2]) < 0.2, -1.0, 0.0)
    in_units = np.where(residual[..., None] < 0, 12.0, mm * per_mm)  # junk coordinates behind residual -1
    in_units[2, 1] = 0.0  # a gap as some systems write it: all zeros, residual >= 0
    labels = [f"{name}   " for name in truth.names[:6]]  # C3D pads labels with blanks
    _raw_c3d(tmp_path / "other.c3d", labels, in_units, residual, 100.0, units, scale)
    back = read_trajectories(tmp_path / "other.c3d")
    assert back.names == truth.names[:6] and back.unit == units and back.rate == pytest.approx(100.0)
    unseen = (residual < 0) | ~_seen(truth.points[:10, :6])  # the truth's NaN were written as zeros
    unseen[2, 1] = True
    assert np.array_equal(~_seen(back.points), unseen)
    np.testing.assert_allclose(back.points[~unseen], mm[~unseen], atol=atol)


def test_a_c3d_unit_the_file_states_cannot_be_contradicted_but_a_blank_one_is_given(truth, tmp_path):
    mm = np.nan_to_num(truth.points[:4, :3])
    _raw_c3d(tmp_path / "m.c3d", list(truth.names[:3]), mm / 1000, np.zeros(mm.shape[:2]), 50.0, "m", -1.0)
    with pytest.raises(InputError, match="says its unit is m"):
        read_trajectories(tmp_path / "m.c3d", "mm")
    _raw_c3d(tmp_path / "blank.c3d", list(truth.names[:3]), mm / 10, np.zeros(mm.shape[:2]), 50.0, "  ", -1.0)
    np.testing.assert_allclose(read_trajectories(tmp_path / "blank.c3d", "cm").points, truth.points[:4, :3], atol=1e-4)
    assert read_trajectories(tmp_path / "blank.c3d").unit is None


def _trc_motive(truth, n_frames: int) -> str:
    """A TRC as Motive/Pose2Sim write it: metres, six decimals, a blank line, empty cells, a trailing tab."""
    names, points = truth.names[:5], truth.points[:n_frames, :5] / 1000
    lines = ["PathFileType\t4\t(X/Y/Z)\tface.trc",
             "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
             f"60.00\t60.00\t{n_frames}\t5\tm\t60.00\t1\t{n_frames}",
             "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t\t",
             "\t\t" + "\t".join(f"{a}{k}" for k in range(1, 6) for a in "XYZ") + "\t",
             ""]
    for k in range(n_frames):
        cells = ["" if np.isnan(v) else f"{v:.6f}" for v in points[k].ravel()]
        lines.append("\t".join([str(k + 1), f"{k / 60:.6f}", *cells]) + "\t")
    return "\n".join(lines) + "\n"


def test_a_trc_as_motive_and_pose2sim_write_it(truth, tmp_path):
    (tmp_path / "face.trc").write_text(_trc_motive(truth, 12))
    back = read_trajectories(tmp_path / "face.trc")
    assert back.names == truth.names[:5] and back.unit == "m" and back.rate == pytest.approx(60.0, rel=1e-4)
    assert np.array_equal(_seen(back.points), _seen(truth.points[:12, :5]))
    np.testing.assert_allclose(back.points, truth.points[:12, :5], atol=5e-4)  # six decimals of a metre


OPENFACE_AUS = ("01", "02", "04", "05", "06", "07", "09", "10", "12", "14", "15", "17", "20", "23", "25", "26", "45")


def _openface_header() -> list[str]:
    """The columns OpenFace 2.2's FeatureExtraction writes, in order."""
    columns = ["frame", "face_id", "timestamp", "confidence", "success"]
    columns += [f"gaze_{e}_{a}" for e in (0, 1) for a in "xyz"] + ["gaze_angle_x", "gaze_angle_y"]
    columns += [f"eye_lmk_{a}_{k}" for a in "xyXYZ" for k in range(56)]
    columns += [f"pose_{p}" for p in ("Tx", "Ty", "Tz", "Rx", "Ry", "Rz")]
    columns += [f"{a}_{k}" for a in "xyXYZ" for k in range(68)]
    columns += ["p_scale", "p_rx", "p_ry", "p_rz", "p_tx", "p_ty"] + [f"p_{k}" for k in range(34)]
    columns += [f"AU{au}_r" for au in OPENFACE_AUS] + [f"AU{au}_c" for au in OPENFACE_AUS if au != "25"] + ["AU28_c"]
    return columns


def test_an_openface_csv_reads_its_3d_landmarks_in_mm(performance, tmp_path):
    header = _openface_header()
    landmarks = performance.marker_positions[:15, :68]  # the simulator's markers as landmarks 0..67
    rng = np.random.default_rng(3)
    lines = [", ".join(header)]
    for k, frame in enumerate(landmarks):
        success = 0 if k == 4 else 1
        row = dict.fromkeys(header, "0")
        row.update(frame=str(k + 1), face_id="0", timestamp=f"{k / 25:.3f}", confidence="0.98",
                   success=str(success))
        for j in range(68):
            row[f"x_{j}"], row[f"y_{j}"] = f"{rng.uniform(0, 640):.1f}", f"{rng.uniform(0, 480):.1f}"
            for axis, value in zip("XYZ", frame[j] if success else np.zeros(3)):
                row[f"{axis}_{j}"] = f"{value:.1f}"
        for au in OPENFACE_AUS:
            row[f"AU{au}_r"] = f"{rng.uniform(0, 5):.2f}"
        lines.append(", ".join(row[c] for c in header))
    (tmp_path / "openface.csv").write_text("\n".join(lines) + "\n")
    back = read_trajectories(tmp_path / "openface.csv")
    assert back.names == tuple(str(k) for k in range(68)) and back.unit == "mm"
    assert back.rate == pytest.approx(25.0)
    assert np.isnan(back.points[4]).all() and np.isfinite(np.delete(back.points, 4, axis=0)).all()
    np.testing.assert_allclose(np.delete(back.points, 4, 0), np.delete(landmarks, 4, 0), atol=0.051)
    with pytest.raises(InputError, match="says its unit is mm"):
        read_trajectories(tmp_path / "openface.csv", "m")


def test_csv_variants_other_tools_write(truth, tmp_path):
    names, points = truth.names[:3], truth.points[:8, :3]
    cells = [["NA" if np.isnan(v) else f"{v / 10:.6f}".replace(".", ",") for v in row.ravel()] for row in points]
    header = ";".join(["Frame"] + [f"{a}_{n}" for n in names for a in "XYZ"])
    text = header + "\n" + "".join(";".join([str(k), *c]) + "\n" for k, c in enumerate(cells))
    (tmp_path / "semi.csv").write_text(text)
    with pytest.raises(InputError, match="give the frame rate") as error:
        read_trajectories(tmp_path / "semi.csv", "cm")
    assert error.value.field == "line 1"
    back = read_trajectories(tmp_path / "semi.csv", "cm", rate=120.0)
    assert back.names == names and back.unit == "cm" and back.rate == pytest.approx(120.0)
    np.testing.assert_allclose(back.points, points, atol=1e-5)
    with pytest.raises(InputError, match="contradicts"):
        read_trajectories(write_trajectories(tmp_path / "ours.csv", truth), rate=30.0)


def test_take_show_prints_markers_frames_rate_unit_and_seen_fractions(truth, tmp_path):
    path = write_trajectories(tmp_path / "take.trc", truth)
    result = CliRunner().invoke(main, ["take", "show", str(path)])
    assert result.exit_code == 0, result.output
    assert f"frames: {len(truth.t)}" in result.output and "60 Hz" in result.output and "unit: mm" in result.output
    listed = " ".join(line for line in result.output.splitlines() if line.startswith("  ")).split()
    shown = dict(zip(listed[::2], listed[1::2]))
    assert shown == {name: f"{fraction:.1%}" for name, fraction in zip(truth.names, _seen(truth.points).mean(axis=0))}
    assert len(result.output.splitlines()) < 30  # short, for 69 markers


@pytest.mark.parametrize(("source", "target"), [(".csv", ".c3d"), (".c3d", ".trc"), (".trc", ".tsv"),
                                                (".npz", ".csv")])
def test_take_convert_between_formats(truth, tmp_path, source, target):
    from livebridge.take.npz import Take

    first = tmp_path / f"in{source}"
    if source == ".npz":
        Take(t=truth.t, marker_names=truth.names, positions=truth.points).save(first)
    else:
        write_trajectories(first, truth)
    result = CliRunner().invoke(main, ["take", "convert", str(first), str(tmp_path / f"out{target}")])
    assert result.exit_code == 0, result.output
    back = read_trajectories(tmp_path / f"out{target}")
    assert back.names == truth.names
    np.testing.assert_allclose(back.points, truth.points, atol=1e-4)
    again = CliRunner().invoke(main, ["take", "convert", str(first), str(tmp_path / f"out{target}")])
    assert again.exit_code != 0 and "--force" in again.output
