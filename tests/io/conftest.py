"""Fixtures of tests/io: a factory of tiny fake datasets (io_fakes.py)."""

from __future__ import annotations

import pytest
from io_fakes import Fakes


@pytest.fixture
def fakes(tmp_path) -> Fakes:
    return Fakes(tmp_path)
