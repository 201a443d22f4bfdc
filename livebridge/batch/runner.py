"""Running jobs: one take (:func:`run_job`, what a cluster worker calls) and a batch in this process
(:func:`run_serial`, the reference a cluster's results must equal bit for bit)."""

from __future__ import annotations

import time
from collections.abc import Callable

from livebridge.batch.jobs import TakeJob, TakeOutcome
from livebridge.batch.outputs import write_results
from livebridge.batch.reprocess import Progress, process_take
from livebridge.errors import InputError

OnProgress = Callable[[str, int, "int | None"], None]
"""``on_progress(take_name, frames_done, frames_total or None)``."""
OnDone = Callable[[TakeOutcome], None]


def run_job(job: TakeJob, progress: Progress | None = None) -> TakeOutcome:
    """Process one take and write its results; a take that cannot be processed (damaged, a file missing, a
    basis or marker set that does not fit it, results that cannot be written) is a failed outcome naming why,
    not an exception, so the batch goes on."""
    start = time.perf_counter()
    try:
        result = process_take(job.take, job.settings, progress)
        write_results(job, result)
    except InputError as error:
        return TakeOutcome(job.name, False, 0, time.perf_counter() - start, str(error))
    except OSError as error:  # a file vanished or cannot be read mid-way
        return TakeOutcome(job.name, False, 0, time.perf_counter() - start, f"{error.filename}: {error.strerror}")
    return TakeOutcome(job.name, True, result.n_frames, time.perf_counter() - start)


def run_serial(jobs: list[TakeJob], on_progress: OnProgress | None = None,
               on_done: OnDone | None = None) -> list[TakeOutcome]:
    """Every job in turn in this process; outcomes in the jobs' order."""
    outcomes = []
    for job in jobs:
        progress = None if on_progress is None else (lambda done, total, name=job.name: on_progress(name, done, total))
        outcome = run_job(job, progress)
        if on_done is not None:
            on_done(outcome)
        outcomes.append(outcome)
    return outcomes
