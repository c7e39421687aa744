"""The one error type of dataset reading."""

from __future__ import annotations

from contextlib import contextmanager

from ..camera import CalibrationError
from .trajectory import TrajectoryError

__all__ = ["DatasetError", "as_dataset_errors"]


class DatasetError(ValueError):
    """A dataset is missing, malformed or inconsistent; the message names the file and the problem."""


@contextmanager
def as_dataset_errors(context: str = ""):
    """Re-raise calibration and trajectory errors (whose messages already name the file) as :class:`DatasetError`."""
    try:
        yield
    except (CalibrationError, TrajectoryError) as exc:
        msg = f"{context}: {exc}" if context else str(exc)
        raise DatasetError(msg) from exc
