"""Shared fixtures: Warp on the CPU (tests never need a GPU), the real-data folder, deterministic seeds."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mgso.io.paths import shared_data_dir


@pytest.fixture(scope="session")
def wp_device():
    """Warp initialised once for the test session, on the CPU unless MGSO_TEST_DEVICE says otherwise."""
    from mgso_kernels import runtime

    return runtime.init(os.environ.get("MGSO_TEST_DEVICE", "cpu"))


@pytest.fixture(scope="session", autouse=True)
def _unnamed_device_is_the_test_device():
    """mgso has no default device: an object made without ``device=`` runs on the CPU
    (``mgso_kernels.runtime.device_or_cpu``). Many tests make helpers without naming one; when the suite runs on a
    GPU (``MGSO_TEST_DEVICE=cuda``) those follow the test device, so that a test never mixes a CPU object with the
    GPU arrays it is given. Nothing changes on the CPU."""
    name = os.environ.get("MGSO_TEST_DEVICE", "cpu")
    if name == "cpu":
        yield
        return
    from mgso_kernels import runtime

    original = runtime.device_or_cpu

    def follow_the_test_device(device):
        return original(device if device is not None else name)

    follow_the_test_device.unpatched = original     # what mgso itself does (tests of the rule itself use it)
    runtime.device_or_cpu = follow_the_test_device
    try:
        yield
    finally:
        runtime.device_or_cpu = original


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``../shared/data`` (or ``$MGSO_DATA``); tests that need it skip when it is absent."""
    d = shared_data_dir()
    if d is None:
        pytest.skip("real recordings not found: set MGSO_DATA or place them in ../shared/data")
    return d


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
