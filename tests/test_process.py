"""livebridge process: recorded takes re-processed on a Dask LocalCluster (2 workers on 127.0.0.1) equal the
serial run bit for bit; a damaged take is reported while the others finish."""

from __future__ import annotations

import shutil
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.batch.jobs import ProcessSettings, plan_jobs
from livebridge.batch.runner import run_serial
from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.take.directory import load_take_dir
from livebridge.take.npz import Take

pytest.importorskip("distributed")
ARRAYS = ("t", "contractions", "positions", "displacements")


def _quiet(_message):
    pass


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    """Three short demo takes recorded with raw frames (3 simulated cameras, 320x200), and the built-in face
    saved as files (workers load them in milliseconds; the built-in marker design takes seconds)."""
    from livebridge.face.builtin import builtin_basis, builtin_markers
    from livebridge.runtime.demo import build_demo
    from livebridge.runtime.pipeline import run_until_stopped

    folder = tmp_path_factory.mktemp("takes")
    builtin_basis().save(folder / "basis.npz")
    builtin_markers().save(folder / "markers.toml")
    paths = []
    for k in range(3):
        take = folder / f"take{k}"
        parts = build_demo(cameras=3, seed=k + 1, size=(320, 200), realtime=False, servo=False, render=False,
                           record=take, record_frames=True, log=_quiet)
        run_until_stopped(parts.pipeline, frames=12 + 4 * k, log=_quiet)
        paths.append(take)
    return folder, paths


@pytest.fixture(scope="module")
def client():
    from livebridge.batch.cluster import open_client

    with open_client(workers=2) as client:
        yield client


def _settings(folder, stage):
    return ProcessSettings(stage, folder / "basis.npz", folder / "markers.toml")


def _results(out, names):
    return {name: Take.load(out / f"{name}.npz") for name in names}


def test_reconstruct_replays_the_live_pipeline(takes, tmp_path):
    """The raw frames through the batch's reconstruction give the contractions the live pipeline recorded."""
    folder, paths = takes
    outcomes = run_serial(plan_jobs(paths, tmp_path, _settings(folder, "reconstruct")))
    assert all(o.ok for o in outcomes), outcomes
    for path in paths:
        live, again = load_take_dir(path), load_take_dir(tmp_path / path.name)
        assert again.complete and again.n_frames >= 0.9 * live.n_frames
        common, in_live, in_again = np.intersect1d(live.seq, again.seq, return_indices=True)
        assert len(common) >= 0.9 * live.n_frames
        assert np.abs(live.contractions[in_live] - again.contractions[in_again]).max() < 1e-5  # CSV: 6 decimals


def test_cluster_equals_serial_bit_for_bit(takes, client, tmp_path):
    from livebridge.batch.cluster import run_on_cluster

    folder, paths = takes
    serial, cluster = tmp_path / "serial", tmp_path / "cluster"
    serial.mkdir(), cluster.mkdir()
    settings = _settings(folder, "both")
    assert all(o.ok for o in run_serial(plan_jobs(paths, serial, settings)))
    events, done = [], []
    outcomes = run_on_cluster(client, plan_jobs(paths, cluster, settings), lambda *e: events.append(e), done.append)
    assert [o.name for o in outcomes] == [p.name for p in paths] and all(o.ok for o in outcomes), outcomes
    assert sorted(o.name for o in done) == sorted(p.name for p in paths)
    names = [p.name for p in paths]
    a, b = _results(serial, names), _results(cluster, names)
    for name in names:
        for array in ARRAYS:
            assert np.array_equal(getattr(a[name], array), getattr(b[name], array), equal_nan=True), (name, array)
        assert a[name].contractions.shape[0] == next(o.frames for o in outcomes if o.name == name) > 0
        for file in ("contractions.csv", "markers.csv", "displacements.csv"):
            assert (serial / name / file).read_bytes() == (cluster / name / file).read_bytes()
    for name in names:  # every take reported its progress, up to its last frame set
        last = [e for e in events if e[0] == name][-1]
        assert last[1] == last[2]


def test_a_damaged_take_is_reported_and_the_others_finish(takes, client, tmp_path):
    from livebridge.batch.cluster import run_on_cluster

    folder, paths = takes
    damaged = tmp_path / "damaged"
    shutil.copytree(paths[1], damaged)
    lines = (damaged / "markers.csv").read_text().splitlines(keepends=True)
    (damaged / "markers.csv").write_text("".join(lines[:3]) + "3,4,x,1\n" + "".join(lines[4:]))
    missing = tmp_path / "missing"
    shutil.copytree(paths[2], missing)
    (missing / "contractions.csv").unlink()
    out = tmp_path / "out"
    out.mkdir()
    jobs = plan_jobs([paths[0], damaged, missing], out, _settings(folder, "solve"))
    outcomes = {o.name: o for o in run_on_cluster(client, jobs)}
    assert outcomes[paths[0].name].ok and (out / f"{paths[0].name}.npz").is_file()
    assert not outcomes["damaged"].ok and "markers.csv" in outcomes["damaged"].reason
    assert "line 4" in outcomes["damaged"].reason
    assert not outcomes["missing"].ok and "contractions.csv" in outcomes["missing"].reason
    assert not (out / "damaged").exists() and not (out / "missing.npz").exists()
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []  # nothing half written


def test_cli_on_a_scheduler_reports_failures_and_keeps_results(takes, client, tmp_path):
    folder, paths = takes
    bad = tmp_path / "bad"
    shutil.copytree(paths[0], bad)
    (bad / "take.toml").write_text("format = 'livebridge-take-dir'\nversion = 9\n")
    out = tmp_path / "out"
    out.mkdir()
    args = ["process", str(paths[0]), str(bad), "--out", str(out), "--basis", str(folder / "basis.npz"),
            "--markers", str(folder / "markers.toml"), "--stage", "solve", "--scheduler", client.scheduler.address]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 1, result.output
    assert "bad: FAILED" in result.output and "version" in result.output
    assert "processed 1 of 2 takes" in result.output
    written = Take.load(out / f"{paths[0].name}.npz")
    again = CliRunner().invoke(main, args)  # results are never overwritten without --force
    assert again.exit_code == 1 and "already exists" in again.output and "--force" in again.output
    forced = CliRunner().invoke(main, [*args[:1], str(paths[0]), *args[3:], "--force"])
    assert forced.exit_code == 0, forced.output
    assert np.array_equal(Take.load(out / f"{paths[0].name}.npz").contractions, written.contractions)


def test_a_take_without_raw_frames_cannot_be_reconstructed(takes, tmp_path):
    folder, paths = takes
    bare = tmp_path / "bare"
    shutil.copytree(paths[0], bare, ignore=shutil.ignore_patterns("frames"))
    out = tmp_path / "out"
    out.mkdir()
    result = CliRunner().invoke(main, ["process", str(bare), "--out", str(out), "--workers", "0", "--stage",
                                       "reconstruct", "--basis", str(folder / "basis.npz"), "--markers",
                                       str(folder / "markers.toml")])
    assert result.exit_code == 1 and "bare: FAILED" in result.output and "raw frames" in result.output


def test_without_dask_the_error_names_the_extra(monkeypatch):
    from livebridge.batch.cluster import open_client

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(InputError, match=r"livebridge\[cluster\]"), open_client(workers=1):
        pass
