"""Image pyramids, gradients and bilinear sampling for the DSO front end (DSO's ``FrameHessian::makeImages``).

Conventions (docs/tracking_kernels.md has the long version):

- Tracking images are float32 intensities in 0-255 (DSO), stored ``[H, W]``; pixel ``(x, y)`` is element ``[y, x]``
  and pixel centres sit at integer coordinates.
- Level ``l`` halves level ``l-1`` by 2x2 averaging: ``I_l[y, x] = 0.25 * (I[2y, 2x] + I[2y, 2x+1] + I[2y+1, 2x]
  + I[2y+1, 2x+1])`` of level ``l-1``. With pixel centres at integers this moves the principal point as
  ``cx_l = (cx + 0.5) / 2^l - 0.5`` (same for ``cy``) and scales ``fx_l = fx / 2^l`` (DSO ``setGlobalCalib``).
- Gradients are DSO's central differences ``dx = 0.5 * (I[y, x+1] - I[y, x-1])``, ``dy = 0.5 * (I[y+1, x] -
  I[y-1, x])``; at the border the index is clamped (the border value is half the one-sided difference; DSO leaves
  the first/last row undefined). Non-finite gradients become 0 (DSO).
- Per level the pyramid keeps ``intensity`` ``[H_l, W_l]`` float32, ``dI`` ``[H_l, W_l]`` vec3 ``(I, dx, dy)``
  (DSO's ``dIp``: one bilinear fetch gives all three) and ``grad_sq`` ``[H_l, W_l]`` = ``dx^2 + dy^2`` (DSO's
  ``absSquaredGrad``).
- Sizes that do not divide by ``2^(levels-1)`` are cropped centrally (or padded) by :func:`plan_pyramid`, which
  returns the shifted principal point so geometry stays exact.

Kernels are pixel-parallel, take ``offset: int`` first and are split over the CPU cores by
:func:`mgso_kernels.runtime.launch_split`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
import warp as wp

from . import runtime
from .image_simd import downsample_span, gradients_span

__all__ = [
    "Pinhole", "PyramidGeometry", "pyramid_levels_for", "plan_pyramid", "level_intrinsics",
    "ImagePyramid", "pyramid_sizes", "downsample", "gradients", "build_pyramid", "sample_points",
    "finite", "finite3", "bilinear_inside", "sample_dI", "sample_intensity", "sample_dI_checked",
    "sample_dI_bilin_derivative",
    "downsample_image", "compute_gradients", "sample_points_kernel", "span_threads",
    "DSO_MAX_LEVELS", "DSO_MIN_COARSE_AREA",
]

wp.set_module_options({"enable_backward": False})

DSO_MAX_LEVELS = 6  # DSO PYR_LEVELS
DSO_MIN_COARSE_AREA = 5000  # DSO setGlobalCalib: keep halving while w*h > 5000


# ------------------------------------------------------------------------------------------------ geometry
@dataclass(frozen=True)
class Pinhole:
    """Pinhole intrinsics in pixels, pixel centres at integer coordinates."""

    fx: float
    fy: float
    cx: float
    cy: float

    def at_level(self, level: int) -> "Pinhole":
        """Intrinsics of pyramid level ``level`` (DSO: ``fx/2^l``, ``(cx + 0.5)/2^l - 0.5``)."""
        return level_intrinsics(self, level)

    def matrix(self) -> np.ndarray:
        """3x3 camera matrix, float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def level_intrinsics(cam: Pinhole, level: int) -> Pinhole:
    """Intrinsics at pyramid level ``level`` for 2x2-average pyramids with pixel centres at integers."""
    if level < 0:
        raise ValueError(f"pyramid level must be >= 0, got {level}")
    s = float(1 << level)
    return Pinhole(cam.fx / s, cam.fy / s, (cam.cx + 0.5) / s - 0.5, (cam.cy + 0.5) / s - 0.5)


def pyramid_levels_for(width: int, height: int, max_levels: int = DSO_MAX_LEVELS,
                       min_area: int = DSO_MIN_COARSE_AREA) -> int:
    """Number of pyramid levels for an image size, DSO's rule without its divisibility test.

    Halve while the current level has more than ``min_area`` pixels and fewer than ``max_levels`` levels exist
    (DSO ``setGlobalCalib``: 640x480 -> 4 levels, coarsest 80x60; 1241x376 -> 5 levels, coarsest 77x23;
    ``min_area=1200`` gives 640x480 five levels down to 40x30). The
    size is then made divisible by ``2^(levels-1)`` by :func:`plan_pyramid`.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if max_levels < 1:
        raise ValueError(f"max_levels must be >= 1, got {max_levels}")
    levels, w, h = 1, int(width), int(height)
    while w * h > min_area and levels < max_levels and w >= 2 and h >= 2:
        w //= 2
        h //= 2
        levels += 1
    return levels


@dataclass(frozen=True)
class PyramidGeometry:
    """How an input image becomes a pyramid: level-0 size after crop/pad, level count and exact intrinsics.

    Level-0 pixel ``(x, y)`` is input pixel ``(x + offset_x, y + offset_y)``; a negative offset means padding.
    ``camera`` is the level-0 intrinsics after the shift (``cx = cx_input - offset_x``).
    """

    input_width: int
    input_height: int
    width: int
    height: int
    levels: int
    offset_x: int
    offset_y: int
    camera: Pinhole | None
    mode: str

    def level_size(self, level: int) -> tuple[int, int]:
        """``(width, height)`` of a level."""
        self._check_level(level)
        return self.width >> level, self.height >> level

    def level_camera(self, level: int) -> Pinhole:
        """Intrinsics of a level (needs ``camera``)."""
        self._check_level(level)
        if self.camera is None:
            raise ValueError("this PyramidGeometry was planned without intrinsics")
        return self.camera.at_level(level)

    def _check_level(self, level: int) -> None:
        if not 0 <= level < self.levels:
            raise ValueError(f"pyramid level {level} out of range 0..{self.levels - 1}")

    def adjust(self, image: np.ndarray) -> np.ndarray:
        """Crop (or edge-pad) an input image ``[H_in, W_in, ...]`` to the level-0 size ``[H, W, ...]``."""
        image = np.asarray(image)
        if image.shape[:2] != (self.input_height, self.input_width):
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}, this pyramid geometry expects "
                             f"{self.input_width}x{self.input_height}")
        if self.mode == "crop":
            return image[self.offset_y:self.offset_y + self.height, self.offset_x:self.offset_x + self.width]
        pad_y0, pad_x0 = -self.offset_y, -self.offset_x
        pad = [(pad_y0, self.height - self.input_height - pad_y0), (pad_x0, self.width - self.input_width - pad_x0)]
        pad += [(0, 0)] * (image.ndim - 2)
        return np.pad(image, pad, mode="edge")


def plan_pyramid(width: int, height: int, camera: Pinhole | None = None, levels: int = 0,
                 max_levels: int = DSO_MAX_LEVELS, min_area: int = DSO_MIN_COARSE_AREA,
                 mode: str = "crop") -> PyramidGeometry:
    """Choose the level count and the crop (or pad) that makes the size divisible by ``2^(levels-1)``.

    ``levels=0`` picks it with :func:`pyramid_levels_for`. ``mode="crop"`` cuts the remainder centrally (KITTI
    1241x376 -> 1232x368 at offset (4, 4), so ``cx -= 4``, ``cy -= 4``); ``mode="pad"`` replicates the border to
    the next multiple (then ``cx`` grows by the left padding). The returned geometry carries the adjusted
    intrinsics so the caller's geometry stays exact.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if mode not in ("crop", "pad"):
        raise ValueError(f"pyramid size mode must be 'crop' or 'pad', got {mode!r}")
    if levels < 0:
        raise ValueError(f"pyramid levels must be >= 0 (0 = automatic), got {levels}")
    if levels == 0:
        levels = pyramid_levels_for(width, height, max_levels, min_area)
    m = 1 << (levels - 1)
    if mode == "crop":
        w0, h0 = (width // m) * m, (height // m) * m
    else:
        w0, h0 = -(-width // m) * m, -(-height // m) * m
    if w0 < 4 * m or h0 < 4 * m:
        raise ValueError(f"image {width}x{height} is too small for {levels} pyramid levels (the coarsest level "
                         f"would be {w0 // m}x{h0 // m}; need at least 4x4)")
    ox, oy = (width - w0) // 2, (height - h0) // 2  # negative when padding
    cam = None
    if camera is not None:
        cam = replace(camera, cx=camera.cx - ox, cy=camera.cy - oy)
    return PyramidGeometry(int(width), int(height), int(w0), int(h0), int(levels), int(ox), int(oy), cam, mode)


# ---------------------------------------------------------------------------------------------- @wp.func
@wp.func
def finite(x: float) -> bool:
    """``wp.isfinite`` inline: ``x - x == 0`` is false exactly for NaN and +-inf (IEEE, no fast-math on the CPU or
    in mgso's CUDA modules). On the CPU ``wp.isfinite`` is a call into Warp's runtime, and a call in a loop makes
    the compiler keep every accumulator in memory around it (the coarse tracker's kernel: 51-52 -> 48-49 ns a residual:
    docs/window.md, "Where the tracker's kernel spends its time")."""
    return x - x == 0.0


@wp.func
def finite3(v: wp.vec3) -> bool:
    """Every component finite (:func:`finite` of each)."""
    return v[0] - v[0] == 0.0 and v[1] - v[1] == 0.0 and v[2] - v[2] == 0.0


@wp.func
def bilinear_inside(x: float, y: float, width: int, height: int) -> bool:
    """True when the 2x2 bilinear footprint of ``(x, y)`` lies in a ``width x height`` image (NaN -> False)."""
    return x >= 0.0 and y >= 0.0 and x <= float(width - 1) and y <= float(height - 1)


@wp.func
def sample_dI(dI: wp.array2d(dtype=wp.vec3), x: float, y: float) -> wp.vec3:
    """Bilinear ``(I, dx, dy)`` at ``(x, y)`` (DSO ``getInterpolatedElement33``). No bounds check: the cell index
    is clamped so memory stays safe, but outside the image the value is an extrapolation; check
    :func:`bilinear_inside` first or use :func:`sample_dI_checked`."""
    h = dI.shape[0]
    w = dI.shape[1]
    ix = wp.clamp(int(x), 0, w - 2)
    iy = wp.clamp(int(y), 0, h - 2)
    fx = x - float(ix)
    fy = y - float(iy)
    fxy = fx * fy
    return (fxy * dI[iy + 1, ix + 1] + (fy - fxy) * dI[iy + 1, ix] + (fx - fxy) * dI[iy, ix + 1]
            + (1.0 - fx - fy + fxy) * dI[iy, ix])


@wp.func
def sample_intensity(dI: wp.array2d(dtype=wp.vec3), x: float, y: float) -> float:
    """Bilinear intensity only (DSO ``getInterpolatedElement31``); same clamping as :func:`sample_dI`."""
    h = dI.shape[0]
    w = dI.shape[1]
    ix = wp.clamp(int(x), 0, w - 2)
    iy = wp.clamp(int(y), 0, h - 2)
    fx = x - float(ix)
    fy = y - float(iy)
    fxy = fx * fy
    return (fxy * dI[iy + 1, ix + 1][0] + (fy - fxy) * dI[iy + 1, ix][0] + (fx - fxy) * dI[iy, ix + 1][0]
            + (1.0 - fx - fy + fxy) * dI[iy, ix][0])


@wp.func
def sample_dI_checked(dI: wp.array2d(dtype=wp.vec3), x: float, y: float):
    """``(value, ok)``: bilinear ``(I, dx, dy)`` and whether ``(x, y)`` was inside and the value finite."""
    if bilinear_inside(x, y, dI.shape[1], dI.shape[0]):
        s = sample_dI(dI, x, y)
        if finite3(s):
            return s, True
    return wp.vec3(0.0), False


@wp.func
def sample_dI_bilin_derivative(dI: wp.array2d(dtype=wp.vec3), x: float, y: float) -> wp.vec3:
    """Bilinear intensity with the gradient of the bilinear interpolant itself (DSO
    ``getInterpolatedElement33BiLin``, used for a new point's host pattern): at integer ``(x, y)`` the gradient
    is the forward difference. Same clamping as :func:`sample_dI`."""
    h = dI.shape[0]
    w = dI.shape[1]
    ix = wp.clamp(int(x), 0, w - 2)
    iy = wp.clamp(int(y), 0, h - 2)
    tl = dI[iy, ix][0]
    tr = dI[iy, ix + 1][0]
    bl = dI[iy + 1, ix][0]
    br = dI[iy + 1, ix + 1][0]
    fx = x - float(ix)
    fy = y - float(iy)
    top = fx * tr + (1.0 - fx) * tl
    bot = fx * br + (1.0 - fx) * bl
    left = fy * bl + (1.0 - fy) * tl
    right = fy * br + (1.0 - fy) * tr
    return wp.vec3(fx * right + (1.0 - fx) * left, right - left, bot - top)


# ------------------------------------------------------------------------------------------------ kernels
SPAN = wp.constant(32)  # pixels of one row handled by one thread of the pyramid kernels


@wp.func
def span_of(i: int, width: int):
    """Thread ``i`` of a span-parallel launch -> ``(row, x_begin, x_end)``: each thread runs along ``SPAN``
    pixels of one row (one integer division per span instead of per pixel; about 3x faster than a thread per
    pixel on the CPU, and still ``H * ceil(W / 32)`` threads on a GPU)."""
    nseg = (width + SPAN - 1) // SPAN
    y = i // nseg
    x0 = (i - y * nseg) * SPAN
    return y, x0, wp.min(x0 + SPAN, width)


@wp.kernel
def downsample_image(offset: int,
                     src: wp.array2d(dtype=float),  # [2H, 2W] intensity of level l-1
                     dst: wp.array2d(dtype=float)):  # [H, W] intensity of level l
    y, x0, x1 = span_of(offset + wp.tid(), dst.shape[1])
    if downsample_span(src, dst, y, x0, x1) == 0:  # the CPU's pointer loop (mgso_kernels.image_simd), else 0
        for x in range(x0, x1):
            dst[y, x] = 0.25 * (src[2 * y, 2 * x] + src[2 * y, 2 * x + 1] + src[2 * y + 1, 2 * x]
                                + src[2 * y + 1, 2 * x + 1])


@wp.kernel
def compute_gradients(offset: int,
                      img: wp.array2d(dtype=float),  # [H, W] intensity
                      dI: wp.array2d(dtype=wp.vec3),  # [H, W] out: (I, dx, dy)
                      grad_sq: wp.array2d(dtype=float)):  # [H, W] out: dx^2 + dy^2
    h = img.shape[0]
    w = img.shape[1]
    y, x0, x1 = span_of(offset + wp.tid(), w)
    ym = wp.max(y - 1, 0)
    yp = wp.min(y + 1, h - 1)
    if gradients_span(img, dI, grad_sq, y, x0, x1) == 0:  # the CPU's pointer loop (mgso_kernels.image_simd)
        for x in range(x0, x1):
            dx = 0.5 * (img[y, wp.min(x + 1, w - 1)] - img[y, wp.max(x - 1, 0)])
            dy = 0.5 * (img[yp, x] - img[ym, x])
            # non-finite -> 0 (DSO); d - d == 0 is false exactly for NaN and inf, and cheaper than isfinite here
            dx = wp.where(dx - dx == 0.0, dx, 0.0)
            dy = wp.where(dy - dy == 0.0, dy, 0.0)
            dI[y, x] = wp.vec3(img[y, x], dx, dy)
            grad_sq[y, x] = dx * dx + dy * dy


def span_threads(height: int, width: int) -> int:
    """Launch size of the span-parallel pyramid kernels for an ``height x width`` output."""
    return height * (-(-width // 32))


@wp.kernel
def sample_points_kernel(offset: int,
                         dI: wp.array2d(dtype=wp.vec3),  # [H, W] (I, dx, dy)
                         xy: wp.array(dtype=wp.vec2),  # [N] pixels
                         bilin_derivative: int,  # 1: gradient of the interpolant (DSO ...BiLin)
                         out: wp.array(dtype=wp.vec3),  # [N] out
                         ok: wp.array(dtype=wp.int32)):  # [N] out: 1 inside and finite
    i = offset + wp.tid()
    p = xy[i]
    if bilin_derivative != 0:
        if bilinear_inside(p[0], p[1], dI.shape[1], dI.shape[0]):
            out[i] = sample_dI_bilin_derivative(dI, p[0], p[1])
            ok[i] = 1
        else:
            out[i] = wp.vec3(0.0)
            ok[i] = 0
    else:
        s, good = sample_dI_checked(dI, p[0], p[1])
        out[i] = s
        ok[i] = wp.where(good, 1, 0)


# ---------------------------------------------------------------------------------------------- launchers
def _check_2d(name: str, a, dtype, shape=None) -> None:
    if not isinstance(a, wp.array) or a.ndim != 2 or a.dtype != dtype:
        raise TypeError(f"{name}: expected a 2-D wp.array of {getattr(dtype, '__name__', dtype)}, got "
                        f"{type(a).__name__} {getattr(a, 'dtype', None)} ndim={getattr(a, 'ndim', None)}")
    if shape is not None and tuple(a.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(a.shape)}")


def downsample(src: wp.array, dst: wp.array, device: str | None = None, split: bool = True,
               recorded: dict | None = None) -> None:
    """``dst [H, W] = 2x2 mean of src [2H, 2W]`` (float32). ``recorded``: a dict kept with the arrays for
    :func:`~mgso_kernels.runtime.launch_split`'s recorded launches (an :class:`ImagePyramid`'s)."""
    _check_2d("src", src, wp.float32)
    _check_2d("dst", dst, wp.float32, (src.shape[0] // 2, src.shape[1] // 2))
    if dst.shape[0] < 1 or dst.shape[1] < 1:
        raise ValueError(f"src {src.shape} is too small to halve")
    device = device or str(src.device)
    runtime.launch_split(downsample_image, span_threads(*dst.shape), [src, dst], device, min_chunk=256,
                         threads=None if split else 1, recorded=recorded)


def gradients(img: wp.array, dI: wp.array, grad_sq: wp.array, device: str | None = None,
              split: bool = True, recorded: dict | None = None) -> None:
    """Central-difference gradients of ``img [H, W]`` into ``dI [H, W] vec3`` and ``grad_sq [H, W]``
    (``recorded``: as :func:`downsample`)."""
    _check_2d("img", img, wp.float32)
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise ValueError(f"image {img.shape} too small for gradients")
    _check_2d("dI", dI, wp.vec3, img.shape)
    _check_2d("grad_sq", grad_sq, wp.float32, img.shape)
    device = device or str(img.device)
    runtime.launch_split(compute_gradients, span_threads(*img.shape), [img, dI, grad_sq], device, min_chunk=256,
                         threads=None if split else 1, recorded=recorded)


class ImagePyramid:
    """Preallocated pyramid buffers of one frame: per level ``intensity``, ``dI`` (I, dx, dy) and ``grad_sq``.

    Owner: the frame that built it (call :meth:`build` once per image; nothing reallocates). Level ``l`` has
    size ``geometry.level_size(l)``; its intrinsics are ``geometry.level_camera(l)``.
    """

    def __init__(self, geometry: PyramidGeometry, device: str | None = None):
        self.geometry = geometry
        self.device = runtime.device_or_cpu(device)
        self.intensity: list[wp.array] = []
        self.dI: list[wp.array] = []
        self.grad_sq: list[wp.array] = []
        for lvl in range(geometry.levels):
            w, h = geometry.level_size(lvl)
            self.intensity.append(wp.zeros((h, w), dtype=wp.float32, device=self.device))
            self.dI.append(wp.zeros((h, w), dtype=wp.vec3, device=self.device))
            self.grad_sq.append(wp.zeros((h, w), dtype=wp.float32, device=self.device))
        # build()'s launches, recorded once for these buffers (runtime.launch_split ``recorded``): a frame's pyramid
        # is 2 launches a level, each ~50 us of Python less when replayed
        self.launches: dict = {}

    @property
    def levels(self) -> int:
        return self.geometry.levels

    def build(self, image, split: bool = True) -> "ImagePyramid":
        """Fill every level from a level-0 image ``[H, W]`` (NumPy uint8/float, or a float32 wp.array on this
        device), already adjusted to the geometry (``geometry.adjust``). Intensities in 0-255."""
        build_pyramid(image, self, split=split)
        return self

    def numpy(self, level: int) -> np.ndarray:
        """``[H_l, W_l, 3]`` float32 (I, dx, dy) of a level (a view on the CPU)."""
        return self.dI[level].numpy()


def build_pyramid(image, pyramid: ImagePyramid, split: bool = True) -> ImagePyramid:
    """Level 0 from ``image``, then halve and take gradients level by level (DSO ``makeImages``)."""
    g = pyramid.geometry
    if isinstance(image, wp.array):
        _check_2d("image", image, wp.float32, (g.height, g.width))
        wp.copy(pyramid.intensity[0], image)
    else:
        img = np.asarray(image)
        if img.ndim != 2:
            raise ValueError(f"image must be a gray [H, W] array, got shape {img.shape}")
        if img.shape != (g.height, g.width):
            raise ValueError(f"image is {img.shape[1]}x{img.shape[0]}, the pyramid expects {g.width}x{g.height} "
                             "(crop/pad it with PyramidGeometry.adjust first)")
        pyramid.intensity[0].assign(np.ascontiguousarray(img, dtype=np.float32))
    for lvl in range(g.levels):
        if lvl > 0:
            downsample(pyramid.intensity[lvl - 1], pyramid.intensity[lvl], pyramid.device, split, pyramid.launches)
        gradients(pyramid.intensity[lvl], pyramid.dI[lvl], pyramid.grad_sq[lvl], pyramid.device, split,
                  pyramid.launches)
    return pyramid


def sample_points(dI: wp.array, xy: np.ndarray, bilin_derivative: bool = False,
                  device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``(I, dx, dy)`` at ``xy [N, 2]`` pixels; returns ``([N, 3] float32, [N] bool inside)``.

    ``bilin_derivative`` uses the gradient of the bilinear interpolant (DSO ``...BiLin``) instead of the
    interpolated central-difference gradient. Mostly for tests and tools; kernels call the ``@wp.func`` directly.
    """
    _check_2d("dI", dI, wp.vec3)
    xy = np.ascontiguousarray(xy, dtype=np.float32)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"xy must be [N, 2], got {xy.shape}")
    device = device or str(dI.device)
    n = xy.shape[0]
    xy_w = wp.array(xy, dtype=wp.vec2, device=device)
    out = wp.zeros(n, dtype=wp.vec3, device=device)
    ok = wp.zeros(n, dtype=wp.int32, device=device)
    if n:
        runtime.launch_split(sample_points_kernel, n, [dI, xy_w, int(bilin_derivative), out, ok], device)
    return out.numpy().reshape(n, 3), ok.numpy().astype(bool)


def pyramid_sizes(width: int, height: int, levels: int) -> Sequence[tuple[int, int]]:
    """``[(w_l, h_l)]`` for a level-0 size (which must divide by ``2^(levels-1)``)."""
    m = 1 << (levels - 1)
    if width % m or height % m:
        raise ValueError(f"{width}x{height} does not divide by 2^{levels - 1}; use plan_pyramid")
    return [(width >> lvl, height >> lvl) for lvl in range(levels)]
