"""Take re-processing on Dask: takes/s with 1 and 2 local workers against this process, results equal to serial."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

ARRAYS = ("t", "contractions", "positions", "displacements")


def _record_takes(folder: Path, count: int, frames: int) -> list[Path]:
    """``count`` demo takes with raw frames (4 simulated cameras, 640x400), ``frames`` frame sets each."""
    from livebridge.runtime.demo import build_demo
    from livebridge.runtime.pipeline import run_until_stopped

    takes = []
    for k in range(count):
        take = folder / f"take{k:02d}"
        parts = build_demo(cameras=4, seed=k + 1, size=(640, 400), realtime=False, servo=False, render=False,
                           record=take, record_frames=True, log=lambda _m: None)
        run_until_stopped(parts.pipeline, frames=frames, log=lambda _m: None)
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


def run(quick: bool, log) -> dict:
    from livebridge.batch.cluster import open_client, run_on_cluster
    from livebridge.batch.jobs import ProcessSettings, plan_jobs
    from livebridge.batch.runner import run_serial
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
        figures, runs = {}, {}
        for label, workers in (("serial", 0), ("1_worker", 1), ("2_workers", 2)):
            out = folder / label
            out.mkdir()
            jobs = plan_jobs(takes, out, settings)
            if workers == 0:
                _warm(takes[0], settings)
                start = time.perf_counter()
                outcomes = run_serial(jobs)
            else:
                with open_client(workers=workers) as client:
                    client.run(_warm, takes[0], settings)
                    start = time.perf_counter()
                    outcomes = run_on_cluster(client, jobs)
            seconds = time.perf_counter() - start
            failed = [o for o in outcomes if not o.ok]
            if failed:
                raise RuntimeError(f"{label}: {failed[0].name} failed: {failed[0].reason}")
            figures[f"takes_per_s_{label}"] = count / seconds
            runs[label] = out
            log(f"{label}: {count} takes in {seconds:.2f} s ({count / seconds:.2f} takes/s)")
        identical = all(_identical(runs["serial"], runs[label], names) for label in ("1_worker", "2_workers"))
    return {
        "takes": count, "frames_per_take": frames, "stage": "both", "cpus": os.cpu_count(),
        "takes_per_s_serial": round(figures["takes_per_s_serial"], 3),
        "takes_per_s_1_worker": round(figures["takes_per_s_1_worker"], 3),
        "takes_per_s_2_workers": round(figures["takes_per_s_2_workers"], 3),
        "speedup_2_vs_1_workers": round(figures["takes_per_s_2_workers"] / figures["takes_per_s_1_worker"], 3),
        "speedup_2_workers_vs_serial": round(figures["takes_per_s_2_workers"] / figures["takes_per_s_serial"], 3),
        "identical_to_serial": bool(identical),
    }
