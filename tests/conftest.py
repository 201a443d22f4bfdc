"""Shared fixtures: the reference data (``../shared/data`` or ``$LIVEBRIDGE_SHARED_DATA``, found by
:mod:`livebridge.bench.data`), a face basis and a seeded RNG."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.bench.data import ict_basis, shared_data_dir
from livebridge.face.basis import Basis


@pytest.fixture(scope="session")
def shared_data():
    """``../shared/data``; tests that need it skip on a machine without it."""
    path = shared_data_dir()
    if path is None:
        pytest.skip("reference data ../shared/data not present")
    return path


@pytest.fixture(scope="session")
def ict(shared_data) -> Basis:
    """The 16-muscle Choe-Ko basis built from ICT-FaceKit."""
    return ict_basis()


@pytest.fixture(scope="session")
def face_basis() -> Basis:
    """The ICT face when the reference data is here, else the built-in face."""
    basis = ict_basis()
    if basis is None:
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
    return basis


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
