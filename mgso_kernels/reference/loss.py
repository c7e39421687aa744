"""NumPy twin of :mod:`mgso_kernels.loss`: L1 + D-SSIM, slow and obvious, in float64.

Forward: scipy.ndimage correlations (separable, zero padding, 'same' size). Gradient: its own analytic formula,
written through the variances (sigma_x^2, sigma_y^2, sigma_xy) rather than the raw second moments, and applied with a
non-separable 2-D correlation, so that it shares no algebra with the Warp kernels it checks.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["gaussian_window", "filter_same", "ssim_map", "l1_dssim_loss"]

LAMBDA_DSSIM = 0.2
C1 = 0.01 ** 2
C2 = 0.03 ** 2


def gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-x ** 2 / (2.0 * sigma ** 2))
    return g / g.sum()


def filter_same(img: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Zero-padded 'same' correlation of every channel of an (H, W[, C]) image with the separable window g x g."""
    out = ndimage.correlate1d(img, g, axis=0, mode="constant", cval=0.0)
    return ndimage.correlate1d(out, g, axis=1, mode="constant", cval=0.0)


def ssim_map(x: np.ndarray, y: np.ndarray, g: np.ndarray, c1: float = C1, c2: float = C2) -> np.ndarray:
    """Per-pixel, per-channel SSIM of (H, W, 3) images x and y."""
    mx, my = filter_same(x, g), filter_same(y, g)
    sxx = filter_same(x * x, g) - mx * mx
    syy = filter_same(y * y, g) - my * my
    sxy = filter_same(x * y, g) - mx * my
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))


def l1_dssim_loss(rendered: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None,
                  exposure: tuple[float, float] | None = None, lambda_dssim: float = LAMBDA_DSSIM,
                  window_size: int = 11, sigma: float = 1.5, c1: float = C1, c2: float = C2) -> dict:
    """Loss values and gradients: keys ``loss, l1, ssim, weight_sum, v_rendered (H, W, 3), v_exposure (2,)``."""
    I = np.asarray(rendered, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    H, W, _ = I.shape
    w = np.ones((H, W)) if mask is None else np.asarray(mask, dtype=np.float64)
    a, b = (0.0, 0.0) if exposure is None else (float(exposure[0]), float(exposure[1]))
    gain = np.exp(a)
    x = gain * I + b
    g = gaussian_window(window_size, sigma)

    # forward
    mx, my = filter_same(x, g), filter_same(y, g)
    sxx = filter_same(x * x, g) - mx * mx
    syy = filter_same(y * y, g) - my * my
    sxy = filter_same(x * y, g) - mx * my
    A1 = 2 * mx * my + c1
    A2 = 2 * sxy + c2
    B1 = mx ** 2 + my ** 2 + c1
    B2 = sxx + syy + c2
    S = A1 * A2 / (B1 * B2)
    wsum = w.sum()
    w3 = w[..., None]
    if wsum <= 0:
        return dict(loss=0.0, l1=0.0, ssim=1.0, weight_sum=0.0, v_rendered=np.zeros_like(I), v_exposure=np.zeros(2))
    l1 = float((w3 * np.abs(x - y)).sum() / (3 * wsum))
    ssim = float((w3 * S).sum() / (3 * wsum))
    loss = (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim)

    # gradient of S with respect to (mu_x, sigma_x^2, sigma_xy), mu_y and sigma_y^2 fixed
    dS_dmx_sig = (2 * my * A2) / (B1 * B2) - S * (2 * mx) / B1
    dS_dsxx = -S / B2
    dS_dsxy = 2 * A1 / (B1 * B2)
    # then to the raw filtered maps (mu_x, E[x^2], E[xy]): sigma_x^2 = E[x^2] - mu_x^2, sigma_xy = E[xy] - mu_x mu_y
    dS_dmx = dS_dmx_sig - 2 * mx * dS_dsxx - my * dS_dsxy
    dS_dExx = dS_dsxx
    dS_dExy = dS_dsxy
    # adjoint of the filter: the same zero-padded correlation with the (symmetric) 2-D window
    g2 = np.outer(g, g)

    def adj(m):
        return np.stack([ndimage.correlate(m[..., c], g2, mode="constant", cval=0.0) for c in range(3)], axis=-1)

    dSsum_dx = adj(w3 * dS_dmx) + 2 * x * adj(w3 * dS_dExx) + y * adj(w3 * dS_dExy)
    dL_dx = ((1 - lambda_dssim) * w3 * np.sign(x - y) - lambda_dssim * dSsum_dx) / (3 * wsum)
    v_rendered = dL_dx * gain
    v_exposure = np.array([(dL_dx * gain * I).sum(), dL_dx.sum()])
    return dict(loss=loss, l1=l1, ssim=ssim, weight_sum=float(wsum), v_rendered=v_rendered, v_exposure=v_exposure)
