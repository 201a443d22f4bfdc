"""Run calibration single-threaded: repeatable results and no thread thrash on busy machines.

OpenCV's parallel ``calibrateCamera`` does not give bit-identical results run to run, and a
multi-threaded BLAS spends most of LSMR's many tiny vector norms waking threads when the cores
are busy (about 8x slower here). Both are limited for the duration of a ``with`` block.
"""

from __future__ import annotations

from contextlib import contextmanager


@contextmanager
def single_threaded():
    """Limit OpenCV and BLAS to one thread inside the block, restoring them afterwards."""
    import cv2
    from threadpoolctl import threadpool_limits

    previous_cv = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
    finally:
        cv2.setNumThreads(previous_cv)
