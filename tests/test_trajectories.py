"""Labelled marker trajectories read from livebridge's own takes."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.take.npz import Take
from livebridge.take.trajectories import read_trajectories


def test_an_npz_take_reads_as_trajectories_from_its_first_frame(tmp_path, rng):
    positions = rng.normal(size=(5, 3, 3)) * 50
    positions[2, 1] = np.nan
    path = tmp_path / "take.npz"
    Take(t=10 + np.arange(5) / 60, marker_names=("a", "b", "c"), positions=positions).save(path)
    traj = read_trajectories(path)
    assert traj.names == ("a", "b", "c") and traj.source == path
    np.testing.assert_allclose(traj.t, np.arange(5) / 60, atol=1e-12)
    np.testing.assert_array_equal(traj.points, positions)
    assert traj.rate == pytest.approx(60.0)


@pytest.mark.parametrize(("name", "units", "message"), [
    ("take.npz", "inch", "unknown unit"), ("take.xyz", None, "unknown marker-file type"),
    ("missing.npz", None, "file not found")])
def test_bad_requests_name_the_file(tmp_path, name, units, message):
    with pytest.raises(InputError, match=message) as error:
        read_trajectories(tmp_path / name, units)
    assert error.value.path == str(tmp_path / name)


def test_a_take_without_positions_is_refused(tmp_path):
    path = tmp_path / "take.npz"
    Take(t=np.arange(3) / 30, marker_names=("a",), displacements=np.zeros((3, 1, 3))).save(path)
    with pytest.raises(InputError, match="no marker positions"):
        read_trajectories(path)
