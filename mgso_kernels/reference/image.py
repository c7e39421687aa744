"""NumPy twin of :mod:`mgso_kernels.image`: pyramid by 2x2 averaging, central-difference gradients, bilinear
sampling. Slow and obvious; the truth the parity tests compare to. Works in the dtype it is given (float32 for
parity, float64 for finite-difference checks)."""

from __future__ import annotations

import numpy as np

__all__ = ["downsample", "gradients", "build_pyramid", "bilinear_inside", "sample_dI", "sample_dI_bilin_derivative"]


def downsample(img: np.ndarray) -> np.ndarray:
    """``[2H, 2W] -> [H, W]`` mean of each 2x2 block (summed in DSO's order)."""
    h, w = img.shape[0] // 2, img.shape[1] // 2
    a = img[0:2 * h:2, 0:2 * w:2]
    b = img[0:2 * h:2, 1:2 * w:2]
    c = img[1:2 * h:2, 0:2 * w:2]
    d = img[1:2 * h:2, 1:2 * w:2]
    return (img.dtype.type(0.25) * (a + b + c + d)).astype(img.dtype)


def gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(dI [H, W, 3] = (I, dx, dy), grad_sq [H, W])`` with central differences, indices clamped at borders."""
    h, w = img.shape
    half = img.dtype.type(0.5)
    dx = np.empty_like(img)
    dy = np.empty_like(img)
    for x in range(w):
        dx[:, x] = half * (img[:, min(x + 1, w - 1)] - img[:, max(x - 1, 0)])
    for y in range(h):
        dy[y, :] = half * (img[min(y + 1, h - 1), :] - img[max(y - 1, 0), :])
    dx[~np.isfinite(dx)] = 0
    dy[~np.isfinite(dy)] = 0
    return np.stack([img, dx, dy], axis=-1), dx * dx + dy * dy


def build_pyramid(image: np.ndarray, levels: int, dtype=np.float32) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``[(intensity, dI, grad_sq)]`` per level."""
    out = []
    img = np.asarray(image, dtype=dtype)
    for lvl in range(levels):
        if lvl > 0:
            img = downsample(img)
        dI, g2 = gradients(img)
        out.append((img, dI, g2))
    return out


def bilinear_inside(x, y, width: int, height: int):
    x = np.asarray(x)
    y = np.asarray(y)
    with np.errstate(invalid="ignore"):
        return (x >= 0) & (y >= 0) & (x <= width - 1) & (y <= height - 1)


def _cell(dI, x, y):
    h, w = dI.shape[:2]
    xf = np.nan_to_num(np.floor(x), nan=0.0, posinf=0.0, neginf=0.0)
    yf = np.nan_to_num(np.floor(y), nan=0.0, posinf=0.0, neginf=0.0)
    ix = np.clip(xf.astype(np.int64), 0, w - 2)
    iy = np.clip(yf.astype(np.int64), 0, h - 2)
    return ix, iy, (x - ix).astype(dI.dtype), (y - iy).astype(dI.dtype)


def sample_dI(dI: np.ndarray, x, y) -> np.ndarray:
    """Bilinear ``(I, dx, dy)`` ``[..., 3]`` at pixel coordinates ``x, y`` (same clamping as the kernel)."""
    x = np.asarray(x, dtype=dI.dtype)
    y = np.asarray(y, dtype=dI.dtype)
    ix, iy, fx, fy = _cell(dI, x, y)
    fxy = fx * fy
    one = dI.dtype.type(1)
    return ((fxy)[..., None] * dI[iy + 1, ix + 1] + (fy - fxy)[..., None] * dI[iy + 1, ix]
            + (fx - fxy)[..., None] * dI[iy, ix + 1] + (one - fx - fy + fxy)[..., None] * dI[iy, ix])


def sample_dI_bilin_derivative(dI: np.ndarray, x, y) -> np.ndarray:
    """Bilinear intensity and the gradient of the bilinear interpolant (DSO ``getInterpolatedElement33BiLin``)."""
    x = np.asarray(x, dtype=dI.dtype)
    y = np.asarray(y, dtype=dI.dtype)
    ix, iy, fx, fy = _cell(dI, x, y)
    one = dI.dtype.type(1)
    tl, tr = dI[iy, ix, 0], dI[iy, ix + 1, 0]
    bl, br = dI[iy + 1, ix, 0], dI[iy + 1, ix + 1, 0]
    top = fx * tr + (one - fx) * tl
    bot = fx * br + (one - fx) * bl
    left = fy * bl + (one - fy) * tl
    right = fy * br + (one - fy) * tr
    return np.stack([fx * right + (one - fx) * left, right - left, bot - top], axis=-1)
