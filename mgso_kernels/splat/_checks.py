"""Argument checks for the splatting launchers and the rasteriser (plain Python, no Warp module)."""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

__all__ = ["as_float_array", "check_array"]


def as_float_array(x: Any, name: str, tail: tuple[int, ...], device: str, n: int | None = None) -> wp.array:
    """Return ``x`` as a float32 Warp array of shape ``(n, *tail)`` on ``device``.

    Accepts NumPy arrays (copied to float32 if needed), float32 Warp arrays of that shape, and Warp arrays of vector
    types whose length matches ``tail`` (viewed as float32 without a copy, e.g. ``wp.vec3`` (N,) as (N, 3)).
    ``tail`` entries of -1 accept any size.
    """
    if isinstance(x, wp.array):
        a = x
        if a.dtype is not wp.float32 and hasattr(a.dtype, "_wp_scalar_type_"):
            if a.dtype._wp_scalar_type_ is not wp.float32:
                raise TypeError(f"{name}: expected float32 data, got a Warp array of {wp.types.type_repr(a.dtype)}")
            a = a.view(wp.float32)
        if a.dtype is not wp.float32:
            raise TypeError(f"{name}: expected a float32 array, got dtype {wp.types.type_repr(a.dtype)}")
        if str(a.device) != str(wp.get_device(device)):
            raise ValueError(f"{name}: array is on {a.device}, the rasteriser runs on {device}")
    else:
        arr = np.asarray(x)
        if arr.dtype.kind not in "fiu":
            raise TypeError(f"{name}: expected numbers, got dtype {arr.dtype}")
        arr = np.ascontiguousarray(arr, dtype=np.float32)
        a = wp.array(arr, dtype=wp.float32, device=device)
    _check_shape(a.shape, name, tail, n)
    return a


def _check_shape(shape, name, tail, n):
    want = ("N" if n is None else str(n),) + tuple("*" if t < 0 else str(t) for t in tail)
    ok = len(shape) == 1 + len(tail) and (n is None or shape[0] == n)
    ok = ok and all(t < 0 or s == t for s, t in zip(shape[1:], tail))
    if not ok:
        raise ValueError(f"{name}: expected shape ({', '.join(want)}), got {tuple(shape)}")


def check_array(a: Any, name: str, dtype, shape: tuple[int, ...], device: str) -> wp.array:
    """Check a kernel argument: a Warp array of ``dtype`` and ``shape`` on ``device`` (the launchers take Warp
    arrays only; :class:`mgso_kernels.splat.Rasterizer` converts NumPy input)."""
    if not isinstance(a, wp.array):
        raise TypeError(f"{name}: expected a Warp array of {wp.types.type_repr(dtype)} {tuple(shape)}, got "
                        f"{type(a).__name__}")
    if a.dtype is not dtype:
        raise TypeError(f"{name}: expected dtype {wp.types.type_repr(dtype)}, got {wp.types.type_repr(a.dtype)}")
    if tuple(a.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(a.shape)}")
    if str(a.device) != str(wp.get_device(device)):
        raise ValueError(f"{name}: array is on {a.device}, expected {device}")
    return a
