"""``livebridge process``: re-process many recorded takes (reconstruction and/or solve), in parallel on a Dask
cluster."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import click

from livebridge.cli._options import InputPath, force_option
from livebridge.cli.markers import BASIS_HELP, BASIS_TYPE

STAGE_HELP = ("reconstruct: the raw frames through the live path's detection, reconstruction and solver (takes "
              "recorded with --record-frames / raw_frames = true); solve: the take's labelled markers through the "
              "offline solve (as `livebridge solve`); both: reconstruct, then solve the markers found.")


class _Bars:
    """tqdm bars on stderr: one for the batch (takes done) and one per take being processed (frame sets)."""

    def __init__(self, total: int):
        from tqdm import tqdm

        self._tqdm = tqdm
        self._lock = threading.Lock()
        self.overall = tqdm(total=total, unit="take", desc="takes", position=0)
        self.takes: dict = {}
        self.failed = 0

    def progress(self, name: str, done: int, total: int | None) -> None:
        with self._lock:
            bar = self.takes.get(name)
            if bar is None:
                bar = self.takes[name] = self._tqdm(total=total, unit="frame set", desc=name, leave=False)
            bar.update(done - bar.n)

    def done(self, outcome) -> None:
        with self._lock:
            bar = self.takes.pop(outcome.name, None)
            if bar is not None:
                bar.close()
            self.failed += not outcome.ok
            self.overall.set_postfix(failed=self.failed, refresh=False)
            self.overall.update(1)

    def close(self) -> None:
        for bar in self.takes.values():
            bar.close()
        self.overall.close()


@click.command("process")
@click.argument("takes", nargs=-1, required=True, type=InputPath("folder"))
@click.option("--out", required=True, type=InputPath("folder"),
              help="Existing folder for the results: per take NAME/ (a take directory) and NAME.npz (full precision).")
@click.option("--stage", type=click.Choice(["reconstruct", "solve", "both"]), default="solve", show_default=True,
              help=STAGE_HELP)
@click.option("--basis", "basis_spec", type=BASIS_TYPE, default="builtin", show_default=True, help=BASIS_HELP)
@click.option("--markers", "markers_spec", default="builtin", show_default=True,
              help="Marker set (.toml, or a shipped set: builtin, builtin-68, ict-68); a take's markers are matched "
              "to it by name.")
@click.option("--calibration", type=InputPath(), default=None,
              help="With reconstruct: the rig's calibration (default: each take's own, recorded with it).")
@click.option("--mode", type=click.Choice(["split-compensated", "split", "joint"]), default="split-compensated",
              show_default=True, help="Solver region mode.")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="An existing Dask scheduler to run on (default: a local cluster on 127.0.0.1).")
@click.option("--workers", type=click.IntRange(0, 1024), default=None,
              help="Worker processes of the local cluster (default 2; 0: process in this process, without Dask).")
@force_option
def process(takes: tuple[Path, ...], out: Path, stage: str, basis_spec: str, markers_spec: str,
            calibration: Path | None, mode: str, scheduler: str | None, workers: int | None, force: bool) -> None:
    """Re-process recorded take directories TAKES... in parallel: reconstruction and/or solve.

    Each take's result equals what the same take gives processed alone, bit for bit. A take that fails
    (damaged, a file missing, a basis that does not fit) is reported with the reason; the others finish, and
    the exit status is 1.
    """
    from livebridge.batch.jobs import ProcessSettings, plan_jobs
    from livebridge.errors import InputError
    from livebridge.face import SHIPPED_MARKER_SETS

    if scheduler is not None and workers is not None:
        raise click.BadParameter("give --scheduler or --workers, not both", param_hint="--workers")
    if scheduler is not None:
        from livebridge.batch.cluster import check_scheduler_address

        check_scheduler_address(scheduler)
    if calibration is not None and stage == "solve":
        raise click.BadParameter("only with --stage reconstruct or both", param_hint="--calibration")
    if markers_spec not in SHIPPED_MARKER_SETS and not Path(markers_spec).is_file():
        raise InputError("marker set not found", markers_spec, "--markers")
    settings = ProcessSettings(stage, basis_spec, markers_spec, calibration, mode)
    jobs = plan_jobs(takes, out, settings, force)
    _check_face(basis_spec, markers_spec)
    started = time.perf_counter()
    bars = _Bars(len(jobs))
    try:
        outcomes = _run(jobs, scheduler, 2 if workers is None else workers, bars)
    finally:
        bars.close()
    _report(outcomes, out, time.perf_counter() - started)


def _check_face(basis_spec: str, markers_spec: str) -> None:
    """A basis or marker-set file that cannot be read, or that does not fit, fails before any take is tried."""
    if basis_spec != "builtin" or Path(markers_spec).is_file():
        from livebridge.batch.reprocess import load_face

        load_face(basis_spec, markers_spec)


def _run(jobs, scheduler: str | None, workers: int, bars: _Bars):
    if scheduler is None and workers == 0:
        from livebridge.batch.runner import run_serial

        return run_serial(jobs, bars.progress, bars.done)
    from livebridge.batch.cluster import open_client, run_on_cluster

    with open_client(scheduler, workers) as client:
        return run_on_cluster(client, jobs, bars.progress, bars.done)


def _report(outcomes, out: Path, seconds: float) -> None:
    for outcome in outcomes:
        if outcome.ok:
            click.echo(f"{outcome.name}: {outcome.frames} frame sets -> {out / outcome.name}/, "
                       f"{out / outcome.name}.npz ({outcome.seconds:.1f} s)")
        else:
            click.echo(f"{outcome.name}: FAILED: {outcome.reason}", err=True)
    failed = [o.name for o in outcomes if not o.ok]
    click.echo(f"processed {len(outcomes) - len(failed)} of {len(outcomes)} takes in {seconds:.1f} s"
               + (f"; failed: {', '.join(failed)}" if failed else ""))
    if failed:
        raise click.exceptions.Exit(1)
