"""Photometric training loss of the Gaussian map: L1 + D-SSIM, fused forward and backward Warp kernels.

    L = (1 - lambda) * L1 + lambda * (1 - SSIM),     lambda = 0.2 (3DGS, graphdeco ``lambda_dssim``)

on the exposure-corrected rendering ``I' = exp(a) * I + b`` (MGSO: the map stores radiance; the keyframe's affine
brightness (a, b) comes from DSO and may be refined with the gradients returned here).

Conventions (the 3DGS training convention, graphdeco ``utils/loss_utils.py``):

- SSIM uses the standard 11x11 Gaussian window (sigma 1.5, normalised to sum 1), C1 = 0.01^2, C2 = 0.03^2 (images in
  [0, 1]), a **zero-padded 'same'** filter (``conv2d(..., padding=5)``: pixels near the border see zeros outside the
  image), and the SSIM map is **averaged over pixels and channels**. L1 is the mean absolute difference over pixels
  and channels.
- An optional per-pixel weight ``mask`` (H, W) >= 0 turns both means into weighted means,
  ``L1 = sum_p w_p sum_c |I'_pc - T_pc| / (3 sum_p w_p)`` and likewise for the SSIM map. The 11x11 windows are not
  masked: a valid pixel next to an invalid border still sees its neighbours (what masked 3DGS trainers do). A mask of
  all zeros gives loss 0 and a zero gradient (``LossResult.weight_sum == 0`` says so).

Algorithm for the standard window (11 taps, sigma 1.5; every caller): **chunk kernels**
(:mod:`mgso_kernels.loss_chunks`, their own Warp module for their compiler options). A row of the image is
3W interleaved floats (r, g, b per pixel); it is cut into *chunks* of 16 consecutive floats, and every operation is
lane-wise on chunks, so the compiler turns it into vector instructions (AVX-512 here). Filtering is channel-agnostic:
a horizontal tap of dx pixels is a shift of 3 dx floats, i.e. a constant lane permutation of a chunk and its two
neighbours; a vertical tap reads the same chunk of another row. A thread handles one chunk column over a band of
rows, keeping the last 11 horizontally filtered rows in a ring buffer, so the horizontally filtered maps never go
to memory:

1. ``ssim_forward_chunks``: per row of the band (plus the 5 rows above and below), the horizontal window over the
   five moment maps x', y, x'^2, y^2, x'y into the ring; per output row the vertical window from the ring, then SSIM,
   L1 and the weighted partial derivatives of SSIM with respect to the three filtered maps that depend on the
   rendering (mu_x, E[x^2], E[xy]), written as three chunk maps; per-thread partial sums of (w, w L1, w SSIM).
2. ``sum_blocks`` + ``sum_partials``: float64 sums of the per-thread partials (no atomics; bitwise reproducible
   however the launch is split).
3. ``ssim_backward_chunks``: the adjoint of a zero-padded 'same' correlation with a symmetric window is the same
   correlation, so the same ring scheme filters the three derivative maps, then the chain rule
   ``dSSIM/dx'(q) = G*A (q) + 2 x'(q) G*B (q) + y(q) G*C (q)``, the L1 term, times exp(a) for dL/dI; and per-thread
   partial sums for dL/da, dL/db, reduced as in 2.

Images whose 3W is a multiple of 16 (W a multiple of 16: 320, 640, 752, ...) are read and written in place through
chunk views; other sizes are staged into zero-padded chunk buffers first (``stage_chunks``). A mask is staged
as per-lane weights. On CUDA a thread handles one row of a chunk column (the ring then costs 11 horizontal rows per
output row, which a GPU affords). Measured (one call, forward + backward, one thread, thread CPU time, min of 9):
320x240 45 -> 17 ms, 640x480 187 -> 60 ms, 80x60 3.6 -> 1.6 ms against the per-pixel kernels below.

**On the CPU** the same work runs as plain row loops (:mod:`mgso_kernels.loss_simd`: a thread does a block of 4
neighbouring chunks of a band, every horizontal tap a load at an offset from a contiguous row): the same operations
in the same order, so the same bits as the chunk kernels (tested), at whatever vector width the CPU has. The chunk
kernels' cross-chunk lane permutations are single instructions with AVX-512 only; on a 2-core AMD EPYC (Zen 3, AVX2)
forward + backward at 640x480 took 160 ms of one thread as chunk kernels and 23 ms as row loops
(docs/mapping.md, "The loss as row loops"). ``L1SSIMLoss(simd=False)`` runs the chunk kernels on the CPU too.

Other window sizes / sigmas use the first implementation, five per-pixel passes: ``filter_moments_rows``
(horizontal window over the five maps), ``ssim_forward_cols`` (vertical window, SSIM, L1 and the partials),
``sum_blocks`` + ``sum_partials``, ``filter_adjoint_rows`` + ``ssim_backward_cols`` (the adjoint filter and the
chain rule), each split over the CPU cores with :func:`runtime.launch_split`.

The NumPy twin is :mod:`mgso_kernels.reference.loss` (scipy.ndimage forward, non-separable analytic adjoint).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import runtime
from .loss_chunks import (BAND_CPU, BAND_GPU, CHUNK, AdjointChunks, ChunkImages, ssim_backward_chunks,
                          ssim_forward_chunks, stage_chunks, vec16)
from .loss_chunks import WINDOW as CHUNK_WINDOW
from .loss_simd import num_blocks, ssim_backward_blocks, ssim_forward_blocks

wp.set_module_options({"enable_backward": False})

__all__ = [
    "LAMBDA_DSSIM", "SSIM_WINDOW", "SSIM_SIGMA", "SSIM_C1", "SSIM_C2", "REDUCE_BLOCK",
    "gaussian_window", "LossResult", "L1SSIMLoss", "l1_dssim_loss",
]

LAMBDA_DSSIM = 0.2          # 3DGS lambda_dssim
SSIM_WINDOW = 11            # window side, pixels (Wang et al. 2004; 3DGS)
SSIM_SIGMA = 1.5            # window standard deviation, pixels
SSIM_C1 = 0.01 ** 2         # (K1 * L)^2 with K1 = 0.01, dynamic range L = 1
SSIM_C2 = 0.03 ** 2         # (K2 * L)^2 with K2 = 0.03
REDUCE_BLOCK = 256          # pixels per float64 partial sum


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """The normalised 1-D Gaussian window (float32, sums to 1); the 2-D window is its outer product."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"SSIM window size must be odd and positive, got {size}")
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(x * x) / (2.0 * sigma * sigma))
    return (g / g.sum()).astype(np.float32)


# ------------------------------------------------------------------------------------------------ structs
@wp.struct
class ImagePair:
    rendered: wp.array2d(dtype=wp.vec3)   # [H, W] RGB radiance from the rasteriser, before exposure
    target: wp.array2d(dtype=wp.vec3)     # [H, W] RGB in [0, 1]
    weight: wp.array2d(dtype=float)       # [H, W] per-pixel weight >= 0 (read only when use_weight == 1)
    use_weight: int                       # 0: every pixel weighs 1
    gain: float                           # exp(a)
    bias: float                           # b


@wp.struct
class MomentMaps:
    mu_x: wp.array2d(dtype=wp.vec3)       # [H, W] filtered x' (per channel)
    mu_y: wp.array2d(dtype=wp.vec3)       # [H, W] filtered y
    xx: wp.array2d(dtype=wp.vec3)         # [H, W] filtered x'^2
    yy: wp.array2d(dtype=wp.vec3)         # [H, W] filtered y^2
    xy: wp.array2d(dtype=wp.vec3)         # [H, W] filtered x' y


@wp.struct
class AdjointMaps:
    d_mu_x: wp.array2d(dtype=wp.vec3)     # [H, W] w_p dSSIM_p / d mu_x(p)
    d_xx: wp.array2d(dtype=wp.vec3)       # [H, W] w_p dSSIM_p / d E[x^2](p)
    d_xy: wp.array2d(dtype=wp.vec3)       # [H, W] w_p dSSIM_p / d E[xy](p)


# -------------------------------------------------------------------------------------------------- funcs
@wp.func
def exposed(img: ImagePair, y: int, x: int):
    return img.rendered[y, x] * img.gain + wp.vec3(img.bias)


@wp.func
def pixel_weight(img: ImagePair, y: int, x: int):
    w = float(1.0)
    if img.use_weight != 0:
        w = img.weight[y, x]
    return w


@wp.func
def ssim_and_partials(mx: float, my: float, exx: float, eyy: float, exy: float, c1: float, c2: float):
    """SSIM of one pixel and channel from the filtered moments, and dSSIM/d(mu_x, E[x^2], E[xy])."""
    sxx = exx - mx * mx
    syy = eyy - my * my
    sxy = exy - mx * my
    n1 = 2.0 * mx * my + c1
    n2 = 2.0 * sxy + c2
    d1 = mx * mx + my * my + c1
    d2 = sxx + syy + c2
    inv = 1.0 / (d1 * d2)
    s = n1 * n2 * inv
    d_mx = 2.0 * my * (n2 - n1) * inv + 2.0 * mx * s * (1.0 / d2 - 1.0 / d1)
    d_xx = -s / d2
    d_xy = 2.0 * n1 * inv
    return wp.vec4(s, d_mx, d_xx, d_xy)


@wp.func
def sign3(v: wp.vec3):
    return wp.vec3(wp.sign(v[0]) * wp.where(v[0] == 0.0, 0.0, 1.0),
                   wp.sign(v[1]) * wp.where(v[1] == 0.0, 0.0, 1.0),
                   wp.sign(v[2]) * wp.where(v[2] == 0.0, 0.0, 1.0))


# ------------------------------------------------------------------------------------------------ kernels
@wp.kernel
def filter_moments_rows(offset: int, img: ImagePair, window: wp.array(dtype=float), out: MomentMaps):
    """Horizontal zero-padded 'same' window over x', y, x'^2, y^2, x'y; one thread per pixel."""
    i = offset + wp.tid()
    w = img.rendered.shape[1]
    y = i // w
    x = i - y * w
    r = window.shape[0] // 2
    mx = wp.vec3()
    my = wp.vec3()
    xx = wp.vec3()
    yy = wp.vec3()
    xy = wp.vec3()
    for k in range(-r, r + 1):
        xs = x + k
        if xs >= 0 and xs < w:
            g = window[k + r]
            a = exposed(img, y, xs)
            b = img.target[y, xs]
            mx += g * a
            my += g * b
            xx += g * wp.cw_mul(a, a)
            yy += g * wp.cw_mul(b, b)
            xy += g * wp.cw_mul(a, b)
    out.mu_x[y, x] = mx
    out.mu_y[y, x] = my
    out.xx[y, x] = xx
    out.yy[y, x] = yy
    out.xy[y, x] = xy


@wp.kernel
def ssim_forward_cols(offset: int, img: ImagePair, window: wp.array(dtype=float), rows: MomentMaps,
                      c1: float, c2: float, adj: AdjointMaps, pixel_sums: wp.array(dtype=wp.vec3)):
    """Vertical window, SSIM and L1 per pixel; writes w_p dSSIM_p/d(filtered maps) and (w, w*L1, w*SSIM)."""
    i = offset + wp.tid()
    h = img.rendered.shape[0]
    w = img.rendered.shape[1]
    y = i // w
    x = i - y * w
    r = window.shape[0] // 2
    mx = wp.vec3()
    my = wp.vec3()
    xx = wp.vec3()
    yy = wp.vec3()
    xy = wp.vec3()
    for k in range(-r, r + 1):
        ys = y + k
        if ys >= 0 and ys < h:
            g = window[k + r]
            mx += g * rows.mu_x[ys, x]
            my += g * rows.mu_y[ys, x]
            xx += g * rows.xx[ys, x]
            yy += g * rows.yy[ys, x]
            xy += g * rows.xy[ys, x]
    wt = pixel_weight(img, y, x)
    s_sum = float(0.0)
    d_mu = wp.vec3()
    d_xx = wp.vec3()
    d_xy = wp.vec3()
    for c in range(3):
        q = ssim_and_partials(mx[c], my[c], xx[c], yy[c], xy[c], c1, c2)
        s_sum += q[0]
        d_mu[c] = wt * q[1]
        d_xx[c] = wt * q[2]
        d_xy[c] = wt * q[3]
    adj.d_mu_x[y, x] = d_mu
    adj.d_xx[y, x] = d_xx
    adj.d_xy[y, x] = d_xy
    diff = exposed(img, y, x) - img.target[y, x]
    l1 = wp.abs(diff[0]) + wp.abs(diff[1]) + wp.abs(diff[2])
    pixel_sums[i] = wp.vec3(wt, wt * l1, wt * s_sum)


@wp.kernel
def filter_adjoint_rows(offset: int, adj: AdjointMaps, window: wp.array(dtype=float), out: AdjointMaps):
    """Horizontal window over the three derivative maps (the adjoint of the forward's vertical pass)."""
    i = offset + wp.tid()
    w = adj.d_mu_x.shape[1]
    y = i // w
    x = i - y * w
    r = window.shape[0] // 2
    a = wp.vec3()
    b = wp.vec3()
    c = wp.vec3()
    for k in range(-r, r + 1):
        xs = x + k
        if xs >= 0 and xs < w:
            g = window[k + r]
            a += g * adj.d_mu_x[y, xs]
            b += g * adj.d_xx[y, xs]
            c += g * adj.d_xy[y, xs]
    out.d_mu_x[y, x] = a
    out.d_xx[y, x] = b
    out.d_xy[y, x] = c


@wp.kernel
def ssim_backward_cols(offset: int, img: ImagePair, window: wp.array(dtype=float), rows: AdjointMaps,
                       totals: wp.array(dtype=wp.vec3d), lambda_dssim: float,
                       v_rendered: wp.array2d(dtype=wp.vec3), pixel_sums: wp.array(dtype=wp.vec3)):
    """Vertical window and chain rule: dL/dI per pixel, and per-pixel (dL/da, dL/db, 0) terms."""
    i = offset + wp.tid()
    h = img.rendered.shape[0]
    w = img.rendered.shape[1]
    y = i // w
    x = i - y * w
    r = window.shape[0] // 2
    ga = wp.vec3()
    gb = wp.vec3()
    gc = wp.vec3()
    for k in range(-r, r + 1):
        ys = y + k
        if ys >= 0 and ys < h:
            g = window[k + r]
            ga += g * rows.d_mu_x[ys, x]
            gb += g * rows.d_xx[ys, x]
            gc += g * rows.d_xy[ys, x]
    weight_sum = float(totals[0][0])
    norm = float(0.0)
    if weight_sum > 0.0:
        norm = 1.0 / (3.0 * weight_sum)
    xp = exposed(img, y, x)
    yt = img.target[y, x]
    d_ssim = ga + 2.0 * wp.cw_mul(xp, gb) + wp.cw_mul(yt, gc)
    d_l1 = pixel_weight(img, y, x) * sign3(xp - yt)
    v_x = norm * ((1.0 - lambda_dssim) * d_l1 - lambda_dssim * d_ssim)   # dL/dI'
    v_rendered[y, x] = v_x * img.gain
    unexposed = xp - wp.vec3(img.bias)                                    # dI'/da = exp(a) I
    pixel_sums[i] = wp.vec3(wp.dot(v_x, unexposed), v_x[0] + v_x[1] + v_x[2], 0.0)


@wp.kernel
def sum_blocks(offset: int, values: wp.array(dtype=wp.vec3), block: int, partials: wp.array(dtype=wp.vec3d)):
    """One thread per block of ``block`` values: float64 partial sum (no atomics)."""
    b = offset + wp.tid()
    lo = b * block
    hi = wp.min(lo + block, values.shape[0])
    acc = wp.vec3d()
    for j in range(lo, hi):
        v = values[j]
        acc += wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))
    partials[b] = acc


@wp.kernel
def sum_partials(partials: wp.array(dtype=wp.vec3d), count: int, totals: wp.array(dtype=wp.vec3d), slot: int):
    """A single thread adds the block partials in order (deterministic on every device)."""
    acc = wp.vec3d()
    for b in range(count):
        acc += partials[b]
    totals[slot] = acc



# ----------------------------------------------------------------------------------------------- launcher
@dataclass(frozen=True)
class LossResult:
    """What :class:`L1SSIMLoss` computed for one image pair.

    ``v_rendered`` is dL/d(rendered image) (before exposure), a Warp array ``[H, W]`` of ``vec3`` owned by the loss
    object: the next call overwrites it (copy it if you keep it). ``v_exposure`` is (dL/da, dL/db).
    """

    loss: float                       # (1 - lambda) * l1 + lambda * (1 - ssim)
    l1: float                         # weighted mean |I' - T| over pixels and channels
    ssim: float                       # weighted mean SSIM over pixels and channels
    weight_sum: float                 # sum of the pixel weights (H * W without a mask); 0 -> loss 0
    v_rendered: wp.array | None       # [H, W] vec3 dL/dI, None when compute_grad=False
    v_exposure: tuple[float, float]   # (dL/da, dL/db); (0, 0) when compute_grad=False

    @property
    def v_rendered_hw3(self) -> wp.array | None:
        """``v_rendered`` as a zero-copy float32 (H, W, 3) Warp view."""
        if self.v_rendered is None:
            return None
        v = wp.array(ptr=self.v_rendered.ptr, dtype=wp.float32, shape=tuple(self.v_rendered.shape) + (3,),
                     device=self.v_rendered.device)
        v._ref = self.v_rendered
        return v

    @property
    def dssim(self) -> float:
        """1 - SSIM, the D-SSIM term as 3DGS logs it."""
        return 1.0 - self.ssim


def _as_image(x, name: str, height: int, width: int, device: str) -> wp.array:
    """A ``[H, W]`` vec3 Warp view of an (H, W, 3) float32 image (NumPy or Warp), copying only when needed."""
    if isinstance(x, wp.array):
        if x.device != wp.get_device(device):
            raise ValueError(f"{name}: on device {x.device}, the loss runs on {device}")
        if x.dtype == wp.vec3 and x.ndim == 2:
            arr = x
        elif x.dtype == wp.float32 and x.ndim == 3 and x.shape[2] == 3:
            if not x.is_contiguous:
                raise ValueError(f"{name}: a (H, W, 3) float32 Warp array must be contiguous")
            arr = wp.array(ptr=x.ptr, dtype=wp.vec3, shape=(x.shape[0], x.shape[1]), device=x.device)
            arr._ref = x  # keep the owner alive
        else:
            raise ValueError(f"{name}: expected a Warp array [H, W] of vec3 or (H, W, 3) float32, got dtype "
                             f"{x.dtype} with shape {x.shape}")
    else:
        a = np.asarray(x)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"{name}: expected an (H, W, 3) RGB image, got shape {a.shape}")
        if not np.issubdtype(a.dtype, np.floating):
            raise ValueError(f"{name}: expected float RGB in [0, 1], got dtype {a.dtype} (divide uint8 by 255)")
        a = np.ascontiguousarray(a, dtype=np.float32)
        arr = wp.array(a, dtype=wp.vec3, device=device, copy=not wp.get_device(device).is_cpu)
    if tuple(arr.shape) != (height, width):
        raise ValueError(f"{name}: image is {arr.shape[1]}x{arr.shape[0]} (WxH), the loss was built for "
                         f"{width}x{height}")
    return arr


def _as_weight(mask, height: int, width: int, device: str) -> wp.array:
    if isinstance(mask, wp.array):
        if mask.dtype != wp.float32 or tuple(mask.shape) != (height, width):
            raise ValueError(f"mask: expected a float32 Warp array of shape ({height}, {width}), got dtype "
                             f"{mask.dtype} shape {mask.shape}")
        return mask
    m = np.asarray(mask)
    if m.shape != (height, width):
        raise ValueError(f"mask: expected shape ({height}, {width}), got {m.shape}")
    m = np.ascontiguousarray(m, dtype=np.float32)
    if not np.all(np.isfinite(m)) or np.any(m < 0):
        raise ValueError("mask: weights must be finite and >= 0")
    return wp.array(m, dtype=wp.float32, device=device, copy=not wp.get_device(device).is_cpu)


class L1SSIMLoss:
    """L1 + D-SSIM loss of one image size, with its scratch buffers allocated once.

    Usage::

        loss_fn = L1SSIMLoss(height=480, width=640, device="cpu")
        res = loss_fn(rendered, target, mask=valid, exposure=(a, b))
        res.loss, res.v_rendered  # dL/dI as [H, W] vec3, overwritten by the next call

    ``rendered`` / ``target``: (H, W, 3) float32 (NumPy, or a Warp array of vec3 [H, W] or float32 (H, W, 3)).
    ``mask``: optional (H, W) float weights >= 0 (0 = ignore the pixel), e.g. undistortion borders.
    ``exposure``: optional (a, b): the loss compares ``exp(a) * rendered + b`` with the target.
    """

    def __init__(self, height: int, width: int, device: str | None = None, *,
                 lambda_dssim: float = LAMBDA_DSSIM, window_size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA,
                 c1: float = SSIM_C1, c2: float = SSIM_C2, simd: bool = True):
        if height < 1 or width < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not 0.0 <= lambda_dssim <= 1.0:
            raise ValueError(f"lambda_dssim must be in [0, 1], got {lambda_dssim}")
        self.device = runtime.device_or_cpu(device)
        self.height, self.width = int(height), int(width)
        self.lambda_dssim = float(lambda_dssim)
        self.c1, self.c2 = float(c1), float(c2)
        # the CPU runs the chunk kernels' work as row loops (mgso_kernels.loss_simd, the same bits); False: the chunk
        # kernels themselves (tests compare the two)
        self.simd = bool(simd) and wp.get_device(self.device).is_cpu
        d = self.device
        shape = (self.height, self.width)
        window = gaussian_window(window_size, sigma)
        self.window = wp.array(window, dtype=wp.float32, device=d)
        # the chunk kernels have the standard window built in; any other window runs the per-pixel kernels
        self.chunked = np.array_equal(window, CHUNK_WINDOW)
        self._totals = wp.zeros(2, dtype=wp.vec3d, device=d)   # [0]: (w, w*l1, w*ssim); [1]: (dL/da, dL/db, 0)
        self.v_rendered = wp.zeros(shape, dtype=wp.vec3, device=d)   # [H, W] dL/dI, overwritten each call
        self._dummy_weight = wp.zeros((1, 1), dtype=wp.float32, device=d)
        if self.chunked:
            self._init_chunks()
            return
        self._rows = MomentMaps()
        for f in ("mu_x", "mu_y", "xx", "yy", "xy"):
            setattr(self._rows, f, wp.zeros(shape, dtype=wp.vec3, device=d))
        self._adj = AdjointMaps()
        self._adj_rows = AdjointMaps()
        for st in (self._adj, self._adj_rows):
            for f in ("d_mu_x", "d_xx", "d_xy"):
                setattr(st, f, wp.zeros(shape, dtype=wp.vec3, device=d))
        npix = self.height * self.width
        self._sums = wp.zeros(npix, dtype=wp.vec3, device=d)
        self._nblocks = -(-npix // REDUCE_BLOCK)
        self._partials = wp.zeros(self._nblocks, dtype=wp.vec3d, device=d)

    def _init_chunks(self) -> None:
        H, W, d = self.height, self.width, self.device
        self._nch = -(-3 * W // CHUNK)
        self._in_place = (3 * W) % CHUNK == 0       # rows are whole chunks: read and write the images in place
        self._cpu = wp.get_device(d).is_cpu
        self._band = BAND_CPU if self._cpu else BAND_GPU
        self._nthreads = -(-H // self._band) * self._nch
        cshape = (H, self._nch)
        self._adj = AdjointChunks()
        for f in ("d_mu_x", "d_xx", "d_xy"):
            setattr(self._adj, f, wp.zeros(cshape, dtype=vec16, device=d))
        self._staged_x = self._staged_y = None
        if not self._in_place:
            self._staged_x = wp.zeros(cshape, dtype=vec16, device=d)
            self._staged_y = wp.zeros(cshape, dtype=vec16, device=d)
        self._staged_w: wp.array | None = None   # made on the first call with a mask
        # on the CPU, a copy of the mask last staged into _staged_w: a call with equal weights (a camera's
        # undistortion mask, the same for every view) skips staging them again, which cost a third of a masked call
        self._staged_w_src: np.ndarray | None = None
        self._sums = wp.zeros(self._nthreads, dtype=wp.vec3, device=d)
        self._nblocks = -(-self._nthreads // REDUCE_BLOCK)
        self._partials = wp.zeros(self._nblocks, dtype=wp.vec3d, device=d)
        self._dummy_chunks = wp.zeros((1, 1), dtype=vec16, device=d)
        self._nblk = num_blocks(self._nch)
        self._status = wp.zeros(-(-H // self._band) * self._nblk, dtype=wp.int32, device=d)
        self._v_chunks = self._chunk_view(self.v_rendered) if self._in_place else self._dummy_chunks
        self._v_flat = wp.array(ptr=self.v_rendered.ptr, dtype=wp.float32, shape=(H, 3 * W), device=d)

    def _chunk_view(self, image: wp.array) -> wp.array:
        """A [H, nch] vec16 view of a contiguous [H, W] vec3 image whose rows are whole chunks."""
        v = wp.array(ptr=image.ptr, dtype=vec16, shape=(self.height, self._nch), device=image.device)
        v._ref = image
        return v

    def _reduce(self, slot: int) -> None:
        runtime.launch_split(sum_blocks, self._nblocks, [self._sums, REDUCE_BLOCK, self._partials],
                             self.device, min_chunk=256)
        wp.launch(sum_partials, dim=1, inputs=[self._partials, self._nblocks, self._totals, slot], device=self.device)

    def __call__(self, rendered, target, mask=None, exposure: tuple[float, float] | None = None,
                 compute_grad: bool = True) -> LossResult:
        H, W, d = self.height, self.width, self.device
        img = ImagePair()
        img.rendered = _as_image(rendered, "rendered", H, W, d)
        img.target = _as_image(target, "target", H, W, d)
        if mask is None:
            img.weight = self._dummy_weight
            img.use_weight = 0
        else:
            img.weight = _as_weight(mask, H, W, d)
            img.use_weight = 1
        a, b = (0.0, 0.0) if exposure is None else (float(exposure[0]), float(exposure[1]))
        if not (math.isfinite(a) and math.isfinite(b)):
            raise ValueError(f"exposure (a, b) must be finite, got {exposure}")
        img.gain = math.exp(a)
        img.bias = b
        if self.chunked:
            self._run_chunks(img, compute_grad)
        else:
            self._run_pixels(img, compute_grad)
        totals = self._totals.numpy()
        wsum, l1_sum, s_sum = (float(v) for v in totals[0])
        if self.chunked:
            wsum /= 3.0   # the chunk kernels sum the weight over the three lanes (channels) of every pixel
        if wsum > 0.0:
            l1 = l1_sum / (3.0 * wsum)
            ssim = s_sum / (3.0 * wsum)
            loss = (1.0 - self.lambda_dssim) * l1 + self.lambda_dssim * (1.0 - ssim)
        else:
            l1, ssim, loss = 0.0, 1.0, 0.0
        v_exp = (float(totals[1][0]), float(totals[1][1])) if compute_grad else (0.0, 0.0)
        return LossResult(loss=loss, l1=l1, ssim=ssim, weight_sum=wsum,
                          v_rendered=self.v_rendered if compute_grad else None, v_exposure=v_exp)

    def _run_pixels(self, img: ImagePair, compute_grad: bool) -> None:
        d, npix = self.device, self.height * self.width
        runtime.launch_split(filter_moments_rows, npix, [img, self.window, self._rows], d)
        runtime.launch_split(ssim_forward_cols, npix,
                             [img, self.window, self._rows, self.c1, self.c2, self._adj, self._sums], d)
        self._reduce(0)
        if compute_grad:
            runtime.launch_split(filter_adjoint_rows, npix, [self._adj, self.window, self._adj_rows], d)
            runtime.launch_split(ssim_backward_cols, npix,
                                 [img, self.window, self._adj_rows, self._totals, self.lambda_dssim,
                                  self.v_rendered, self._sums], d)
            self._reduce(1)

    def _run_chunks(self, img: ImagePair, compute_grad: bool) -> None:
        d, H = self.device, self.height
        ci = ChunkImages()
        ci.nch, ci.height, ci.width3 = self._nch, H, 3 * self.width
        ci.use_weight = img.use_weight
        in_place = self._in_place and img.rendered.is_contiguous and img.target.is_contiguous
        if in_place:
            ci.x, ci.y = self._chunk_view(img.rendered), self._chunk_view(img.target)
            ci.gain, ci.bias = img.gain, img.bias
        else:
            if self._staged_x is None:
                shape = (H, self._nch)
                self._staged_x = wp.zeros(shape, dtype=vec16, device=d)
                self._staged_y = wp.zeros(shape, dtype=vec16, device=d)
            ci.x, ci.y = self._staged_x, self._staged_y
            ci.gain, ci.bias = 1.0, 0.0   # staged with the exposure applied
        ci.weight = self._dummy_chunks
        stage_weight = 0
        if img.use_weight:
            if self._staged_w is None:
                self._staged_w = wp.zeros((H, self._nch), dtype=vec16, device=d)
            ci.weight = self._staged_w
            stage_weight = 1
            if self._cpu:
                w = img.weight.numpy()
                if self._staged_w_src is not None and np.array_equal(w, self._staged_w_src):
                    stage_weight = 0
                else:
                    self._staged_w_src = None   # until staged
        if not in_place or stage_weight:
            runtime.launch_split(stage_chunks, H * self._nch,
                                 [img.rendered, img.target, img.weight, stage_weight, img.gain, img.bias,
                                  self._nch, int(not in_place), ci.x, ci.y, ci.weight], d, min_chunk=1024)
            if stage_weight and self._cpu:
                self._staged_w_src = np.array(img.weight.numpy(), copy=True)
        sums = self._sums.reshape((self._nthreads, 1))
        simd = self.simd
        if simd:
            runtime.launch_split(ssim_forward_blocks, self._status.shape[0],
                                 [ci, self._band, self._nblk, self.c1, self.c2, self._adj, sums, self._status], d,
                                 min_chunk=2)
            simd = bool(self._status.numpy().all())   # a snippet that declined: the chunk kernels (never seen)
        if not simd:
            runtime.launch_split(ssim_forward_chunks, self._nthreads,
                                 [ci, self._band, self.c1, self.c2, self._adj, sums], d, min_chunk=8)
        self._reduce(0)
        if compute_grad:
            v_in_place = in_place and self.v_rendered.is_contiguous
            v_chunks = self._v_chunks if v_in_place else self._dummy_chunks
            if simd:
                runtime.launch_split(ssim_backward_blocks, self._status.shape[0],
                                     [ci, self._band, self._nblk, self._adj, self._totals.reshape((2, 1)),
                                      self.lambda_dssim, img.gain, img.bias, v_chunks, self._v_flat,
                                      int(v_in_place), sums, self._status], d, min_chunk=2)
                simd = bool(self._status.numpy().all())
            if not simd:
                runtime.launch_split(ssim_backward_chunks, self._nthreads,
                                     [ci, self._band, self._adj, self._totals.reshape((2, 1)), self.lambda_dssim,
                                      img.gain, img.bias, v_chunks, self._v_flat, int(v_in_place), sums], d,
                                     min_chunk=8)
            self._reduce(1)


def l1_dssim_loss(rendered, target, mask=None, exposure: tuple[float, float] | None = None,
                  lambda_dssim: float = LAMBDA_DSSIM, device: str | None = None,
                  compute_grad: bool = True) -> LossResult:
    """One-off convenience: builds an :class:`L1SSIMLoss` for this image size and calls it.

    Allocates scratch buffers on every call; a training loop should keep one :class:`L1SSIMLoss` per image size.
    """
    shape = rendered.shape
    return L1SSIMLoss(shape[0], shape[1], device, lambda_dssim=lambda_dssim)(
        rendered, target, mask=mask, exposure=exposure, compute_grad=compute_grad)
