"""Shared fixtures: the reference data and small seeded bases."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.face.basis import Basis
from livebridge.face.reference import ict_basis, shared_data_dir


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


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
