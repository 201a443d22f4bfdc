"""Run calibration single-threaded: repeatable results and no thread thrash on busy machines.

OpenCV's parallel ``calibrateCamera`` does not give bit-identical results run to run, and a
multi-threaded OpenBLAS spends most of LSMR's many tiny vector norms waking threads when the
cores are busy (about 8x slower here). Both are limited for the duration of a ``with`` block.
OpenBLAS is found among the loaded libraries (Linux ``/proc/self/maps``); elsewhere its
threads are left alone (results are still deterministic for a fixed thread count).
"""

from __future__ import annotations

import ctypes
from contextlib import contextmanager
from pathlib import Path

_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads64_",
            "openblas_set_num_threads")
_GETTERS = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads", "openblas_get_num_threads64_",
            "openblas_get_num_threads")


def _openblas_libraries() -> list[tuple]:
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return []
    found = []
    paths = sorted({line.split()[-1] for line in maps.read_text().splitlines()
                    if "openblas" in line.lower() and line.split()[-1].startswith("/")})
    for path in paths:
        try:
            library = ctypes.CDLL(path)
        except OSError:
            continue
        setter = next((getattr(library, n) for n in _SETTERS if hasattr(library, n)), None)
        getter = next((getattr(library, n) for n in _GETTERS if hasattr(library, n)), None)
        if setter is not None and getter is not None:
            getter.restype = ctypes.c_int
            found.append((setter, getter))
    return found


@contextmanager
def single_threaded():
    """Limit OpenCV and OpenBLAS to one thread inside the block, restoring them afterwards."""
    import cv2

    previous_cv = cv2.getNumThreads()
    libraries = _openblas_libraries()
    previous_blas = [getter() for _, getter in libraries]
    cv2.setNumThreads(1)
    for setter, _ in libraries:
        setter(1)
    try:
        yield
    finally:
        cv2.setNumThreads(previous_cv)
        for (setter, _), count in zip(libraries, previous_blas):
            setter(count)
