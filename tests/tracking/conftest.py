"""Synthetic sequences shared by the tracking tests (rendered once per session, small sizes for speed)."""

from __future__ import annotations

import pytest

from mgso import synthetic


@pytest.fixture(scope="session")
def seq160():
    """40 frames at 160x120 of the textured room (1.3 cm and 0.7 degrees a frame)."""
    return synthetic.make_sequence(seed=0, num_frames=40, width=160, height=120)


@pytest.fixture(scope="session")
def seq320():
    """12 frames at 320x240."""
    return synthetic.make_sequence(seed=0, num_frames=12, width=320, height=240)
