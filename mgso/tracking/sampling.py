"""Vectorised NumPy bilinear sampling of a pyramid level, for the per-point work of the front end that runs in NumPy
(initialiser, activation, fixed-window depth refinement).

Same interpolation as :func:`mgso_kernels.image.sample_dI` (DSO ``getInterpolatedElement33``): the cell index is
clamped so memory stays safe; callers check the margins first (:func:`inside`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["sample_dI", "sample_intensity", "inside", "sample_level"]


def inside(x: np.ndarray, y: np.ndarray, width: int, height: int, lo: float, hi: float) -> np.ndarray:
    """DSO's margin test ``lo < x < width - hi`` and ``lo < y < height - hi`` (NaN -> False)."""
    with np.errstate(invalid="ignore"):
        return (x > lo) & (y > lo) & (x < width - hi) & (y < height - hi)


def _corners(shape, x, y):
    h, w = shape[0], shape[1]
    xf = np.floor(np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0))
    yf = np.floor(np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0))
    ix = np.clip(xf, 0, w - 2).astype(np.int64)
    iy = np.clip(yf, 0, h - 2).astype(np.int64)
    fx = (x - ix).astype(np.float32)
    fy = (y - iy).astype(np.float32)
    return iy * w + ix, fx, fy, w


def sample_dI(dI: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``[..., 3]`` bilinear ``(I, dx, dy)`` of ``dI [H, W, 3]`` at pixel coordinates ``x, y`` (any equal shapes)."""
    x = np.asarray(x)
    y = np.asarray(y)
    idx, fx, fy, w = _corners(dI.shape, x, y)
    flat = dI.reshape(-1, 3)
    fxy = fx * fy
    return ((fxy)[..., None] * flat[idx + w + 1] + (fy - fxy)[..., None] * flat[idx + w]
            + (fx - fxy)[..., None] * flat[idx + 1] + (1.0 - fx - fy + fxy)[..., None] * flat[idx])


def sample_intensity(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear intensity of ``img [H, W]`` (or of channel 0 of ``[H, W, 3]``) at ``x, y``."""
    x = np.asarray(x)
    y = np.asarray(y)
    flat = img.reshape(-1, 3)[:, 0] if img.ndim == 3 else img.reshape(-1)
    idx, fx, fy, w = _corners(img.shape, x, y)
    fxy = fx * fy
    return (fxy * flat[idx + w + 1] + (fy - fxy) * flat[idx + w] + (fx - fxy) * flat[idx + 1]
            + (1.0 - fx - fy + fxy) * flat[idx])


def sample_level(dI, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``[..., 3]`` bilinear ``(I, dx, dy)`` at ``x, y``: through the Warp kernel
    (:func:`mgso_kernels.image.sample_points`, several times faster for large batches) when ``dI`` is a
    ``wp.array`` of a pyramid level, else :func:`sample_dI` on a NumPy ``[H, W, 3]``. Outside the image the Warp
    path answers 0 (callers test the margins themselves)."""
    import warp as wp

    if isinstance(dI, wp.array):
        from mgso_kernels.image import sample_points

        x = np.asarray(x, dtype=np.float32)
        y = np.asarray(y, dtype=np.float32)
        shape = x.shape
        xy = np.stack([np.nan_to_num(x.reshape(-1), nan=-1.0), np.nan_to_num(y.reshape(-1), nan=-1.0)], axis=1)
        out, _ = sample_points(dI, xy)
        return out.reshape(shape + (3,))
    return sample_dI(dI, x, y)
