"""The real third-party reference data (ICT-FaceKit, a stereo chessboard) for benchmarks and tests.

The data is never copied into the package, and the product never looks for it: it is read from
``../shared/data`` beside the checkout, or from ``$LIVEBRIDGE_SHARED_DATA``. Tests reach it through the
``shared_data`` and ``ict`` fixtures of ``tests/conftest.py``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from livebridge.face.basis import Basis

_REPO_ROOT = Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path | None:
    """The reference-data folder, or None when this machine has none."""
    candidates = [os.environ.get("LIVEBRIDGE_SHARED_DATA"), _REPO_ROOT.parent / "shared" / "data",
                  Path.cwd().parent / "shared" / "data"]
    for candidate in candidates:
        if candidate and (Path(candidate) / "ict-facekit").is_dir():
            return Path(candidate)
    return None


def ict_basis() -> Basis | None:
    """The 16-muscle Choe-Ko basis built from ICT-FaceKit's face region, or None without the data."""
    from livebridge.face.basis_import import import_basis

    data = shared_data_dir()
    if data is None:
        return None
    return import_basis("choe-ko-ict", data / "ict-facekit" / "face_region.npz")


ICT_EYE_MATERIALS = {"M_ScleraLeft": False, "M_ScleraRight": False, "M_IrisLeft": True, "M_IrisRight": True}
"""The ICT head's eyeball materials, and whether each is an iris."""


def ict_eyeballs():
    """The ICT head's eyeballs (:class:`~livebridge.bench.scan_eyes.Eyeballs`, mm, in its face region's frame)
    from its neutral OBJ, or None without the data."""
    from livebridge.bench.scan_eyes import Eyeballs
    from livebridge.face.basis_import import UNITS_TO_MM
    from livebridge.face.obj_file import read_obj_data

    data = shared_data_dir()
    if data is None:
        return None
    path = data / "ict-facekit" / "obj" / "generic_neutral_mesh.obj"
    obj = read_obj_data(path.read_bytes(), path)
    eye = np.flatnonzero([name in ICT_EYE_MATERIALS for name in obj.face_material])
    used, triangles = np.unique(obj.triangles[eye], return_inverse=True)
    iris = np.array([ICT_EYE_MATERIALS[obj.face_material[k]] for k in eye])
    return Eyeballs(obj.points[used] * UNITS_TO_MM["cm"], triangles.reshape(-1, 3), iris)
