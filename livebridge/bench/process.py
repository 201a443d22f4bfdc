"""Take re-processing on Dask: takes/s with 1 and 2 local worker processes against this process, results equal to
serial.

Besides takes/s it reports what the figures depend on: the machine's load average before and after (other
processes share the cores), the CPU seconds a take costs in this process and on the workers (a worker's
includes its event loop: heartbeats, progress events), and the seconds to start each cluster and warm its
workers (imports, compiled kernels and the face loaded once per worker; not in takes/s). ``cores_used_*`` (CPU
seconds over wall seconds) says how much of the machine each run got: when 2 workers use no more cores than 1,
the machine's other load, not the cluster, held them back.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ARRAYS = ("t", "contractions", "positions", "displacements")


LABELLING_TIMEOUT_S = 120.0  # recording on a busy machine: the first frame set may take long to come


def _record_takes(folder: Path, count: int, frames: int) -> list[Path]:
    """``count`` demo takes with raw frames (4 simulated cameras, 640x400), ``frames`` frame sets each."""
    from livebridge.runtime.build import build_pipeline
    from livebridge.runtime.demo import demo_session
    from livebridge.runtime.pipeline import run_until_stopped

    takes = []
    for k in range(count):
        take = folder / f"take{k:02d}"
        session = demo_session(cameras=4, seed=k + 1, size=(640, 400), realtime=False, servo=False, render=False,
                               record=take, record_frames=True)
        session = replace(session, labelling_timeout_s=LABELLING_TIMEOUT_S)
        run_until_stopped(build_pipeline(session, log=lambda _m: None), frames=frames, log=lambda _m: None)
        takes.append(take)
    return takes


def _warm(take: Path, settings) -> None:
    """One take processed and thrown away: imports, compiled kernels and the face loaded before timing."""
    from livebridge.batch.reprocess import process_take

    process_take(take, settings)


def _identical(a: Path, b: Path, names) -> bool:
    from livebridge.take.npz import Take

    for name in names:
        first, second = Take.load(a / f"{name}.npz"), Take.load(b / f"{name}.npz")
        if not all(np.array_equal(getattr(first, k), getattr(second, k), equal_nan=True) for k in ARRAYS):
            return False
    return True


def _serial(jobs, settings) -> tuple[list, float, float]:
    """Outcomes, wall seconds and CPU seconds of the jobs in this process (warmed first)."""
    from livebridge.batch.runner import run_serial

    _warm(jobs[0].take, settings)
    start, cpu = time.perf_counter(), time.process_time()
    outcomes = run_serial(jobs)
    return outcomes, time.perf_counter() - start, time.process_time() - cpu


def _on_cluster(jobs, settings, workers: int, log) -> tuple[list, float, float]:
    """Outcomes, wall seconds and CPU seconds (all workers' processes) of the jobs on a new local cluster of
    ``workers`` worker processes, each warmed first."""
    from livebridge.batch.cluster import open_client, run_on_cluster

    start = time.perf_counter()
    with open_client(workers=workers) as client:
        client.run(_warm, jobs[0].take, settings)
        log(f"{workers} worker(s) started and warmed in {time.perf_counter() - start:.1f} s")
        cpu = client.run(time.process_time)
        start = time.perf_counter()
        outcomes = run_on_cluster(client, jobs)
        seconds = time.perf_counter() - start
        cpu = sum(client.run(time.process_time).values()) - sum(cpu.values())
    return outcomes, seconds, cpu


def run(quick: bool, log) -> dict:
    from livebridge.batch.jobs import ProcessSettings, plan_jobs
    from livebridge.face.builtin import builtin_basis, builtin_markers

    count, frames = (4, 30) if quick else (8, 90)
    with tempfile.TemporaryDirectory(prefix="livebridge-bench-process-") as tmp:
        folder = Path(tmp)
        builtin_basis().save(folder / "basis.npz")
        builtin_markers().save(folder / "markers.toml")
        settings = ProcessSettings("both", folder / "basis.npz", folder / "markers.toml")
        log(f"recording {count} takes of {frames} frame sets (4 cameras, 640x400, raw frames)")
        takes = _record_takes(folder / "takes", count, frames)
        names = [t.name for t in takes]
        load_before = os.getloadavg()[0]
        rate, cpu, runs = {}, {}, {}
        for label, workers in (("serial", 0), ("1_worker", 1), ("2_workers", 2)):
            out = folder / label
            out.mkdir()
            jobs = plan_jobs(takes, out, settings)
            outcomes, seconds, cpu_s = _serial(jobs, settings) if workers == 0 else \
                _on_cluster(jobs, settings, workers, log)
            failed = [o for o in outcomes if not o.ok]
            if failed:
                raise RuntimeError(f"{label}: {failed[0].name} failed: {failed[0].reason}")
            rate[label], cpu[label], runs[label] = count / seconds, cpu_s / count, out
            log(f"{label}: {count} takes in {seconds:.2f} s ({rate[label]:.2f} takes/s, "
                f"{cpu[label]:.3f} CPU s per take)")
        identical = all(_identical(runs["serial"], runs[label], names) for label in ("1_worker", "2_workers"))
    return {
        "takes": count, "frames_per_take": frames, "stage": "both", "cpus": os.cpu_count(),
        "load_average_1min_before": round(load_before, 2), "load_average_1min_after": round(os.getloadavg()[0], 2),
        **{f"takes_per_s_{label}": round(value, 3) for label, value in rate.items()},
        **{f"cpu_s_per_take_{label}": round(value, 3) for label, value in cpu.items()},
        "speedup_2_vs_1_workers": round(rate["2_workers"] / rate["1_worker"], 3),
        "speedup_2_workers_vs_serial": round(rate["2_workers"] / rate["serial"], 3),
        **{f"cores_used_{label}": round(cpu[label] * rate[label], 3) for label in rate},
        "identical_to_serial": bool(identical),
    }
