"""Warp kernels of mgso: kernels, ``@wp.func`` helpers and thin launchers.

This package never imports :mod:`mgso` and never initialises Warp at import time; call
:func:`mgso_kernels.runtime.init` first (the ``mgso`` package does this for you). Every kernel has a slow, obvious
NumPy twin under :mod:`mgso_kernels.reference` and a parity test.
"""

from . import runtime

__all__ = ["runtime"]
