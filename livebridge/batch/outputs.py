"""A processed take on disk: a take directory (``out/NAME/``, what the recorder writes, so ``take show``,
``replay`` of its markers, ``export-c3d`` and ``play`` read it) and the same take at full precision
(``out/NAME.npz``, :class:`livebridge.take.npz.Take`, for ``basis check`` / ``basis refine`` and for
comparing runs bit for bit).

Nothing is half written: the take directory is written under a hidden name beside its place and renamed
into it, the ``.npz`` by :func:`livebridge.atomic.write_atomically`.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from livebridge.atomic import write_atomically
from livebridge.batch.jobs import TakeJob
from livebridge.batch.reprocess import ProcessedTake
from livebridge.errors import InputError


def write_results(job: TakeJob, result: ProcessedTake) -> None:
    """Write ``result`` as ``job.take_out`` and ``job.npz_out`` (replacing them only when ``job.force``)."""
    for path in (job.take_out, job.npz_out):
        if path.exists() and not job.force:
            raise InputError("already exists; add --force to overwrite it", path, "--out")
    _write_take_dir(job.take_out, result)
    write_atomically(job.npz_out, lambda handle: _take(result).save(handle), "take (.npz)")


def _take(result: ProcessedTake):
    from livebridge.take.npz import Take

    return Take(result.t, result.marker_names, displacements=result.displacements, positions=result.positions,
                contractions=result.contractions, muscle_names=result.muscle_names, fps=result.fps)


def _write_take_dir(target: Path, result: ProcessedTake) -> None:
    from livebridge.take.recorder import TakeRecorder

    staging = target.with_name(f".{target.name}.partial")
    old = target.with_name(f".{target.name}.old")
    for leftover in (staging, old):  # from a run that was killed
        shutil.rmtree(leftover, ignore_errors=True)
    try:
        with TakeRecorder(staging, result.muscle_names, result.marker_names, calibration_file=result.calibration,
                          fps=result.fps) as recorder:
            for k in range(result.n_frames):
                recorder.record(int(result.seq[k]), float(result.t[k]), result.contractions[k], result.positions[k],
                                result.displacements[k], tuple(result.region_errors[k]))
        if target.exists():
            os.replace(target, old)
        os.replace(staging, target)
    except OSError as error:
        raise InputError(f"cannot write the take ({error.strerror or error})", target) from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
